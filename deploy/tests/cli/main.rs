//! The command line's tests, one module a concern, in one test binary (one link instead of
//! three on every build); the cross-process runtime tests are the workspace's `tests/runtime.rs`.

mod cli;
mod docs_links;
mod inline_resume;
