//! TensorBoard event files, so that `tensorboard --logdir runs/` shows a run's (or a sweep's)
//! curves side by side.
//!
//! A file `events.out.tfevents.<seconds>.<host>.<role>` is a sequence of records, each
//! `len (u64 LE) | masked_crc(len) | data | masked_crc(data)` with the CRC-32C masked as
//! `((c >> 15) | (c << 17)) + 0xa282ead8`; the data are `tensorflow.Event` protocol buffers: a
//! first one with `file_version = "brain.Event:2"`, then one per step whose `Summary` holds
//! `simple_value` scalars. The messages are declared here with prost's derive macros (the field
//! numbers of tensorflow/core/util/event.proto and framework/summary.proto), so no protobuf
//! compiler is needed at build time.

use prost::Message;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Why an event file could not be written or read back; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum EventFileError {
    /// The file could not be created, written or read.
    #[error("{action} {}", .path.display())]
    Io {
        /// What was being done (`"creating"`, `"writing"`, `"reading"`).
        action: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A record's framing is broken: what, and where.
    #[error("{}: {what} at byte {at}", .path.display())]
    Framing {
        /// The file.
        path: PathBuf,
        /// What is wrong (`"a record with a bad CRC"`, ...).
        what: &'static str,
        /// Where the record starts.
        at: usize,
    },
    /// A record holds no event.
    #[error("{}: an undecodable event at byte {at}", .path.display())]
    Decode {
        /// The file.
        path: PathBuf,
        /// Where the record starts.
        at: usize,
        /// prost's reason.
        #[source]
        source: prost::DecodeError,
    },
    /// The file does not start as an event file does.
    #[error("{}: does not start with the brain.Event:2 version", .0.display())]
    Version(PathBuf),
}

/// The outcome of an event-file operation.
type Result<T> = std::result::Result<T, EventFileError>;

/// An [`EventFileError::Io`] of `action` on `path`.
fn io_error(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> EventFileError {
    let path = path.to_path_buf();
    move |source| EventFileError::Io {
        action,
        path,
        source,
    }
}

/// `tensorflow.Event`, the fields ctxrace writes.
#[derive(Clone, PartialEq, prost::Message)]
struct Event {
    #[prost(double, tag = "1")]
    wall_time: f64,
    #[prost(int64, tag = "2")]
    step: i64,
    #[prost(oneof = "What", tags = "3, 5")]
    what: Option<What>,
}

/// `Event.what`.
#[derive(Clone, PartialEq, prost::Oneof)]
enum What {
    #[prost(string, tag = "3")]
    FileVersion(String),
    #[prost(message, tag = "5")]
    Summary(Summary),
}

/// `tensorflow.Summary`.
#[derive(Clone, PartialEq, prost::Message)]
struct Summary {
    #[prost(message, repeated, tag = "1")]
    value: Vec<SummaryValue>,
}

/// `tensorflow.Summary.Value` with a scalar.
#[derive(Clone, PartialEq, prost::Message)]
struct SummaryValue {
    #[prost(string, tag = "1")]
    tag: String,
    #[prost(oneof = "Scalar", tags = "2")]
    value: Option<Scalar>,
}

/// `Summary.Value.value` (a oneof, so that a scalar of 0 is still written).
#[derive(Clone, PartialEq, prost::Oneof)]
enum Scalar {
    #[prost(float, tag = "2")]
    SimpleValue(f32),
}

/// The masked CRC-32C of TFRecord framing.
fn masked_crc(bytes: &[u8]) -> u32 {
    let c = crc32c::crc32c(bytes);
    (c.rotate_right(15)).wrapping_add(0xa282_ead8)
}

/// Appends scalar events to one event file of a run directory.
pub struct EventWriter {
    file: BufWriter<File>,
    path: PathBuf,
}

impl EventWriter {
    /// A new event file in `dir` for the process `role` (e.g. `learner`).
    pub fn create(dir: &Path, role: &str) -> Result<Self> {
        let secs = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "localhost".into());
        let path = dir.join(format!(
            "events.out.tfevents.{secs}.{host}.{}.{role}",
            std::process::id()
        ));
        // a new file, never one (or a link) already there
        let file = File::create_new(&path).map_err(io_error("creating", &path))?;
        let mut w = Self {
            file: BufWriter::new(file),
            path,
        };
        w.record(&Event {
            wall_time: wall_time(),
            step: 0,
            what: Some(What::FileVersion("brain.Event:2".into())),
        })?;
        w.flush()?;
        Ok(w)
    }

    /// Writes the finite `values` as scalars at `step` (tags such as `model/loss`).
    pub fn scalars<'a>(
        &mut self,
        step: u64,
        values: impl IntoIterator<Item = (&'a str, f64)>,
    ) -> Result<()> {
        let value: Vec<SummaryValue> = values
            .into_iter()
            .filter(|(_, v)| v.is_finite())
            .map(|(tag, v)| SummaryValue {
                tag: tag.to_string(),
                value: Some(Scalar::SimpleValue(v as f32)),
            })
            .collect();
        if value.is_empty() {
            return Ok(());
        }
        self.record(&Event {
            wall_time: wall_time(),
            step: step as i64,
            what: Some(What::Summary(Summary { value })),
        })
    }

    /// Pushes what was written to the file (TensorBoard reads it live).
    pub fn flush(&mut self) -> Result<()> {
        self.file.flush().map_err(io_error("writing", &self.path))
    }

    fn record(&mut self, event: &Event) -> Result<()> {
        let data = event.encode_to_vec();
        let len = (data.len() as u64).to_le_bytes();
        let w = &mut self.file;
        w.write_all(&len)
            .and_then(|()| w.write_all(&masked_crc(&len).to_le_bytes()))
            .and_then(|()| w.write_all(&data))
            .and_then(|()| w.write_all(&masked_crc(&data).to_le_bytes()))
            .map_err(io_error("writing", &self.path))
    }
}

impl Drop for EventWriter {
    fn drop(&mut self) {
        let _ = self.file.flush();
    }
}

fn wall_time() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// One scalar read back from an event file.
#[derive(Clone, Debug, PartialEq)]
pub struct ScalarRecord {
    /// The step.
    pub step: i64,
    /// The tag.
    pub tag: String,
    /// The value.
    pub value: f32,
}

/// Every scalar of an event file, checking the framing and both CRCs of every record; the
/// file must start with the `brain.Event:2` version event.
pub fn read_scalars(path: &Path) -> Result<Vec<ScalarRecord>> {
    let bytes = std::fs::read(path).map_err(io_error("reading", path))?;
    let mut rest = &bytes[..];
    let mut out = Vec::new();
    let mut first = true;
    while !rest.is_empty() {
        let at = bytes.len() - rest.len();
        let bad = |what: &'static str| EventFileError::Framing {
            path: path.to_path_buf(),
            what,
            at,
        };
        let Some((len_bytes, tail)) = rest.split_first_chunk::<8>() else {
            return Err(bad("a truncated record header"));
        };
        let Some((crc, tail)) = tail.split_first_chunk::<4>() else {
            return Err(bad("a truncated record header"));
        };
        if u32::from_le_bytes(*crc) != masked_crc(len_bytes) {
            return Err(bad("a length with a bad CRC"));
        }
        let len = u64::from_le_bytes(*len_bytes) as usize;
        if tail.len() < len.saturating_add(4) {
            return Err(bad("a truncated record"));
        }
        let (data, tail) = tail.split_at(len);
        let Some((crc, tail)) = tail.split_first_chunk::<4>() else {
            return Err(bad("a truncated record"));
        };
        if u32::from_le_bytes(*crc) != masked_crc(data) {
            return Err(bad("a record with a bad CRC"));
        }
        let event = Event::decode(data).map_err(|source| EventFileError::Decode {
            path: path.to_path_buf(),
            at,
            source,
        })?;
        match (first, event.what) {
            (true, Some(What::FileVersion(v))) if v == "brain.Event:2" => {}
            (true, _) => return Err(EventFileError::Version(path.to_path_buf())),
            (false, Some(What::Summary(s))) => out.extend(s.value.into_iter().filter_map(|v| {
                let Some(Scalar::SimpleValue(value)) = v.value else {
                    return None;
                };
                Some(ScalarRecord {
                    step: event.step,
                    tag: v.tag,
                    value,
                })
            })),
            (false, _) => {}
        }
        first = false;
        rest = tail;
    }
    Ok(out)
}

