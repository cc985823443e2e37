//! A table of text cells, written as Markdown or as CSV.

use anyhow::Result;
use std::path::Path;

/// A header row and data rows of text cells (every row as long as the header).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Table {
    /// Column names.
    pub header: Vec<String>,
    /// Data rows.
    pub rows: Vec<Vec<String>>,
}

impl Table {
    /// An empty table with these column names.
    pub fn new<S: Into<String>>(header: impl IntoIterator<Item = S>) -> Self {
        Self {
            header: header.into_iter().map(Into::into).collect(),
            rows: Vec::new(),
        }
    }

    /// Appends a row.
    pub fn push(&mut self, row: Vec<String>) {
        debug_assert_eq!(row.len(), self.header.len(), "row width");
        self.rows.push(row);
    }

    /// The table in GitHub Markdown (first column left-aligned, the others right-aligned).
    pub fn markdown(&self) -> String {
        let line = |cells: &[String]| format!("| {} |\n", cells.join(" | "));
        let rule: Vec<String> = (0..self.header.len())
            .map(|i| if i == 0 { ":--" } else { "--:" }.to_string())
            .collect();
        let mut out = line(&self.header) + &line(&rule);
        for row in &self.rows {
            out += &line(row);
        }
        out
    }

    /// Writes the table as CSV with a header line.
    pub fn write_csv(&self, path: &Path) -> Result<()> {
        let records: Vec<&Vec<String>> = std::iter::once(&self.header).chain(&self.rows).collect();
        Ok(ctxrace_run::results::write_csv(path, &records)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table() -> Table {
        let mut t = Table::new(["algo", "PG"]);
        t.push(vec!["cmask".into(), "**0.5**".into()]);
        t
    }

    #[test]
    fn markdown_has_header_rule_and_rows() {
        assert_eq!(
            table().markdown(),
            "| algo | PG |\n| :-- | --: |\n| cmask | **0.5** |\n"
        );
    }

    #[test]
    fn csv_has_header_and_quotes_when_needed() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.csv");
        let mut t = table();
        t.push(vec!["a, b".into(), "1".into()]);
        t.write_csv(&path).unwrap();
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "algo,PG\ncmask,**0.5**\n\"a, b\",1\n"
        );
    }
}
