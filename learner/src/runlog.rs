//! The training-metrics log of a run directory: one row per logging interval in
//! `metrics.jsonl` (every key), `metrics.csv` (the keys of the first row, in order) and a
//! TensorBoard event file (every key as a scalar at the row's `grad_steps`).

use crate::tensorboard::EventWriter;
use crate::Metrics;
use anyhow::{Context as _, Result};
use ctxrace_common::run_dir::{open_append, METRICS_CSV, METRICS_JSONL};
use std::fs::File;
use std::io::Write;
use std::path::Path;

/// Appends training-interval rows to `metrics.jsonl`, `metrics.csv` and an event file.
pub struct MetricsLog {
    jsonl: File,
    csv: File,
    columns: Option<Vec<String>>,
    events: EventWriter,
}

impl MetricsLog {
    /// Opens (appending) the logs in `run_dir`, with a new event file for the process `role`.
    pub fn open(run_dir: &Path, role: &str) -> Result<Self> {
        let open = |name: &str| {
            let path = run_dir.join(name);
            open_append(&path).with_context(|| format!("opening {}", path.display()))
        };
        let csv_path = run_dir.join(METRICS_CSV);
        let columns = std::fs::read_to_string(&csv_path).ok().and_then(|t| {
            t.lines()
                .next()
                .map(|h| h.split(',').map(String::from).collect())
        });
        Ok(Self {
            jsonl: open(METRICS_JSONL)?,
            csv: open("metrics.csv")?,
            columns,
            events: EventWriter::create(run_dir, role)?,
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
        let step = row.get("grad_steps").copied().unwrap_or(0.0) as u64;
        self.events
            .scalars(step, row.iter().map(|(k, v)| (k.as_str(), *v)))?;
        self.events.flush()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_keep_the_first_header_across_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let row = |a: f64| Metrics::from([("a".into(), a), ("b".into(), 2.0)]);
        MetricsLog::open(dir.path(), "a")
            .unwrap()
            .write(&row(1.0))
            .unwrap();
        let mut log = MetricsLog::open(dir.path(), "b").unwrap();
        log.write(&Metrics::from([("b".into(), 3.0), ("c".into(), 4.0)]))
            .unwrap();
        let csv = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
        assert_eq!(csv, "a,b\n1,2\n,3\n");
        let jsonl = std::fs::read_to_string(dir.path().join("metrics.jsonl")).unwrap();
        assert_eq!(jsonl.lines().count(), 2);
        assert!(jsonl.contains("\"c\":4.0"));
        let events = crate::tensorboard::event_files(dir.path());
        assert_eq!(events.len(), 2);
        let scalars = crate::tensorboard::read_scalars(&events[1]).unwrap();
        assert_eq!(scalars.len(), 2, "{scalars:?}");
    }
}
