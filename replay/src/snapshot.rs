//! Replay snapshots: the buffer and the rate limiter's counters in one versioned little-endian
//! file ending in a CRC-32, written atomically (temporary file, fsync, rename, folder fsync).
//! Only the steps held are written (oldest first), so a snapshot's size follows the fill, not
//! the capacity. Encoding ([`encode_snapshot`]) is separate from writing ([`write_encoded`]), so
//! that the replay loop pauses only for the copy and writes on another thread.

use crate::buffer::{ReplayBuffer, Stream};
use ctxrace_run::run_dir::write_atomic;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

/// Why a replay snapshot could not be written or restored; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    /// The snapshot could not be written.
    #[error("writing replay snapshot {}", .path.display())]
    Write {
        /// The snapshot file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The thread writing a snapshot in the background panicked.
    #[error("the snapshot writer thread panicked")]
    WriterPanicked,
    /// The snapshot could not be read back, or is of another run.
    #[error("restoring replay snapshot {}", .path.display())]
    Restore {
        /// The snapshot file.
        path: PathBuf,
        /// What is wrong with it.
        #[source]
        source: SnapshotDamage,
    },
}

/// What is wrong with a snapshot file that cannot be restored.
#[derive(Debug, thiserror::Error)]
pub enum SnapshotDamage {
    /// It could not be opened or read.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// It is shorter than a header.
    #[error("{file_len} bytes, shorter than a snapshot header: truncated or corrupt")]
    Short {
        /// Its length.
        file_len: u64,
    },
    /// Its bytes do not match its trailing checksum.
    #[error("checksum {computed:#010x}, file says {stored:#010x}: truncated or corrupt")]
    Checksum {
        /// The checksum of its bytes.
        computed: u32,
        /// The checksum it ends with.
        stored: u32,
    },
    /// It does not start as a snapshot does.
    #[error("not a ctxrace replay snapshot (bad magic)")]
    Magic,
    /// It was written in another layout.
    #[error("snapshot version {version}, this build reads {SNAPSHOT_VERSION}")]
    Version {
        /// Its layout version.
        version: u32,
    },
    /// It holds a buffer of another shape.
    #[error(
        "the snapshot holds {held}, the run has {expected}: a snapshot of another run or \
         configuration"
    )]
    Shape {
        /// The shape it holds.
        held: SnapshotShape,
        /// The run's.
        expected: SnapshotShape,
    },
    /// A stream longer than its capacity or the file.
    #[error("stream of {len} steps does not fit capacity {cap} or the file: truncated or corrupt")]
    Stream {
        /// Steps the stream says it holds.
        len: usize,
        /// Steps a stream holds at most.
        cap: usize,
    },
    /// Bytes after the last stream.
    #[error("{budget} bytes beyond the streams: corrupt")]
    Trailing {
        /// Bytes left over.
        budget: u64,
    },
    /// The bytes read differ from those checked (the file changed while it was read).
    #[error("checksum {computed:#010x}, file says {stored:#010x}: corrupt")]
    Changed {
        /// The checksum of the bytes read.
        computed: u32,
        /// The checksum it ends with.
        stored: u32,
    },
}

const MAGIC: &[u8; 8] = b"CTXRPLY\0";
/// Snapshot layout version; bump on any change.
pub const SNAPSHOT_VERSION: u32 = 3;
const HEADER_BYTES: u64 = 8 + 4 * 4 + 8 * 4;
const STREAM_HEADER_BYTES: u64 = 8 * 2;

/// What a snapshot restores besides the buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LimiterCounts {
    /// Steps inserted.
    pub inserts: u64,
    /// Steps sampled.
    pub samples: u64,
}

/// Writes `buffer` and `counts` to `path` atomically.
pub fn write_snapshot(
    path: &Path,
    buffer: &ReplayBuffer,
    counts: LimiterCounts,
) -> Result<(), SnapshotError> {
    write_encoded(path, encode_snapshot(buffer, counts))
}

