//! The files of a run directory, named once for the processes that write them and the commands
//! that read them (`train` and its roles write, `eval`, `report`, `sweep` and `race` read).
//!
//! ```text
//! runs/<algo>-<track>-<rivals>r-s<seed>/   (run_name)
//!   config.toml            CONFIG_FILE: the experiment as trained (eval and report reuse it)
//!   .lock                  LOCK_FILE: held by the process writing the directory
//!   status.json            STATUS_FILE: the launcher's live counters
//!   learner-status.json    LEARNER_STATUS: the learner's transport counters, each second
//!   replay-status.json     REPLAY_REPORT: the replay's final counters
//!   replay-streams.json    REPLAY_STREAMS: the steps stored, surplus and rejected of each actor
//!   replay.snapshot        REPLAY_SNAPSHOT: the replay buffer, for restarts
//!   actors/actor-<id>-<n>.json   ACTOR_REPORTS: each actor incarnation's final counters
//!   logs/<role>.log        LOGS: each process's log
//!   episodes.csv           TRAINING_EPISODES: one row per finished training episode
//!   training_masks.csv     TRAINING_MASKS: cMask's mean mask per training episode (inline)
//!   metrics.csv, metrics.jsonl   METRICS_CSV, METRICS_JSONL: the learner's metrics
//!   events.out.tfevents.*  TensorBoard event files
//!   checkpoints/step-<N>/  CHECKPOINTS: policy.safetensors (POLICY_FILE), agent.toml
//!                          (AGENT_FILE), the optimisers and the counters
//!   checkpoints/best/      BEST_DIR: the policy of the best training return
//!   resume/                RESUME_DIR: a single-process run's newest resume point
//!   eval/                  EVAL_DIR: meta.json (EVAL_META), job.json (EVAL_JOB), episodes.csv
//!                          (EVAL_EPISODES), contexts.csv and contexts.json (EVAL_CONTEXTS_*)
//! ```
//!
//! A run directory may be shared, so nothing planted in it is trusted: whole files are written
//! with [`write_atomic`] (a temporary created exclusively, renamed over the file), logs are
//! opened with [`open_append`], and files read by a name from another file with
//! [`read_regular`] or [`open_regular`]; none of them follows a link or waits on a FIFO.

/// The name of a run: `<algo>-<track>-<rivals>r-s<seed>`, e.g. `cmask-f1_esp-3r-s0` (its
/// directory under `runs/` unless another is given).
pub fn run_name(cfg: &ExperimentConfig) -> String {
    format!(
        "{}-{}-{}r-s{}",
        cfg.agent.algo,
        cfg.track.replace([':', '/'], "_"),
        cfg.race.rivals,
        cfg.train.seed
    )
}

/// The experiment as trained.
pub const CONFIG_FILE: &str = "config.toml";
/// The lock file of a directory being written.
pub const LOCK_FILE: &str = ".lock";
/// The launcher's live status.
pub const STATUS_FILE: &str = "status.json";
/// The learner's transport counters of its current start, rewritten each second (the launcher
/// copies them into [`STATUS_FILE`]).
pub const LEARNER_STATUS: &str = "learner-status.json";
/// What the replay's current start took of each actor, and of the run's env-step budget
/// ([`crate::results::ReplayStreams`]), rewritten each second: the launcher restarts an actor
/// that steps while none of its steps arrive, and stops the actors once the budget is stored.
pub const REPLAY_STREAMS: &str = "replay-streams.json";
/// The replay's final counters.
pub const REPLAY_REPORT: &str = "replay-status.json";
/// The replay buffer's snapshot.
pub const REPLAY_SNAPSHOT: &str = "replay.snapshot";
/// The folder of the actors' final reports.
pub const ACTOR_REPORTS: &str = "actors";
/// The folder of the processes' logs.
pub const LOGS: &str = "logs";
/// The training episodes (training curves).
pub const TRAINING_EPISODES: &str = "episodes.csv";
/// cMask's mean context mask of each training episode of a single-process run
/// ([`crate::results::TrainingMask`]), beside its `episodes.csv` row.
pub const TRAINING_MASKS: &str = "training_masks.csv";
/// The learner's metrics as CSV.
pub const METRICS_CSV: &str = "metrics.csv";
/// The learner's metrics as JSON lines.
pub const METRICS_JSONL: &str = "metrics.jsonl";
/// The folder of the checkpoints.
pub const CHECKPOINTS: &str = "checkpoints";
/// A checkpoint's acting-policy weights.
pub const POLICY_FILE: &str = "policy.safetensors";
/// A checkpoint's agent configuration.
pub const AGENT_FILE: &str = "agent.toml";
/// The best checkpoint's folder, inside [`CHECKPOINTS`].
pub const BEST_DIR: &str = "best";
/// Folder of a single-process run's resume point (the learner's `resume` module).
pub const RESUME_DIR: &str = "resume";
/// The default evaluation folder of a run.
pub const EVAL_DIR: &str = "eval";
/// What an evaluation evaluated, and how.
pub const EVAL_META: &str = "meta.json";
/// The job of an evaluation in progress (to resume it).
pub const EVAL_JOB: &str = "job.json";
/// One row per evaluation episode.
pub const EVAL_EPISODES: &str = "episodes.csv";
/// One row per context of the grid.
pub const EVAL_CONTEXTS_CSV: &str = "contexts.csv";
/// The same as JSON.
pub const EVAL_CONTEXTS_JSON: &str = "contexts.json";

