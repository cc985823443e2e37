//! Simulator throughput: one decision (10 physics steps of every car, collisions, the ego's
//! 108-beam LiDAR) on f1_esp (from ../shared/tracks, else a generated track), with 0 and 3 rivals,
//! the ego driving pure pursuit, episodes reset as they end. Targets: ≥ 50,000 decisions/s with no
//! rivals, ≥ 20,000 with 3 (one core).
#![allow(missing_docs)] // criterion's macros define undocumented functions

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ctxrace_config::{Context, RaceConfig};
use ctxrace_sim::baseline::{Baseline, BaselineKind};
use ctxrace_sim::RaceEnv;
use ctxrace_tracks::{Track, TrackOptions};
use std::path::PathBuf;
use std::sync::Arc;

fn track() -> Track {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/tracks");
    let opts = TrackOptions {
        tracks_dir: dir.clone(),
        ..Default::default()
    };
    if dir.is_dir() {
        Track::load("f1_esp", &opts).expect("f1_esp loads")
    } else {
        Track::load("generated:0", &opts).expect("generated track")
    }
}

fn decisions(c: &mut Criterion) {
    let track = Arc::new(track());
    let mut group = c.benchmark_group(format!("race_decision/{}", track.name));
    group.throughput(Throughput::Elements(1));
    for rivals in [0usize, 3] {
        let cfg = RaceConfig {
            rivals,
            ..Default::default()
        };
        let mut env = RaceEnv::new(track.clone(), cfg).expect("valid config");
        let grid = Context::grid(7, 0.3);
        let mut episode = 0u64;
        env.reset(episode, grid[0]);
        let mut policy = Baseline::new(BaselineKind::PurePursuit, &env, episode);
        group.bench_function(format!("{rivals}_rivals"), |b| {
            b.iter(|| {
                let step = env.step(policy.act(&env)).expect("finite action");
                if step.terminated || step.truncated {
                    episode += 1;
                    env.reset(episode, grid[episode as usize % grid.len()]);
                    policy = Baseline::new(BaselineKind::PurePursuit, &env, episode);
                }
                step.reward
            })
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(4));
    targets = decisions
}
criterion_main!(benches);