/// The snapshot of `buffer` and `counts` as bytes, without its trailing checksum: the part that
/// needs the buffer, quick enough for the replay loop; [`write_encoded`] does the rest, off it.
pub fn encode_snapshot(buffer: &ReplayBuffer, counts: LimiterCounts) -> Vec<u8> {
    let (o, a) = (buffer.obs_dim, buffer.act_dim);
    let per_step = 4 * (o + a + 1 + 2 + 2) + 1 + 8;
    let steps: usize = buffer.streams.iter().map(|s| s.len).sum();
    let size = HEADER_BYTES as usize
        + buffer.streams.len() * STREAM_HEADER_BYTES as usize
        + steps * per_step
        + 4;
    let mut w = Vec::with_capacity(size);
    w.extend_from_slice(MAGIC);
    let cap = buffer.streams.first().map_or(0, |s| s.reward.len());
    for v in [
        SNAPSHOT_VERSION,
        o as u32,
        a as u32,
        buffer.streams.len() as u32,
    ] {
        w.extend_from_slice(&v.to_le_bytes());
    }
    for v in [cap as u64, buffer.inserted, counts.inserts, counts.samples] {
        w.extend_from_slice(&v.to_le_bytes());
    }
    for s in &buffer.streams {
        for v in [s.len as u64, s.segment] {
            w.extend_from_slice(&v.to_le_bytes());
        }
        for i in 0..s.len {
            let k = s.slot(i);
            for part in [
                &s.obs[k * o..(k + 1) * o],
                &s.action[k * a..(k + 1) * a],
                &s.reward[k..k + 1],
                &s.context[k * 2..k * 2 + 2],
                &s.mask[k * 2..k * 2 + 2],
            ] {
                for v in part {
                    w.extend_from_slice(&v.to_le_bytes());
                }
            }
            w.push(s.flags[k]);
            w.extend_from_slice(&s.segments[k].to_le_bytes());
        }
    }
    w
}

/// Appends the CRC-32 to an [`encode_snapshot`] and writes it to `path` atomically
/// ([`write_atomic`]: a temporary file created exclusively, fsynced, renamed over the old
/// snapshot, the folder fsynced).
pub fn write_encoded(path: &Path, mut bytes: Vec<u8>) -> Result<(), SnapshotError> {
    let crc = crc32fast::hash(&bytes);
    bytes.extend_from_slice(&crc.to_le_bytes());
    write_atomic(path, &bytes).map_err(|source| SnapshotError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// Snapshots written on a thread of their own, so that the replay loop pauses only to encode.
#[derive(Default)]
pub struct BackgroundWriter {
    job: Option<std::thread::JoinHandle<Result<(), SnapshotError>>>,
}

impl BackgroundWriter {
    /// A write is still running.
    pub fn busy(&self) -> bool {
        self.job.as_ref().is_some_and(|j| !j.is_finished())
    }

    /// Starts writing `bytes` ([`encode_snapshot`]) to `path` once the previous write is done;
    /// a failure of the previous write is returned here.
    pub fn start(&mut self, path: PathBuf, bytes: Vec<u8>) -> Result<(), SnapshotError> {
        self.wait()?;
        self.job = Some(std::thread::spawn(move || write_encoded(&path, bytes)));
        Ok(())
    }

    /// Waits for the running write, if any, and returns its result.
    pub fn wait(&mut self) -> Result<(), SnapshotError> {
        match self.job.take() {
            Some(job) => job.join().map_err(|_| SnapshotError::WriterPanicked)?,
            None => Ok(()),
        }
    }
}

/// The shape of a replay buffer, which a snapshot must match to be restored into it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SnapshotShape {
    /// Streams (one per actor).
    pub actors: usize,
    /// Steps each stream holds at most.
    pub stream_capacity: usize,
    /// Observation size.
    pub obs_dim: usize,
    /// Action size.
    pub act_dim: usize,
}

impl SnapshotShape {
    /// The shape of `buffer`.
    pub fn of(buffer: &ReplayBuffer) -> Self {
        Self {
            actors: buffer.streams.len(),
            stream_capacity: buffer.streams.first().map_or(0, Stream::cap),
            obs_dim: buffer.obs_dim,
            act_dim: buffer.act_dim,
        }
    }

    /// The shape [`ReplayBuffer::new`] gives a buffer of these sizes, without making it.
    pub fn of_new(capacity: usize, actors: usize, obs_dim: usize, act_dim: usize) -> Self {
        Self {
            actors: actors.max(1),
            stream_capacity: crate::buffer::stream_capacity(capacity, actors),
            obs_dim,
            act_dim,
        }
    }
}

impl std::fmt::Display for SnapshotShape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} actors x {} steps, obs_dim {}, act_dim {}",
            self.actors, self.stream_capacity, self.obs_dim, self.act_dim
        )
    }
}

