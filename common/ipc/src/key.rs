//! The run's key: 32 bytes drawn from the OS random source by the launcher for each run, with
//! which every process of the run tags its messages ([`crate::wire::Sealer`]).
//!
//! The key never appears in a command line, an environment variable, a file or the run folder.
//! The launcher hands it to each child start over a pipe of its own ([`RunKey::hand_to`]): it
//! writes the 32 bytes into the pipe, closes its write end, lets the child inherit the read end,
//! and names only the read end's descriptor number on the child's command line
//! ([`KEY_FD_FLAG`]). The child reads exactly 32 bytes from it as it starts and closes it
//! ([`RunKey::from_fd`]).

use crate::error::{IpcError, Result};
use std::io::{Read as _, Write as _};
use std::os::fd::{AsRawFd as _, FromRawFd as _, OwnedFd, RawFd};
use std::os::unix::process::CommandExt as _;
use std::process::Command;

/// Bytes of a run key.
pub const KEY_LEN: usize = 32;

/// The command-line flag that names the descriptor a role reads its run's key from.
pub const KEY_FD_FLAG: &str = "--key-fd";

/// A run's secret key. Its `Debug` shows no byte of it.
#[derive(Clone, PartialEq, Eq)]
pub struct RunKey([u8; KEY_LEN]);

impl std::fmt::Debug for RunKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RunKey(..)")
    }
}

impl RunKey {
    /// A fresh key from the OS random source.
    pub fn generate() -> Result<Self> {
        let mut key = [0u8; KEY_LEN];
        getrandom::fill(&mut key).map_err(|e| IpcError::Key(format!("drawing a run key: {e}")))?;
        Ok(Self(key))
    }

    /// The key of these bytes (tests and tools that make a run of their own).
    pub fn from_bytes(bytes: [u8; KEY_LEN]) -> Self {
        Self(bytes)
    }

    /// The key's bytes, for the keyed hash.
    pub(crate) fn bytes(&self) -> &[u8; KEY_LEN] {
        &self.0
    }

    /// Hands the key to the child `cmd` will start: a pipe holding the key, whose read end the
    /// child inherits and whose number is added to its arguments as [`KEY_FD_FLAG`]. Keep the
    /// returned read end until `cmd` has spawned, then drop it (the child has its own copy).
    pub fn hand_to(&self, cmd: &mut Command) -> Result<KeyPipe> {
        let pipe_error = |e: std::io::Error| IpcError::Key(format!("a pipe for the run key: {e}"));
        // both ends close on exec: only the read end is kept open in the child, below
        let (reader, mut writer) = std::io::pipe().map_err(pipe_error)?;
        // 32 bytes fit in any pipe's buffer: the write completes without a reader
        writer.write_all(&self.0).map_err(pipe_error)?;
        drop(writer);
        let fd = reader.as_raw_fd();
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
        cmd.args([KEY_FD_FLAG, &fd.to_string()]);
        Ok(KeyPipe {
            _read_end: OwnedFd::from(reader),
        })
    }

    /// Reads the key a launcher handed over ([`hand_to`](Self::hand_to)) from descriptor `fd`:
    /// exactly [`KEY_LEN`] bytes, then closes it. `fd` must be a pipe this process inherited.
    pub fn from_fd(fd: RawFd) -> Result<Self> {
        let bad = |why: String| {
            IpcError::Key(format!(
                "reading the run key from descriptor {fd} ({KEY_FD_FLAG}): {why}; the roles are \
                 started by `ctxrace train`, which hands them the key over a pipe"
            ))
        };
        if fd < 3 {
            return Err(bad(
                "not an inherited pipe (0 to 2 are the standard streams)".into(),
            ));
        }
        // SAFETY: fstat writes only into `stat`, which is valid for writes; a descriptor that
        // is not open makes it fail without effect.
        let mut stat: libc::stat = unsafe { std::mem::zeroed() };
        // SAFETY: as above.
        if unsafe { libc::fstat(fd, &mut stat) } == -1 {
            return Err(bad(std::io::Error::last_os_error().to_string()));
        }
        if stat.st_mode & libc::S_IFMT != libc::S_IFIFO {
            return Err(bad("not a pipe".into()));
        }
        // SAFETY: `fd` is an open pipe (checked above) that nothing else in this process owns:
        // it was inherited for this read alone, and is closed when `pipe` drops.
        let pipe = unsafe { OwnedFd::from_raw_fd(fd) };
        let mut key = [0u8; KEY_LEN];
        std::fs::File::from(pipe)
            .read_exact(&mut key)
            .map_err(|e| bad(format!("{e} (another process may have read it first)")))?;
        Ok(Self(key))
    }
}

/// The parent's copy of the read end of a pipe holding the run key ([`RunKey::hand_to`]);
/// dropping it closes it.
#[derive(Debug)]
pub struct KeyPipe {
    _read_end: OwnedFd,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_fresh_and_their_debug_shows_no_byte() {
        let (a, b) = (RunKey::generate().unwrap(), RunKey::generate().unwrap());
        assert_ne!(a, b);
        assert_eq!(format!("{a:?}"), "RunKey(..)");
    }

    /// A child started with [`RunKey::hand_to`] finds the key's bytes on the descriptor its
    /// arguments name, and nowhere on its command line; a descriptor that is no pipe is refused.
    #[test]
    fn a_child_reads_the_key_from_the_descriptor_it_is_given() {
        let key = RunKey::from_bytes([7; KEY_LEN]);
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "od -v -An -tu1 -N32 <&$2 | tr -s ' \\n' ' '", "sh"]);
        let pipe = key.hand_to(&mut cmd).unwrap();
        let out = cmd.output().unwrap();
        drop(pipe);
        let got: Vec<u8> = String::from_utf8(out.stdout)
            .unwrap()
            .split_whitespace()
            .map(|b| b.parse().unwrap())
            .collect();
        assert_eq!(got, vec![7; KEY_LEN]);
        let args: Vec<_> = cmd
            .get_args()
            .map(|a| a.to_string_lossy().into_owned())
            .collect();
        assert_eq!(args[args.len() - 2], KEY_FD_FLAG);
        assert!(!args.iter().any(|a| a.contains("7 7")), "{args:?}");
        for fd in [0, 2, 999] {
            let e = RunKey::from_fd(fd).unwrap_err().to_string();
            assert!(e.contains("ctxrace train"), "{e}");
        }
        let file = tempfile::tempfile().unwrap();
        let e = RunKey::from_fd(file.as_raw_fd()).unwrap_err().to_string();
        assert!(e.contains("not a pipe"), "{e}");
    }

    /// A pipe that holds fewer than 32 bytes (someone read it first) is refused.
    #[test]
    fn a_short_key_is_refused() {
        let (reader, mut writer) = std::io::pipe().unwrap();
        writer.write_all(&[1; 5]).unwrap();
        drop(writer);
        let fd = OwnedFd::from(reader);
        let raw = fd.as_raw_fd();
        std::mem::forget(fd); // from_fd takes it over
        let e = RunKey::from_fd(raw).unwrap_err().to_string();
        assert!(e.contains("another process may have read it first"), "{e}");
    }
}
