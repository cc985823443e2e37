//! Data parallelism for one training step: a batch of sequences is split into one shard per
//! worker thread; each shard computes its part of a loss (its mean times its share
//! `|rows| / B` of the batch) and differentiates it, and the optimiser steps on the sum of the
//! shards' gradients, which is the batch's gradient. Each sequence draws its noise from its own
//! stream, so a step computes the same losses whatever the number of workers.

use crate::algorithm::Metrics;
use crate::error::{LearnerError, Result};
use rand_chacha::ChaCha8Rng;

/// A shard of a batch: the sequences one worker thread trains on.
#[derive(Clone)]
pub(crate) struct Shard {
    /// Its position among the shards.
    pub(crate) index: usize,
    /// Its sequences.
    pub(crate) rows: std::ops::Range<usize>,
    /// Its share of the batch, `|rows| / B`: a shard's mean loss times this sums to the batch's.
    pub(crate) weight: f64,
}

/// Runs `f` on each shard of a batch of `batch` sequences, one per worker thread, in parallel,
/// with the noise streams of the shard's sequences and the shard's state: shard `i` gets
/// `states[i]` (there must be one per shard: `min(workers, batch)` of them); returns the results
/// in shard order.
pub(crate) fn on_shards_with<S: Send, T: Send>(
    workers: usize,
    batch: usize,
    rngs: &mut [ChaCha8Rng],
    states: &mut [S],
    f: impl Fn(Shard, &mut [ChaCha8Rng], &mut S) -> Result<T> + Sync,
) -> Result<Vec<T>> {
    let workers = workers.clamp(1, batch.max(1));
    let per = batch.div_ceil(workers).max(1);
    let count = batch.div_ceil(per);
    if states.len() < count || rngs.len() < batch {
        return Err(LearnerError::ShardInputs {
            batch,
            shards: count,
            states: states.len(),
            streams: rngs.len(),
        });
    }
    let mut shards = Vec::with_capacity(count);
    let mut rest = rngs;
    for ((index, start), state) in (0..batch).step_by(per).enumerate().zip(states.iter_mut()) {
        let rows = start..(start + per).min(batch);
        let (mine, others) = rest.split_at_mut(rows.len());
        rest = others;
        let weight = rows.len() as f64 / batch as f64;
        shards.push((
            Shard {
                index,
                rows,
                weight,
            },
            mine,
            state,
        ));
    }
    in_parallel(&mut shards, |_, (shard, rngs, state)| {
        f(shard.clone(), rngs, state)
    })
}

/// Runs `f` on each of `items` (with its index), each on a thread of its own, in parallel (on
/// this thread if there is one); returns the results in order.
pub(crate) fn in_parallel<S: Send, T: Send>(
    items: &mut [S],
    f: impl Fn(usize, &mut S) -> Result<T> + Sync,
) -> Result<Vec<T>> {
    if let [only] = items {
        return Ok(vec![f(0, only)?]);
    }
    let f = &f;
    std::thread::scope(|scope| {
        let handles: Vec<_> = items
            .iter_mut()
            .enumerate()
            .map(|(i, item)| scope.spawn(move || f(i, item)))
            .collect();
        handles.into_iter().map(join_worker).collect()
    })
}

/// The result of a worker thread; a panic becomes an error.
fn join_worker<T>(h: std::thread::ScopedJoinHandle<'_, Result<T>>) -> Result<T> {
    h.join().map_err(|_| LearnerError::WorkerPanicked)?
}

/// Adds a shard's `part` to the running `sum` of the shards' gradients with `add`, or makes it
/// the sum if it is the first (no zeroed sum to start from).
pub(crate) fn add_part<T>(sum: &mut Option<T>, part: T, add: impl FnOnce(&mut T, &T)) {
    match sum {
        Some(sum) => add(sum, &part),
        None => *sum = Some(part),
    }
}

/// The mean of the shards' metrics, each weighted by its share of the batch.
pub(crate) fn weighted_mean(parts: &[(f64, Metrics)]) -> Metrics {
    let mut out = Metrics::new();
    for (w, m) in parts {
        for (k, v) in m {
            *out.entry(k.clone()).or_insert(0.0) += w * v;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn streams(n: u64) -> Vec<ChaCha8Rng> {
        (0..n).map(ChaCha8Rng::seed_from_u64).collect()
    }

    #[test]
    fn shards_cover_the_batch_in_order_and_missing_inputs_are_an_error() {
        let mut rngs = streams(5);
        let mut states = vec![0usize; 2];
        let rows = on_shards_with(2, 5, &mut rngs, &mut states, |shard, rngs, state| {
            *state = shard.rows.len();
            Ok((shard.index, shard.rows, rngs.len(), shard.weight))
        })
        .unwrap();
        assert_eq!(rows, [(0, 0..3, 3, 0.6), (1, 3..5, 2, 0.4)]);
        assert_eq!(states, [3, 2]);

        let mut one_state = vec![0usize; 1];
        let err = on_shards_with(2, 5, &mut rngs, &mut one_state, |_, _, _| Ok(())).unwrap_err();
        assert!(
            matches!(
                err,
                LearnerError::ShardInputs {
                    batch: 5,
                    shards: 2,
                    states: 1,
                    streams: 5
                }
            ),
            "{err}"
        );
        let mut few = streams(3);
        let err = on_shards_with(2, 5, &mut few, &mut states, |_, _, _| Ok(())).unwrap_err();
        assert!(err.to_string().contains("3 noise streams"), "{err}");
    }
}
