//! ctxrace's training algorithms behind one [`Algorithm`] trait.

pub mod algorithm;

pub use algorithm::{Algorithm, Batch, BatchKind, Metrics};
