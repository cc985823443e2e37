//! The replay process's settings (`[replay]`) and how its capacity is shared out.

use serde::{Deserialize, Serialize};

/// Default largest batch payload in floats (64 MiB), `[replay] max_batch_floats`.
pub const DEFAULT_MAX_BATCH_FLOATS: usize = 16 << 20;

/// Steps each of `actors` streams holds when a replay of `capacity` steps is shared out.
pub fn stream_capacity(capacity: usize, actors: usize) -> usize {
    (capacity / actors.max(1)).max(1)
}

/// The replay process's settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReplayOptions {
    /// Steps held, shared equally between the actors' streams.
    pub capacity: usize,
    /// Steps inserted before the first batch is sampled.
    pub min_fill: usize,
    /// Sampled steps allowed per inserted step (a `B x T` sequence batch samples `B·T` steps,
    /// a transition batch `B`); 0 disables the ratio and only `min_fill` holds.
    pub samples_per_insert: f64,
    /// How far, in inserted steps, the ratio may drift either way before sampling (or
    /// inserting) waits, as Reverb's `error_buffer` (in samples: this times the ratio).
    pub error_buffer_steps: f64,
    /// Seconds between periodic snapshots; 0 snapshots only on shutdown.
    pub snapshot_every_secs: u64,
    /// Snapshot file; none disables snapshots.
    pub snapshot_path: Option<std::path::PathBuf>,
    /// Seed of the sampling RNG.
    pub seed: u64,
    /// Largest batch payload in floats.
    pub max_batch_floats: usize,
    /// How sequence batches are drawn (not read from `[replay]`: the launcher sets it from
    /// `[agent] sampler`).
    #[serde(skip)]
    pub sampler: crate::agents::Sampler,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        Self {
            capacity: 1_000_000,
            min_fill: 1000,
            samples_per_insert: 0.0,
            error_buffer_steps: 1000.0,
            snapshot_every_secs: 60,
            snapshot_path: None,
            seed: 0,
            max_batch_floats: DEFAULT_MAX_BATCH_FLOATS,
            sampler: crate::agents::Sampler::Uniform,
        }
    }
}