use ctxrace_config::ExperimentConfig;
use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
use std::path::Path;

/// Writes `bytes` to `path` atomically and without following links: into a temporary file
/// created exclusively (`O_EXCL`, a fresh random name) beside `path`, flushed to disk, then
/// renamed over `path` (which replaces a link planted there instead of writing through it), and
/// the folder flushed. A reader sees the old file or the new one, never half of one.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomic_with(path, |_, file| file.write_all(bytes))
}

/// Writes `path` atomically and without following links as [`write_atomic`] does, through
/// `write`, for what streams its output (a CSV, an animation, a picture a library draws to a
/// path): `write` fills the temporary file, given as its path (which ends in `path`'s
/// extension) and open; it is renamed over `path` only once `write` succeeded, else removed,
/// leaving `path` as it was.
pub fn write_atomic_with<E: From<std::io::Error>>(
    path: &Path,
    write: impl FnOnce(&Path, &mut File) -> Result<(), E>,
) -> Result<(), E> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let suffix = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    let mut tmp = tempfile::Builder::new()
        .prefix(".tmp-")
        .suffix(&suffix)
        .permissions(std::fs::Permissions::from_mode(0o666))
        .tempfile_in(dir)?;
    let tmp_path = tmp.path().to_path_buf();
    write(&tmp_path, tmp.as_file_mut())?;
    tmp.as_file().sync_all()?;
    tmp.persist(path).map_err(|e| e.error)?;
    File::open(dir)?.sync_all()?;
    Ok(())
}

/// Puts the folder `new` in place of `target` in one step: where `target` exists the two are
/// exchanged (Linux's `renameat2(RENAME_EXCHANGE)`, so that a crash at any moment leaves either
/// the old folder or the new one at `target`, never neither or a half-removed one) and the old
/// contents, now at `new`, are removed; elsewhere `new` is renamed to `target`. A file system
/// that cannot exchange gets the old folder removed first.
pub fn replace_dir(new: &Path, target: &Path) -> std::io::Result<()> {
    use std::os::unix::ffi::OsStrExt;
    if target.symlink_metadata().is_err() {
        return std::fs::rename(new, target);
    }
    let c = |p: &Path| {
        std::ffi::CString::new(p.as_os_str().as_bytes())
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))
    };
    let (from, to) = (c(new)?, c(target)?);
    // SAFETY: both paths are NUL-terminated strings that live across the call; AT_FDCWD makes
    // them relative to the working directory, as `std::fs::rename`'s are.
    let done = unsafe {
        libc::renameat2(
            libc::AT_FDCWD,
            from.as_ptr(),
            libc::AT_FDCWD,
            to.as_ptr(),
            libc::RENAME_EXCHANGE,
        )
    };
    if done != 0 {
        let e = std::io::Error::last_os_error();
        if !matches!(e.raw_os_error(), Some(libc::EINVAL | libc::ENOSYS)) {
            return Err(e);
        }
        remove_path(target)?;
        return std::fs::rename(new, target);
    }
    remove_path(new)
}

/// Removes the folder or file at `path` (a link itself, never what it points to).
pub fn remove_path(path: &Path) -> std::io::Result<()> {
    match path.symlink_metadata() {
        Ok(m) if m.is_dir() => std::fs::remove_dir_all(path),
        _ => std::fs::remove_file(path),
    }
}

