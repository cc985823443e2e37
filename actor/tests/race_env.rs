//! End-to-end behaviour of `RaceEnv`: determinism, lap completion, collisions and their metrics.

use ctxrace_actor::baseline::{Baseline, BaselineKind};
use ctxrace_actor::{RaceEnv, Step};
use ctxrace_common::{Context, RaceConfig};
use ctxrace_tracks::files::shared_reference;
use ctxrace_tracks::{Track, TrackOptions};
use std::sync::Arc;

/// Runs one episode with a reference policy; returns every step.
fn episode(
    env: &mut RaceEnv,
    kind: BaselineKind,
    seed: u64,
    ctx: Context,
) -> (Vec<f32>, Vec<Step>) {
    let first = env.reset(seed, ctx);
    let mut policy = Baseline::new(kind, env, seed);
    let mut steps = Vec::new();
    loop {
        let step = env.step(policy.act(env)).unwrap();
        let done = step.terminated || step.truncated;
        steps.push(step);
        if done {
            return (first, steps);
        }
    }
}

fn generated() -> Arc<Track> {
    Arc::new(Track::load("generated:1", &TrackOptions::default()).unwrap())
}

#[test]
fn same_seed_gives_the_same_episode_bit_for_bit() {
    let cfg = RaceConfig {
        rivals: 3,
        ..Default::default()
    };
    let mut env = RaceEnv::new(generated(), cfg).unwrap();
    let ctx = Context::new(0.2, -0.1).unwrap();
    let (first_a, a) = episode(&mut env, BaselineKind::Random, 11, ctx);
    let (first_b, b) = episode(&mut env, BaselineKind::Random, 11, ctx);
    assert_eq!(first_a, first_b);
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.obs, y.obs);
        assert_eq!(x.reward.to_bits(), y.reward.to_bits());
        assert_eq!(x.info, y.info);
    }
    // another seed changes the LiDAR noise
    let (first_c, _) = episode(&mut env, BaselineKind::Random, 12, ctx);
    assert_ne!(first_a, first_c);
}

#[test]
fn ramming_a_slow_rival_ends_the_episode_as_a2a() {
    let cfg = RaceConfig {
        rivals: 1,
        ..Default::default()
    };
    let mut env = RaceEnv::new(generated(), cfg).unwrap();
    let (_, steps) = episode(
        &mut env,
        BaselineKind::PurePursuit,
        0,
        Context::new(-0.3, 0.0).unwrap(),
    );
    let last = steps.last().unwrap();
    assert!(last.terminated && last.info.a2a, "{:?}", last.info);
    let m = env.metrics();
    assert!(m.a2a && !m.wall_crash && m.lap_time.is_none());
    assert!(m.progress > 0.0 && m.progress < 0.2, "{m:?}");
    // the collision step carries the crash penalty
    assert!(last.reward < 0.0, "{}", last.reward);
    assert!(
        env.step([0.0, 0.0]).is_err(),
        "stepping a finished episode is an error"
    );
    assert!(env.reset(0, Context::default()).len() == 108);
    assert!(
        env.step([f64::NAN, 0.0]).is_err(),
        "NaN actions are rejected"
    );
}

#[test]
fn pure_pursuit_ego_laps_both_paper_tracks_alone() {
    let dir = shared_reference("tracks").unwrap_or_else(|e| panic!("{e}"));
    let opts = TrackOptions {
        tracks_dir: dir,
        ..Default::default()
    };
    for name in ["f1_esp", "f1_gbr"] {
        let track = Arc::new(Track::load(name, &opts).unwrap());
        let mut env = RaceEnv::new(
            track,
            RaceConfig {
                rivals: 0,
                ..Default::default()
            },
        )
        .unwrap();
        let (_, steps) = episode(&mut env, BaselineKind::PurePursuit, 0, Context::default());
        let m = env.metrics();
        assert!(steps.last().unwrap().info.lap_complete, "{name}: {m:?}");
        assert_eq!(m.progress, 1.0);
        let lap = m.lap_time.unwrap();
        assert!((30.0..80.0).contains(&lap), "{name}: lap {lap}");
        assert_eq!(m.overtakes, 0);
        // the shaped reward is mostly positive when driving fast along the track
        assert!(m.episode_return > 0.3 * steps.len() as f64, "{name}: {m:?}");
        assert!(steps
            .iter()
            .all(|s| s.obs.iter().all(|v| (0.0..=1.0).contains(v))));
    }
}

#[test]
fn the_grid_spaces_cars_in_metres_or_in_lap_fractions() {
    let track = generated();
    let length = track.length();
    let grid = |cfg: RaceConfig| {
        let mut env = RaceEnv::new(track.clone(), cfg).unwrap();
        env.reset(0, Context::default());
        env.cars().iter().map(|c| c.travelled).collect::<Vec<_>>()
    };
    // the default: the tables' code, 5.5 m apart on a track without an entry of its own
    let metres = grid(RaceConfig {
        rivals: 3,
        ..Default::default()
    });
    for (i, s) in metres.iter().enumerate() {
        assert!((s - 5.5 * i as f64).abs() < 1e-9, "car {i} at {s}");
    }
    // a track's own entry replaces start_spacing
    let mut cfg = RaceConfig::from_toml(
        "rivals = 2\nstart_spacing = 3.0\n[start_spacing_tracks]\n\"generated:1\" = 4.0\n",
    )
    .unwrap();
    assert_eq!(grid(cfg.clone())[2], 8.0);
    cfg.start_spacing_tracks.clear();
    assert_eq!(grid(cfg)[2], 6.0);
    // the release's grid: 5% of the lap
    let fraction =
        grid(RaceConfig::from_toml("rivals = 3\nstart_grid = \"lap-fraction\"").unwrap());
    assert!((fraction[3] - 0.15 * length).abs() < 1e-9, "{fraction:?}");
    // a grid longer than the lap is refused, naming the key
    let err = RaceEnv::new(
        track.clone(),
        RaceConfig::from_toml(&format!("rivals = 7\nstart_spacing = {}", length / 7.0)).unwrap(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(err.contains("start_spacing:"), "{err}");
}
