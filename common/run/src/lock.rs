//! Exclusive locks on the directories a process writes (a run, an evaluation, a sweep), so that
//! two `train`, `eval` or `sweep` processes never interleave their files.
//!
//! A lock is `flock(2)` on `<dir>/.lock`, which also names its holder (pid and command line).
//! The kernel drops it when the holder exits, however it dies, so a stale lock cannot remain.
//!
//! The processes a lock holder starts to write into its directory (the launcher's actors,
//! replay and learner; `eval`'s workers) hold the lock with it ([`DirLock::share_with`]): the
//! kernel drops it only once the last of them has exited, so that a second `train` or `eval`
//! never starts while a child still finishes a snapshot, a checkpoint or a row. Every child the
//! binary starts dies with its parent ([`die_with_parent`]).

use crate::path_error::PathIoError;
use crate::run_dir::LOCK_FILE;
use std::fs::File;
use std::io::{Read, Seek, Write};
use std::os::fd::AsRawFd;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A directory lock that could not be taken.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// Another process (or the processes it started) holds it.
    #[error(
        "{} is in use by another process ({holder}, or the processes it started, still \
         finishing); wait for it to finish or stop it",
        .dir.display()
    )]
    InUse {
        /// The locked directory.
        dir: PathBuf,
        /// Who holds it, as its lock file names it (`unknown` when it names nobody).
        holder: String,
    },
    /// The directory or its lock file could not be created, opened or written.
    #[error(transparent)]
    Io(#[from] PathIoError),
}

/// `Result` of a lock operation.
pub type Result<T> = std::result::Result<T, LockError>;

/// A held lock; dropping it releases it.
#[derive(Debug)]
pub struct DirLock {
    file: File,
}

impl DirLock {
    /// Locks `dir` (creating it) for this process, or fails naming the process that holds it.
    pub fn acquire(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(PathIoError::at("creating", dir))?;
        let path = dir.join(LOCK_FILE);
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(PathIoError::at("opening", &path))?;
        // SAFETY: flock on a file descriptor this function owns; no memory is involved.
        let locked = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0;
        if !locked {
            let mut holder = String::new();
            file.read_to_string(&mut holder).ok();
            return Err(LockError::InUse {
                dir: dir.to_path_buf(),
                holder: match holder.trim() {
                    "" => "unknown".to_string(),
                    h => h.to_string(),
                },
            });
        }
        // args_os: a path that is not UTF-8 on the command line is named lossily, not a panic
        let command: Vec<String> = std::env::args_os()
            .map(|a| a.to_string_lossy().into_owned())
            .collect();
        file.set_len(0)
            .and_then(|()| file.rewind())
            .and_then(|()| write!(file, "pid {}: {}", std::process::id(), command.join(" ")))
            .and_then(|()| file.flush())
            .map_err(PathIoError::at("writing", &path))?;
        Ok(Self { file })
    }

    /// A second handle on this lock (the same open file, so the same lock), for a part of the
    /// program that starts children.
    pub fn try_clone(&self) -> Result<Self> {
        Ok(Self {
            file: self
                .file
                .try_clone()
                .map_err(PathIoError::at("sharing the lock", Path::new(LOCK_FILE)))?,
        })
    }

