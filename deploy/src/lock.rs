//! Exclusive locks on the directories a process writes (a run, an evaluation, a sweep), so that
//! two `train`, `eval` or `sweep` processes never interleave their files.
//!
//! A lock is `flock(2)` on `<dir>/.lock`, which also names its holder (pid and command line).
//! The kernel drops it when the holder exits, however it dies, so a stale lock cannot remain.

use anyhow::{bail, Context as _, Result};
use ctxrace_common::run_dir::LOCK_FILE;
use std::fs::File;
use std::io::{Read, Seek, Write};
use std::os::fd::AsRawFd;
use std::path::Path;

/// A held lock; dropping it releases it.
#[derive(Debug)]
pub struct DirLock {
    _file: File,
}

impl DirLock {
    /// Locks `dir` (creating it) for this process, or fails naming the process that holds it.
    pub fn acquire(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = dir.join(LOCK_FILE);
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .with_context(|| format!("opening {}", path.display()))?;
        // SAFETY: flock on a file descriptor this function owns; no memory is involved.
        let locked = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0;
        if !locked {
            let mut holder = String::new();
            file.read_to_string(&mut holder).ok();
            bail!(
                "{} is in use by another process ({}); wait for it to finish or stop it",
                dir.display(),
                match holder.trim() {
                    "" => "unknown",
                    h => h,
                }
            );
        }
        let command: Vec<String> = std::env::args().collect();
        file.set_len(0)?;
        file.rewind()?;
        write!(file, "pid {}: {}", std::process::id(), command.join(" "))
            .and_then(|()| file.flush())
            .with_context(|| format!("writing {}", path.display()))?;
        Ok(Self { _file: file })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_fails_naming_the_holder_until_the_first_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let first = DirLock::acquire(dir.path()).unwrap();
        // flock locks belong to the open file: a second open in this process conflicts too
        let err = DirLock::acquire(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("in use by another process")
                && err.contains(&format!("pid {}", std::process::id())),
            "{err}"
        );
        drop(first);
        DirLock::acquire(dir.path()).unwrap();
    }
}