/// Reads a snapshot that must have the shape `expected` (the run's buffer): the header is
/// checked against it before anything is sized from the header; any damage (bad magic,
/// version, sizes, checksum) or another shape is an error naming the file.
pub fn read_snapshot(
    path: &Path,
    expected: SnapshotShape,
) -> Result<(ReplayBuffer, LimiterCounts), SnapshotError> {
    read(path, expected).map_err(|source| SnapshotError::Restore {
        path: path.to_path_buf(),
        source,
    })
}

/// Checks the file's trailing CRC-32 against all bytes before it, reading it once without
/// holding it, so that nothing is sized from a header that may be damaged.
fn verify_checksum(path: &Path, file_len: u64) -> Result<(), SnapshotDamage> {
    if file_len < HEADER_BYTES + 4 {
        return Err(SnapshotDamage::Short { file_len });
    }
    let mut r = BufReader::with_capacity(1 << 20, File::open(path)?);
    let mut hasher = crc32fast::Hasher::new();
    let mut left = file_len - 4;
    let mut buf = vec![0u8; 1 << 20];
    while left > 0 {
        let n = (left as usize).min(buf.len());
        r.read_exact(&mut buf[..n])?;
        hasher.update(&buf[..n]);
        left -= n as u64;
    }
    let mut crc = [0u8; 4];
    r.read_exact(&mut crc)?;
    let (stored, computed) = (u32::from_le_bytes(crc), hasher.finalize());
    if stored != computed {
        return Err(SnapshotDamage::Checksum { computed, stored });
    }
    Ok(())
}

/// Checks that the snapshot at `path` would restore into a buffer of shape `expected`: its
/// checksum, magic, version and shape, without reading its steps into memory (what a launcher
/// checks before it starts any process).
pub fn check_snapshot(path: &Path, expected: SnapshotShape) -> Result<(), SnapshotError> {
    open_checked(path, expected)
        .map(drop)
        .map_err(|source| SnapshotError::Restore {
            path: path.to_path_buf(),
            source,
        })
}

/// The header of a snapshot whose checksum holds and whose shape is `expected`.
struct Header {
    /// The file's length.
    file_len: u64,
    /// Steps the buffer had inserted.
    inserted: u64,
    /// The rate limiter's counts.
    counts: LimiterCounts,
}