/// The event files of a run directory.
pub fn event_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.file_name()
                        .and_then(|n| n.to_str())
                        .is_some_and(|n| n.starts_with("events.out.tfevents."))
                })
                .collect()
        })
        .unwrap_or_default();
    files.sort();
    files
}

/// The tags of every scalar in the event files of a run directory.
pub fn scalar_tags(dir: &Path) -> Result<std::collections::BTreeSet<String>> {
    let mut tags = std::collections::BTreeSet::new();
    for file in event_files(dir) {
        tags.extend(read_scalars(&file)?.into_iter().map(|r| r.tag));
    }
    Ok(tags)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scalars_round_trip_with_their_framing_checked() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = EventWriter::create(dir.path(), "learner").unwrap();
        w.scalars(10, [("model/loss", 1.5), ("zero", 0.0), ("nan", f64::NAN)])
            .unwrap();
        w.scalars(20, [("model/loss", 0.25)]).unwrap();
        drop(w);
        let files = event_files(dir.path());
        assert_eq!(files.len(), 1);
        assert!(files[0].to_str().unwrap().ends_with(".learner"));
        let got = read_scalars(&files[0]).unwrap();
        let want = [
            (10, "model/loss", 1.5),
            (10, "zero", 0.0),
            (20, "model/loss", 0.25),
        ];
        assert_eq!(got.len(), want.len(), "{got:?}");
        for (g, (step, tag, value)) in got.iter().zip(want) {
            assert_eq!((g.step, g.tag.as_str(), g.value), (step, tag, value));
        }
        // the CRC of TFRecord framing: crc32c("") is 0, masked 0xa282ead8
        assert_eq!(masked_crc(b""), 0xa282_ead8);
        // a flipped byte is caught
        let mut bytes = std::fs::read(&files[0]).unwrap();
        let last = bytes.len() - 6;
        bytes[last] ^= 1;
        std::fs::write(&files[0], &bytes).unwrap();
        assert!(read_scalars(&files[0])
            .unwrap_err()
            .to_string()
            .contains("bad CRC"));
    }
}
