//! ctxrace-ipc's receivers under fault injection, in one test binary.

mod rewrite;
mod telemetry;

/// The key of the tests' runs.
fn test_key() -> ctxrace_ipc::RunKey {
    ctxrace_ipc::RunKey::from_bytes([9; ctxrace_ipc::KEY_LEN])
}
