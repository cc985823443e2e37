//! End-to-end behaviour of `RaceEnv`: determinism, lap completion, collisions and their metrics.

use ctxrace_config::{Context, RaceConfig};
use ctxrace_sim::baseline::{Baseline, BaselineKind};
use ctxrace_sim::{RaceEnv, Step};
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

/// Each car stands on the raceline beside its grid place, facing along it (the default), or
/// on the centreline (`grid_line = "centreline"`, the paper's code).
#[test]
fn cars_stand_on_the_chosen_line() {
    let track = generated();
    let on = |cfg: &str| {
        let mut env = RaceEnv::new(track.clone(), RaceConfig::from_toml(cfg).unwrap()).unwrap();
        env.reset(0, Context::default());
        env.cars()
            .iter()
            .map(|c| {
                let p = c.vehicle.position();
                let to_line = track.raceline.curve.project(&p).lateral.abs();
                let to_centre = track.centreline.curve.project(&p).lateral.abs();
                (to_line, to_centre)
            })
            .collect::<Vec<_>>()
    };
    let raceline = on("rivals = 3");
    let centreline = on("rivals = 3\ngrid_line = \"centreline\"");
    assert!(raceline.iter().all(|&(l, _)| l < 1e-6), "{raceline:?}");
    assert!(centreline.iter().all(|&(_, c)| c < 1e-6), "{centreline:?}");
    // the generated track's raceline leaves the centreline somewhere on the grid
    assert!(raceline.iter().any(|&(_, c)| c > 0.05), "{raceline:?}");
}

/// A race on the generated track whose one rival, 15 m ahead at three times the raceline's
/// speed, crashes at the first bend, where the pure-pursuit ego passes it after 4.2 s.
fn crashing_rival(extra: &str, max_time: f64) -> (RaceEnv, Vec<Step>) {
    let cfg = RaceConfig::from_toml(&format!(
        "rivals = 1\nstart_spacing = 15.0\nmax_time = {max_time}\n{extra}\n[rival]\nspeed_factor = 3.0\nmax_speed = 20.0\n"
    ))
    .unwrap();
    let mut env = RaceEnv::new(generated(), cfg).unwrap();
    let (_, steps) = episode(&mut env, BaselineKind::PurePursuit, 0, Context::default());
    (env, steps)
}

#[test]
fn the_paper_codes_crashed_rivals_ot_and_pg_are_reachable() {
    // the ego passes the crashed rival at some step k
    let (env, steps) = crashing_rival("", 240.0);
    assert!(env.cars()[1].crashed);
    let k = steps
        .iter()
        .position(|s| s.info.overtakes == 1)
        .expect("a pass");
    // ending the episode (time-out) right at that step: the code leaves its rank change out
    let at_k = (k + 1) as f64 * 0.1;
    let (env, steps) = crashing_rival("", at_k);
    assert_eq!((steps.len(), steps[k].info.overtakes), (k + 1, 1));
    assert_eq!(env.metrics().overtakes, 1);
    let (env, _) = crashing_rival("overtakes_last_step = false", at_k);
    assert_eq!(env.metrics().overtakes, 0);
    // a stopped rival stays put; a coasting one brakes from its crash speed
    let rival_at = |extra: &str, t: f64| {
        let (env, _) = crashing_rival(extra, t);
        let car = &env.cars()[1];
        assert!(car.crashed, "{extra} at {t} s");
        (car.vehicle.position(), car.vehicle.speed())
    };
    let ((early, v_early), (late, v_late)) = (rival_at("", 3.0), rival_at("", 3.5));
    assert_eq!((early, v_early, v_late), (late, 0.0, 0.0));
    let coast = "crashed_rivals = \"coast\"";
    let ((early, v_early), (late, v_late)) = (rival_at(coast, 3.0), rival_at(coast, 3.5));
    assert!(early != late && v_early > v_late, "{v_early} {v_late}");
    // PG past the line: the distance driven over the lap's length
    let (env, steps) = crashing_rival("progress_past_line = true", 240.0);
    assert!(steps.last().unwrap().info.lap_complete);
    let pg = env.metrics().progress;
    assert!(pg > 1.0 && pg < 1.05, "{pg}");
}

#[test]
fn the_relaunch_takes_over_whenever_the_ego_slows_below_its_threshold() {
    let ego_after_braking = |relaunch: bool| {
        let cfg = RaceConfig::from_toml(&format!(
            "rivals = 0\nego_launch_below = 1.0\nego_relaunch = {relaunch}\n"
        ))
        .unwrap();
        let mut env = RaceEnv::new(generated(), cfg).unwrap();
        env.reset(0, Context::default());
        let mut speeds = Vec::new();
        for _ in 0..5 {
            // full brake: the command 0 m/s
            let step = env.step([0.0, -1.0]).unwrap();
            assert!(!step.terminated);
            speeds.push(env.ego_state()[ctxrace_sim::vehicle::idx::V]);
        }
        (speeds, env.metrics().steps)
    };
    // launched only at the start, the ego stops
    let (speeds, once) = ego_after_braking(false);
    assert!(speeds[4] < 0.1, "{speeds:?}");
    // relaunched, it never ends a step below 1 m/s: the launch's decisions add to the agent's
    let (speeds, again) = ego_after_braking(true);
    assert!(
        speeds.iter().all(|&v| v >= 1.0) && again > once,
        "{speeds:?} {again} {once}"
    );
}

