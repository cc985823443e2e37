//! How long a snapshot keeps the replay loop from delivering batches: before, the loop wrote
//! the snapshot itself (`write_snapshot`: encode, write, fsync, rename); now it only encodes
//! (`encode_snapshot`) and a thread of its own writes. A buffer of 100 000 steps of 108-beam
//! frames, as a run's replay holds after a few minutes.
//!
//!     cargo bench -p ctxrace-replay --bench snapshot
#![allow(missing_docs)] // criterion's macros define undocumented functions

use criterion::{criterion_group, criterion_main, Criterion};
use ctxrace_ipc::TrajectoryStep;
use ctxrace_replay::{encode_snapshot, write_snapshot, LimiterCounts, ReplayBuffer};

const OBS: usize = 108;
const STEPS: usize = 100_000;

fn full_buffer() -> ReplayBuffer {
    let actors = 4;
    let mut buffer = ReplayBuffer::new(STEPS / actors, actors, OBS, 2);
    let obs = vec![0.5f32; OBS];
    for actor in 0..actors {
        for episode in 0..STEPS / actors / 100 {
            let mut payload = Vec::new();
            for k in 0..100 {
                TrajectoryStep {
                    obs: &obs,
                    action: &[0.1, -0.1],
                    reward: episode as f32,
                    is_first: k == 0,
                    is_terminal: false,
                    is_last: k == 99,
                    context: [0.1, -0.2],
                    mask: None,
                }
                .encode(&mut payload);
            }
            buffer.insert_chunk(actor, &payload, false);
        }
    }
    buffer
}

fn snapshot_pause(c: &mut Criterion) {
    let buffer = full_buffer();
    let counts = LimiterCounts {
        inserts: STEPS as u64,
        samples: 0,
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("replay.snapshot");
    let mut group = c.benchmark_group("snapshot_pause_100k_steps");
    group.sample_size(10);
    group.bench_function("before: write in the loop", |b| {
        b.iter(|| write_snapshot(&path, &buffer, counts).unwrap())
    });
    group.bench_function("now: encode in the loop", |b| {
        b.iter(|| encode_snapshot(&buffer, counts))
    });
    group.finish();
}

criterion_group!(benches, snapshot_pause);
criterion_main!(benches);