    /// Makes the process `cmd` starts hold this lock too (its file descriptor is inherited),
    /// so that the lock outlives this process until that child has exited as well.
    pub fn share_with(&self, cmd: &mut Command) {
        let fd = self.file.as_raw_fd();
        // SAFETY: the closure runs in the forked child before exec and only calls fcntl on a
        // descriptor the child inherited, which is async-signal-safe, allocating nothing.
        unsafe {
            cmd.pre_exec(move || {
                if libc::fcntl(fd, libc::F_SETFD, 0) == -1 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
    }
}

/// Makes the process `cmd` starts die (SIGTERM) when the thread that starts it ends, with its
/// process, however it ends (even killed outright): start children from a thread that lives as
/// long as they should. A parent that died before the child set this up is caught too (the
/// child then no longer has it as parent, and exits at once).
pub fn die_with_parent(cmd: &mut Command) {
    let parent = std::process::id() as libc::pid_t;
    // SAFETY: the closure runs in the forked child before exec and only calls prctl, getppid
    // and _exit, which are async-signal-safe, allocating nothing and taking no lock.
    unsafe {
        cmd.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) == -1 {
                return Err(std::io::Error::last_os_error());
            }
            if libc::getppid() != parent {
                libc::_exit(1);
            }
            Ok(())
        });
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

    /// `sleep 30`, dying with this thread and holding `lock`.
    fn bound_sleep(lock: &DirLock) -> std::process::Child {
        let mut cmd = Command::new("sleep");
        cmd.arg("30");
        die_with_parent(&mut cmd);
        lock.share_with(&mut cmd);
        cmd.spawn().unwrap()
    }

    /// Whether process `pid` has exited (gone, or a zombie nobody reaped yet).
    fn exited(pid: u32) -> bool {
        std::fs::read_to_string(format!("/proc/{pid}/stat")).map_or(true, |s| {
            s.rsplit(')')
                .next()
                .unwrap_or("")
                .trim_start()
                .starts_with('Z')
        })
    }

    #[test]
    fn a_child_holds_the_lock_until_it_exits() {
        let dir = tempfile::tempdir().unwrap();
        let lock = DirLock::acquire(dir.path()).unwrap();
        let mut child = bound_sleep(&lock);
        drop(lock);
        let err = DirLock::acquire(dir.path()).unwrap_err().to_string();
        assert!(err.contains("processes it started"), "{err}");
        child.kill().unwrap();
        child.wait().unwrap();
        acquire_soon(dir.path());
    }

    /// Acquires the lock of `dir`, which must come free within seconds: a child that another
    /// test forked while this lock's file was open holds a copy of it until it executes its
    /// program (its descriptors close on exec), later on a loaded machine.
    fn acquire_soon(dir: &Path) -> DirLock {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        loop {
            match DirLock::acquire(dir) {
                Ok(lock) => return lock,
                Err(e) if std::time::Instant::now() > deadline => panic!("{e}"),
                Err(_) => std::thread::sleep(std::time::Duration::from_millis(20)),
            }
        }
    }

    /// The folder [`intermediate_parent`] locks, set by the test that starts it.
    const PARENT_DIR: &str = "CTXRACE_TEST_PARENT_LOCK_DIR";

    #[test]
    #[ignore = "the parent that a_child_dies_with_its_killed_parent starts and kills"]
    fn intermediate_parent() {
        let Some(dir) = std::env::var_os(PARENT_DIR) else {
            return;
        };
        let lock = DirLock::acquire(Path::new(&dir)).unwrap();
        let mut child = bound_sleep(&lock);
        println!("child {}", child.id());
        std::io::stdout().flush().unwrap();
        // killed by the test long before the child ends
        child.wait().unwrap();
    }

    #[test]
    fn a_child_dies_with_its_killed_parent_and_then_frees_the_lock() {
        use std::io::BufRead;
        let dir = tempfile::tempdir().unwrap();
        let mut parent = Command::new(std::env::current_exe().unwrap())
            .args(["--exact", "lock::tests::intermediate_parent", "--ignored"])
            .args(["--nocapture", "--test-threads=1"])
            .env(PARENT_DIR, dir.path())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let child: u32 = std::io::BufReader::new(parent.stdout.take().unwrap())
            .lines()
            .map_while(|l| l.ok())
            // libtest prints the test's name before it, on the same line
            .find_map(|l| {
                l.rsplit_once("child ")
                    .and_then(|(_, p)| p.trim().parse().ok())
            })
            .unwrap();
        assert!(!exited(child));
        // held by the parent and its child
        assert!(DirLock::acquire(dir.path()).is_err());
        parent.kill().unwrap();
        parent.wait().unwrap();
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while !exited(child) && std::time::Instant::now() < deadline {
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let dead = exited(child);
        if !dead {
            // SAFETY: signals the test's own stray `sleep`.
            unsafe { libc::kill(child as libc::pid_t, libc::SIGKILL) };
        }
        assert!(dead, "the child outlived its killed parent");
        acquire_soon(dir.path());
    }
}