/// The pure-pursuit ego against one rival on f1_esp, in each of the paper's test contexts
/// (17-48 of the 7 x 7 grid, `c_v`-major), under the `paper-code` preset: the paper's own
/// simulator (c0fd903, deploy/paper_sim_agreement.sh) ends the same episodes in the rival at
/// the same place (its PG to 1e-4: the two measure progress along the centreline a little
/// differently near its vertices) and completes the others (its PG 1.00025 there, ctxrace's
/// 1.00101: its lap ends half a decision early, docs/table2/sim_agreement.md). Under the race
/// the table was trained in (rival contacts per physics step, the car's wheelbase and steering
/// for the rivals, the centreline grid, the traced walls), the fast rivals of (0.3, 0.2) and
/// (0.3, 0.3) graze a wall, stop, and the ego runs into them.
#[test]
fn paper_code_pure_pursuit_ego_meets_the_rival_where_the_papers_simulator_does() {
    let dir = shared_reference("tracks").unwrap_or_else(|e| panic!("{e}"));
    let opts = TrackOptions {
        tracks_dir: dir,
        raceline_source: ctxrace_tracks::RacelineSource::File,
        ..Default::default()
    };
    let track = Arc::new(Track::load("f1_esp", &opts).unwrap());
    // the paper's simulator: PG where the ego hit the rival, per context, c_v -0.1 to 0.1
    let crashed = [
        0.087720, 0.087513, 0.087720, 0.087720, // c_v -0.1, c_θ 0 to 0.3
        0.129141, 0.129892, 0.128927, 0.126211, 0.124303, 0.124091, 0.123671, // c_v 0
        0.283420, 0.279392, 0.278548, 0.273808, 0.271240, 0.267455, 0.263758, // c_v 0.1
    ];
    let race = |text: &str| {
        let cfg = RaceConfig::from_toml(text).unwrap();
        RaceEnv::new(track.clone(), cfg).unwrap()
    };
    let mut paper_code = race("preset = \"paper-code\"");
    let mut table_era = race(
        "preset = \"paper-code\"\ngrid_line = \"centreline\"\nwall_contact = \"centre\"\n\
         rival_contacts = \"per-step\"\n[rival]\nwheelbase = 0.3302\nmax_steer = 0.4189\n",
    );
    for (k, ctx) in Context::grid(7, 0.3).into_iter().enumerate().skip(17) {
        episode(&mut paper_code, BaselineKind::PurePursuit, 0, ctx);
        let m = paper_code.metrics();
        match crashed.get(k - 17) {
            Some(&pg) => {
                assert!(m.a2a && (m.progress - pg).abs() < 1e-4, "{ctx:?}: {m:?}");
            }
            None => assert!(m.lap_time.is_some() && !m.a2a, "{ctx:?}: {m:?}"),
        }
        episode(&mut table_era, BaselineKind::PurePursuit, 0, ctx);
        let fast_and_long = ctx.speed > 0.25 && ctx.steer > 0.15;
        assert_eq!(
            table_era.metrics().a2a,
            m.a2a || fast_and_long,
            "{ctx:?}: {:?}",
            table_era.metrics()
        );
    }
    // the rivals stand where the paper's code put them: on the x axis, facing +x
    let (p, yaw) = ctxrace_sim::grid::grid_pose(&track, ctxrace_config::GridLine::XAxis, 5.5);
    assert_eq!((p.x, p.y, yaw), (5.5, 0.0, 0.0));
}

#[test]
fn the_state_gives_the_egos_pose_and_the_rivals_relative_to_it() {
    let cfg = RaceConfig {
        rivals: 2,
        ..Default::default()
    };
    let mut env = RaceEnv::new(generated(), cfg).unwrap();
    env.reset(3, Context::default());
    assert_eq!(env.state_dim(), 5 + 4 * 2);
    let mut state = vec![f32::NAN; env.state_dim()];
    env.state_into(&mut state);
    assert!(state.iter().all(|v| v.is_finite()), "{state:?}");
    // the rivals stand ahead of the ego on the grid, one grid gap apart, facing about its way
    let (ahead_1, ahead_2) = (state[5], state[9]);
    assert!(0.0 < ahead_1 && ahead_1 < ahead_2, "{state:?}");
    for heading in [state[7], state[11]] {
        assert!(heading.abs() <= std::f32::consts::PI, "{state:?}");
    }
    let gap = (state[5].powi(2) + state[6].powi(2)).sqrt();
    assert!((3.0..8.0).contains(&gap), "first rival {gap} m away");
    let (low, high) = env.state_bounds();
    assert_eq!((low.len(), high.len()), (state.len(), state.len()));
    for ((v, lo), hi) in state.iter().zip(&low).zip(&high) {
        assert!(
            lo <= v && v <= hi && *lo == -*hi,
            "{v} outside [{lo}, {hi}]"
        );
    }
}
