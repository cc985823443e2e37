//! ctxrace's training algorithms behind one [`Algorithm`] trait.

pub mod algorithm;
pub mod sac;

pub use algorithm::{Algorithm, Batch, BatchKind, Metrics};
pub use sac::{Sac, SacConfig};
