//! ctxrace's training algorithms behind one [`Algorithm`] trait.

pub mod algorithm;
pub mod dreamer;
pub mod returns;
pub mod sac;

pub use algorithm::{Algorithm, Batch, BatchKind, Metrics};
pub use dreamer::{ContextMode, Dreamer, DreamerConfig, DreamerPolicy};
pub use sac::{Sac, SacConfig};