/// Opens the snapshot at `path`, verifies its checksum and reads its header, which must be of
/// the shape `expected`; returns the reader positioned at the first stream.
fn open_checked(
    path: &Path,
    expected: SnapshotShape,
) -> Result<(Hashing<BufReader<File>>, Header), SnapshotDamage> {
    let file = File::open(path)?;
    let file_len = file.metadata()?.len();
    verify_checksum(path, file_len)?;
    let mut r = Hashing {
        inner: BufReader::with_capacity(1 << 20, file),
        hasher: crc32fast::Hasher::new(),
    };
    let mut magic = [0u8; 8];
    r.read_exact(&mut magic)?;
    if &magic != MAGIC {
        return Err(SnapshotDamage::Magic);
    }
    let version = r.u32()?;
    if version != SNAPSHOT_VERSION {
        return Err(SnapshotDamage::Version { version });
    }
    let (obs_dim, act_dim, actors) = (r.u32()? as u64, r.u32()? as u64, r.u32()? as u64);
    let (cap, inserted, inserts, samples) = (r.u64()?, r.u64()?, r.u64()?, r.u64()?);
    let held = SnapshotShape {
        actors: usize::try_from(actors).unwrap_or(usize::MAX),
        stream_capacity: usize::try_from(cap).unwrap_or(usize::MAX),
        obs_dim: obs_dim as usize,
        act_dim: act_dim as usize,
    };
    if held != expected {
        return Err(SnapshotDamage::Shape { held, expected });
    }
    let counts = LimiterCounts { inserts, samples };
    Ok((
        r,
        Header {
            file_len,
            inserted,
            counts,
        },
    ))
}

fn read(
    path: &Path,
    expected: SnapshotShape,
) -> Result<(ReplayBuffer, LimiterCounts), SnapshotDamage> {
    let (mut r, h) = open_checked(path, expected)?;
    let (file_len, inserted, actors) = (h.file_len, h.inserted, expected.actors as u64);
    let (o, a, cap) = (expected.obs_dim, expected.act_dim, expected.stream_capacity);
    let per_step = 4 * (o + a + 1 + 2 + 2) as u64 + 1 + 8;
    // every stream's steps must fit in what is left of the file before they are allocated
    let mut budget = file_len.saturating_sub(HEADER_BYTES + 4);
    let mut streams = Vec::with_capacity(actors as usize);
    for _ in 0..actors {
        let (len, segment) = (r.u64()? as usize, r.u64()?);
        let bytes = (len as u64).saturating_mul(per_step);
        if len > cap || bytes.saturating_add(STREAM_HEADER_BYTES) > budget {
            return Err(SnapshotDamage::Stream { len, cap });
        }
        budget -= bytes + STREAM_HEADER_BYTES;
        let mut s = Stream::new(cap, o, a);
        for k in 0..len {
            s.obs[k * o..(k + 1) * o].copy_from_slice(&r.f32s(o)?);
            s.action[k * a..(k + 1) * a].copy_from_slice(&r.f32s(a)?);
            s.reward[k] = r.f32s(1)?[0];
            s.context[k * 2..k * 2 + 2].copy_from_slice(&r.f32s(2)?);
            s.mask[k * 2..k * 2 + 2].copy_from_slice(&r.f32s(2)?);
            let mut flag = [0u8; 1];
            r.read_exact(&mut flag)?;
            s.flags[k] = flag[0];
            s.segments[k] = r.u64()?;
        }
        s.len = len;
        s.head = len % cap;
        s.segment = segment;
        streams.push(s);
    }
    if budget != 0 {
        return Err(SnapshotDamage::Trailing { budget });
    }
    let computed = r.hasher.clone().finalize();
    let mut crc = [0u8; 4];
    r.inner.read_exact(&mut crc)?;
    let stored = u32::from_le_bytes(crc);
    if stored != computed {
        return Err(SnapshotDamage::Changed { computed, stored });
    }
    Ok((
        ReplayBuffer {
            obs_dim: o,
            act_dim: a,
            streams,
            inserted,
        },
        h.counts,
    ))
}

/// A reader that hashes every byte passing through.
struct Hashing<T> {
    inner: T,
    hasher: crc32fast::Hasher,
}

impl<R: Read> Read for Hashing<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.hasher.update(&buf[..n]);
        Ok(n)
    }
}

impl<R: Read> Hashing<R> {
    fn u32(&mut self) -> std::io::Result<u32> {
        let mut b = [0u8; 4];
        self.read_exact(&mut b)?;
        Ok(u32::from_le_bytes(b))
    }

    fn u64(&mut self) -> std::io::Result<u64> {
        let mut b = [0u8; 8];
        self.read_exact(&mut b)?;
        Ok(u64::from_le_bytes(b))
    }

