//! Copying out of shared memory whose addresses may lie.
//!
//! A received sample's address is an offset its publisher chose with an allocator whose state
//! lives in the publisher's own data segment. Flip bits there (another program writing into
//! `/dev/shm`, a stray write of a peer) and the publisher can hand out an offset outside every
//! mapping; a plain read of the sample then kills the reader by SIGSEGV (the launcher died so,
//! reading a heartbeat, under the fuzz test of issue 47). The copies here go through
//! `process_vm_readv(2)` on this process: where a read would fault, it fails with `EFAULT`, and
//! the message is rejected as [`WireError::Unreadable`] instead. Each copy is one system call,
//! and no byte is read twice: what was copied is what gets validated and used.
//!
//! Where the call is refused (a seccomp profile without it), copies fall back to plain reads,
//! said once in the log.

use super::wire::WireError;
use std::mem::{size_of, size_of_val, MaybeUninit};
use std::sync::atomic::{AtomicBool, Ordering};

/// Set once `process_vm_readv` was refused: copies are plain reads from then on.
static PLAIN_READS: AtomicBool = AtomicBool::new(false);

/// Copies `len` bytes at `src` to `dst`, failing where part of `src` is not readable.
///
/// # Safety
/// `dst` must be valid for writes of `len` bytes and not overlap `src`.
unsafe fn copy_bytes(src: *const u8, dst: *mut u8, len: usize) -> Result<(), WireError> {
    let mut done = 0;
    while done < len && !PLAIN_READS.load(Ordering::Relaxed) {
        let local = libc::iovec {
            iov_base: dst.wrapping_add(done).cast(),
            iov_len: len - done,
        };
        let remote = libc::iovec {
            iov_base: src.wrapping_add(done).cast_mut().cast(),
            iov_len: len - done,
        };
        // SAFETY: the kernel writes at most `len - done` bytes to `local`, which the caller
        // guarantees writable; `remote` is only read, by the kernel, which checks it.
        let n = unsafe { libc::process_vm_readv(libc::getpid(), &local, 1, &remote, 1, 0) };
        match n {
            n if n > 0 => done += n as usize,
            0 => return Err(unreadable(src, len, "nothing copied")),
            _ => {
                let error = std::io::Error::last_os_error();
                match error.raw_os_error() {
                    Some(libc::ENOSYS | libc::EPERM) => {
                        tracing::warn!(
                            "process_vm_readv refused ({error}): shared memory is read plainly, \
                             and a corrupted segment can crash this process"
                        );
                        PLAIN_READS.store(true, Ordering::Relaxed);
                    }
                    Some(libc::EINTR) => {}
                    _ => return Err(unreadable(src, len, &error.to_string())),
                }
            }
        }
    }
    if done < len {
        // SAFETY: plain reads only where the kernel refused to check them (see above);
        // `dst` is writable for `len` bytes (caller).
        unsafe { std::ptr::copy_nonoverlapping(src.wrapping_add(done), dst.add(done), len - done) };
    }
    Ok(())
}

fn unreadable(src: *const u8, len: usize, why: &str) -> WireError {
    WireError::Unreadable(format!("{len} bytes at {src:p}: {why}"))
}

/// Reads a value out of shared memory exactly once, failing where its memory is not readable.
/// Another process may change the memory at any time: only the copy is validated and used.
pub(crate) fn read_once<T: Copy>(shared: &T) -> Result<T, WireError> {
    let mut copy = MaybeUninit::<T>::uninit();
    // SAFETY: `copy` is writable for `size_of::<T>()` bytes and separate from `shared`.
    unsafe {
        copy_bytes(
            (shared as *const T).cast(),
            copy.as_mut_ptr().cast(),
            size_of::<T>(),
        )?
    };
    // SAFETY: every byte of `copy` was written from a value the shared memory held; the
    // message types are `repr(C)` plain numbers, for which every bit pattern is valid.
    Ok(unsafe { copy.assume_init() })
}

/// Fails where the memory of `shared` is not readable: for a sample's iceoryx2 header, which
/// must be read before its payload slice can even be measured.
pub(crate) fn check_readable<T: ?Sized>(shared: &T) -> Result<(), WireError> {
    // read once a sample, on the stack: a header is a few dozen bytes
    let mut scratch = [0u8; 256];
    let start: *const u8 = (shared as *const T).cast();
    let len = size_of_val(shared);
    for at in (0..len).step_by(scratch.len()) {
        let n = (len - at).min(scratch.len());
        // SAFETY: `scratch` is writable for `n` bytes and separate from `shared`.
        unsafe { copy_bytes(start.wrapping_add(at), scratch.as_mut_ptr(), n)? };
    }
    Ok(())
}

/// Replaces `out` with a copy of `shared`, failing where its memory is not readable. The caller
/// bounds `shared.len()` first: a corrupted sample header can claim any length.
pub(crate) fn copy_slice<T: Copy>(shared: &[T], out: &mut Vec<T>) -> Result<(), WireError> {
    copy_slice_with(shared, out, shared.len().max(1), |_| {})
}

/// [`copy_slice`] in blocks of `block` values, handing each block of the copy to `each` as soon
/// as it is copied, while it is still in cache (a checksum computed while copying).
pub(crate) fn copy_slice_with<T: Copy>(
    shared: &[T],
    out: &mut Vec<T>,
    block: usize,
    mut each: impl FnMut(&[T]),
) -> Result<(), WireError> {
    out.clear();
    out.reserve(shared.len());
    for part in shared.chunks(block.max(1)) {
        let start = out.len();
        // SAFETY: `out` has room for `shared.len()` values; `part` is written past its length
        // before the length covers it.
        unsafe {
            copy_bytes(
                part.as_ptr().cast(),
                out.as_mut_ptr().add(start).cast(),
                size_of_val(part),
            )?;
            out.set_len(start + part.len());
        }
        each(&out[start..]);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readable_memory_is_copied_exactly() {
        let values: Vec<f32> = (0..10_000).map(|i| i as f32 * 0.5).collect();
        let mut out = vec![1.0; 3];
        copy_slice(&values, &mut out).unwrap();
        assert_eq!(out, values);
        let mut blocks = Vec::new();
        copy_slice_with(&values, &mut out, 4096, |b| blocks.push(b.len())).unwrap();
        assert_eq!((out, blocks), (values.clone(), vec![4096, 4096, 1808]));
        assert_eq!(read_once(&values[17]).unwrap(), 8.5);
        check_readable(&values[..]).unwrap();
    }

    #[test]
    fn an_address_outside_every_mapping_is_an_error_not_a_crash() {
        // a plain read of the wild address below would kill the test binary: say why instead
        read_once(&1u64).unwrap();
        assert!(
            !PLAIN_READS.load(Ordering::Relaxed),
            "process_vm_readv is refused on this machine (a seccomp profile?): readers of \
             shared memory are not protected against addresses outside their mappings"
        );
        // an address in the first page, which is never mapped
        let wild = std::ptr::dangling::<[u64; 4]>();
        // SAFETY: never dereferenced by Rust code: read_once hands the address to the kernel,
        // which refuses it (a reference to it is formed for the call only).
        let got = read_once(unsafe { &*wild });
        assert!(matches!(got, Err(WireError::Unreadable(_))), "{got:?}");
    }
}
