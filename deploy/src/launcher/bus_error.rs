//! What the launcher says when a shared-memory segment it reads is truncated under it (SIGBUS).

/// What the launcher says when a shared-memory segment it reads is truncated under it.
const BUS_ERROR_MESSAGE: &[u8] = b"\nctxrace train: the run's shared memory was truncated or \
    removed under the launcher (SIGBUS); the run stops here, its processes with it (they stop \
    when the launcher dies). The next `ctxrace train` removes the run's files; resume this run \
    with --resume.\n";

/// Writes [`BUS_ERROR_MESSAGE`] to stderr and dies of the signal, as without a handler.
extern "C" fn on_bus_error(_: libc::c_int) {
    // SAFETY: write, signal and raise are async-signal-safe; the message is a static buffer.
    unsafe {
        libc::write(
            2,
            BUS_ERROR_MESSAGE.as_ptr().cast(),
            BUS_ERROR_MESSAGE.len(),
        );
        libc::signal(libc::SIGBUS, libc::SIG_DFL);
        libc::raise(libc::SIGBUS);
    }
}

/// Makes a SIGBUS (a segment truncated under the launcher, which iceoryx2 maps) say what
/// happened before the launcher dies of it, instead of dying without a word.
pub(super) fn explain_bus_errors() {
    // SAFETY: installs a handler that only calls async-signal-safe functions.
    unsafe {
        libc::signal(
            libc::SIGBUS,
            on_bus_error as *const () as libc::sighandler_t,
        );
    }
}