    fn f32s(&mut self, n: usize) -> std::io::Result<Vec<f32>> {
        let mut bytes = vec![0u8; n * 4];
        self.read_exact(&mut bytes)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::buffer::tests::payload;
    use ctxrace_config::validate::Causes;

    /// The error and its causes, as the binary prints them.
    fn causes(e: SnapshotError) -> String {
        Causes(&e).to_string()
    }

    #[test]
    fn round_trip_and_corruption() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("replay.snap");
        let mut b = ReplayBuffer::new(20, 2, 2, 1);
        let v: Vec<f32> = (0..13).map(|v| v as f32).collect();
        b.insert_chunk(0, &payload(0.0, &v, &[0], &[12]), true);
        b.insert_chunk(1, &payload(1.0, &v[..3], &[0], &[]), true);
        let counts = LimiterCounts {
            inserts: 16,
            samples: 40,
        };
        write_snapshot(&path, &b, counts).unwrap();
        let shape = SnapshotShape::of(&b);
        let (back, c) = read_snapshot(&path, shape).unwrap();
        assert_eq!(c, counts);
        // the same steps in the same order (the ring may start elsewhere)
        let again = dir.path().join("again.snap");
        write_snapshot(&again, &back, counts).unwrap();
        assert_eq!(
            std::fs::read(&again).unwrap(),
            std::fs::read(&path).unwrap()
        );
        let sample = |buf: &ReplayBuffer| {
            use rand::SeedableRng;
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
            buf.sample_sequences(4, 3, &mut rng)
        };
        assert_eq!(sample(&back), sample(&b));
        assert!(sample(&b).is_some());
        // the two snapshots and no temporary
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);

        let mut bytes = std::fs::read(&path).unwrap();
        let mid = bytes.len() / 2;
        bytes[mid] ^= 0x40;
        std::fs::write(&path, &bytes).unwrap();
        let err = causes(read_snapshot(&path, shape).unwrap_err());
        assert!(
            err.contains("replay.snap") && err.contains("corrupt"),
            "{err}"
        );

        // a header claiming another shape, its checksum recomputed, is refused before anything
        // is sized from it (obs_dim 2^31 - 1 would be 2^31 floats per step)
        let mut lying = std::fs::read(&again).unwrap();
        lying.truncate(lying.len() - 4);
        lying[12..16].copy_from_slice(&0x7fff_ffffu32.to_le_bytes());
        let crc = crc32fast::hash(&lying);
        lying.extend_from_slice(&crc.to_le_bytes());
        std::fs::write(&path, &lying).unwrap();
        let err = causes(read_snapshot(&path, shape).unwrap_err());
        assert!(
            err.contains("replay.snap")
                && err.contains("obs_dim 2147483647")
                && err.contains("another run"),
            "{err}"
        );
        // so is one of another run's shape
        let other = SnapshotShape {
            obs_dim: 3,
            ..shape
        };
        let err = causes(read_snapshot(&again, other).unwrap_err());
        assert!(
            err.contains("obs_dim 2, act_dim 1") && err.contains("obs_dim 3"),
            "{err}"
        );

        // a header claiming a huge capacity is caught by the checksum before anything is sized
        let mut huge = std::fs::read(&again).unwrap();
        huge[8 + 4 * 4 + 7] = 0x7f;
        std::fs::write(&path, &huge).unwrap();
        let err = causes(read_snapshot(&path, shape).unwrap_err());
        assert!(err.contains("checksum") && err.contains("corrupt"), "{err}");

        std::fs::write(&path, &bytes[..100]).unwrap();
        let err = causes(read_snapshot(&path, shape).unwrap_err());
        assert!(
            err.contains("replay.snap") && err.contains("truncated"),
            "{err}"
        );

        std::fs::write(&path, b"garbage").unwrap();
        assert!(read_snapshot(&path, shape).is_err());
        assert!(read_snapshot(&dir.path().join("missing"), shape).is_err());
    }
}