/// Opens `path` for appending, creating it, but only as a regular file: a link planted at
/// `path` is refused rather than followed, and a FIFO is refused rather than waited on.
pub fn open_append(path: &Path) -> std::io::Result<File> {
    regular(
        OpenOptions::new()
            .create(true)
            .append(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
            .open(path),
        path,
    )
}

/// Opens `path` for reading only if it is a regular file: a link, a device or a FIFO (without
/// waiting on it) is refused with an error naming `path`.
pub fn open_regular(path: &Path) -> std::io::Result<File> {
    regular(
        OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
            .open(path),
        path,
    )
}

/// Reads the regular file `path` ([`open_regular`]) whole, refusing a file larger than
/// `max_bytes` before reading any of it.
pub fn read_regular(path: &Path, max_bytes: u64) -> std::io::Result<Vec<u8>> {
    let file = open_regular(path)?;
    let len = file.metadata()?.len();
    if len > max_bytes {
        return Err(std::io::Error::other(format!(
            "{} holds {len} bytes, more than the {max_bytes} expected",
            path.display()
        )));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(max_bytes.saturating_add(1))
        .read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max_bytes {
        return Err(std::io::Error::other(format!(
            "{} grew past {max_bytes} bytes while being read",
            path.display()
        )));
    }
    Ok(bytes)
}

/// The file `opened` if it is a regular file; a clear error naming `path` otherwise.
fn regular(opened: std::io::Result<File>, path: &Path) -> std::io::Result<File> {
    let file = opened.map_err(|e| match e.raw_os_error() {
        Some(libc::ELOOP) => std::io::Error::other(format!(
            "{} is a symbolic link; ctxrace neither reads nor writes a run's files through \
             links: replace it with the file itself",
            path.display()
        )),
        Some(libc::ENXIO) => not_regular(path),
        _ => e,
    })?;
    if !file.metadata()?.is_file() {
        return Err(not_regular(path));
    }
    Ok(file)
}

fn not_regular(path: &Path) -> std::io::Error {
    std::io::Error::other(format!(
        "{} is not a regular file (a FIFO, device or folder); remove it",
        path.display()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_names_carry_every_axis_of_the_paper_matrix() {
        let mut cfg = ExperimentConfig::default();
        cfg.race.rivals = 3;
        cfg.train.seed = 4;
        assert_eq!(run_name(&cfg), "dreamerv3-f1_esp-3r-s4");
        cfg.track = "generated:7".into();
        cfg.agent.algo = ctxrace_config::AlgoKind::Sac;
        cfg.race.rivals = 1;
        assert_eq!(run_name(&cfg), "sac-generated_7-1r-s4");
    }

    #[test]
    fn a_link_planted_at_the_path_is_replaced_not_written_through() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("target");
        std::fs::write(&target, "untouched").unwrap();
        let path = dir.path().join(STATUS_FILE);
        std::os::unix::fs::symlink(&target, &path).unwrap();
        write_atomic(&path, b"new").unwrap();
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "untouched");
        assert!(!path.symlink_metadata().unwrap().is_symlink());
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        // nothing but the file, its old target and no temporary is left
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }

    #[test]
    fn appending_refuses_links_and_fifos() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("target");
        std::fs::write(&target, "untouched").unwrap();
        let log = dir.path().join("learner.log");
        std::os::unix::fs::symlink(&target, &log).unwrap();
        let err = open_append(&log).unwrap_err().to_string();
        assert!(
            err.contains("symbolic link") && err.contains("learner.log"),
            "{err}"
        );
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "untouched");
        let fifo = dir.path().join("fifo.log");
        make_fifo(&fifo);
        let err = open_append(&fifo).unwrap_err().to_string();
        assert!(err.contains("not a regular file"), "{err}");
        let mut file = open_append(&dir.path().join("fresh.log")).unwrap();
        file.write_all(b"line\n").unwrap();
    }

    #[test]
    fn reading_refuses_links_fifos_devices_and_oversized_files_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let zero = dir.path().join("zero");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        let err = read_regular(&zero, 1 << 20).unwrap_err().to_string();
        assert!(err.contains("symbolic link"), "{err}");
        let err = read_regular(Path::new("/dev/zero"), 1 << 20)
            .unwrap_err()
            .to_string();
        assert!(err.contains("not a regular file"), "{err}");
        let fifo = dir.path().join("fifo");
        make_fifo(&fifo);
        let err = read_regular(&fifo, 1 << 20).unwrap_err().to_string();
        assert!(err.contains("not a regular file"), "{err}");
        let big = dir.path().join("big");
        std::fs::write(&big, vec![0u8; 100]).unwrap();
        let err = read_regular(&big, 99).unwrap_err().to_string();
        assert!(err.contains("100 bytes"), "{err}");
        assert_eq!(read_regular(&big, 100).unwrap().len(), 100);
    }

    /// Makes a FIFO at `path`.
    fn make_fifo(path: &Path) {
        let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: mkfifo reads the NUL-terminated path `c` owns, nothing else.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    }
}
