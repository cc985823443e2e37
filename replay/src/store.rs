//! The replay buffer as the single-process trainer's sample store
//! ([`ctxrace_run::experience::SampleStore`]): one stream per actor, the payload trusted as the
//! trainer's own, its contents saved and restored as a replay snapshot ([`crate::snapshot`]).

use crate::buffer::ReplayBuffer;
use crate::snapshot::{read_snapshot, write_snapshot, LimiterCounts, SnapshotShape};
use ctxrace_config::{Batch, BatchSpec, Sampler};
use ctxrace_run::experience::{SampleStore, StoreError};
use rand_chacha::ChaCha8Rng;
use std::path::Path;

/// The single-process trainer's store (one stream per actor, the payload trusted as the
/// trainer's own).
impl SampleStore for ReplayBuffer {
    fn obs_dim(&self) -> usize {
        ReplayBuffer::obs_dim(self)
    }

    fn act_dim(&self) -> usize {
        ReplayBuffer::act_dim(self)
    }

    fn len(&self) -> usize {
        ReplayBuffer::len(self)
    }

    fn capacity(&self) -> usize {
        ReplayBuffer::capacity(self)
    }

    fn insert_chunk(&mut self, actor: usize, payload: &[f32], after_gap: bool) {
        ReplayBuffer::insert_chunk(self, actor, payload, after_gap);
    }

    fn sample(&self, spec: BatchSpec, sampler: Sampler, rng: &mut ChaCha8Rng) -> Option<Batch> {
        ReplayBuffer::sample(self, spec, sampler, rng)
    }

    /// A replay snapshot ([`crate::snapshot`]); its limiter counts are the steps inserted.
    fn save(&self, path: &Path) -> Result<(), StoreError> {
        let counts = LimiterCounts {
            inserts: self.inserted,
            samples: 0,
        };
        Ok(write_snapshot(path, self, counts)?)
    }

    fn restore(&mut self, path: &Path) -> Result<(), StoreError> {
        let (buffer, _) = read_snapshot(path, SnapshotShape::of(self))?;
        *self = buffer;
        Ok(())
    }
}
