//! The training-metrics log of a run directory: one row per logging interval in
//! `metrics.jsonl` (every key) and `metrics.csv` (the keys of the first row, in order).

use crate::Metrics;
use anyhow::{Context as _, Result};
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::Path;

/// Appends training-interval rows to `metrics.jsonl` and `metrics.csv`.
pub struct MetricsLog {
    jsonl: File,
    csv: File,
    columns: Option<Vec<String>>,
}

impl MetricsLog {
    /// Opens (appending) the logs in `run_dir`.
    pub fn open(run_dir: &Path) -> Result<Self> {
        let open = |name: &str| {
            let path = run_dir.join(name);
            OpenOptions::new()
                .create(true)
                .append(true)
                .open(&path)
                .with_context(|| format!("opening {}", path.display()))
        };
        let csv_path = run_dir.join("metrics.csv");
        let columns = std::fs::read_to_string(&csv_path).ok().and_then(|t| {
            t.lines()
                .next()
                .map(|h| h.split(',').map(String::from).collect())
        });
        Ok(Self {
            jsonl: open("metrics.jsonl")?,
            csv: open("metrics.csv")?,
            columns,
        })
    }

    /// Appends one row.
    pub fn write(&mut self, row: &Metrics) -> Result<()> {
        serde_json::to_writer(&mut self.jsonl, row)?;
        self.jsonl.write_all(b"\n")?;
        let columns = match &self.columns {
            Some(c) => c,
            None => {
                let c: Vec<String> = row.keys().cloned().collect();
                writeln!(self.csv, "{}", c.join(","))?;
                self.columns.insert(c)
            }
        };
        let cells: Vec<String> = columns
            .iter()
            .map(|k| row.get(k).map_or(String::new(), |v| v.to_string()))
            .collect();
        writeln!(self.csv, "{}", cells.join(","))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_keep_the_first_header_across_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let row = |a: f64| Metrics::from([("a".into(), a), ("b".into(), 2.0)]);
        MetricsLog::open(dir.path())
            .unwrap()
            .write(&row(1.0))
            .unwrap();
        let mut log = MetricsLog::open(dir.path()).unwrap();
        log.write(&Metrics::from([("b".into(), 3.0), ("c".into(), 4.0)]))
            .unwrap();
        let csv = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
        assert_eq!(csv, "a,b\n1,2\n,3\n");
        let jsonl = std::fs::read_to_string(dir.path().join("metrics.jsonl")).unwrap();
        assert_eq!(jsonl.lines().count(), 2);
        assert!(jsonl.contains("\"c\":4.0"));
    }
}
