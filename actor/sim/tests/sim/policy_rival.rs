//! Rivals driven by a trained agent (`[rival] driver = "policy"`), on f1_esp (read from
//! ../shared/tracks) with the cMask agent of the table's record `docs/table2/1r/cmask/seed10000`
//! (trained on f1_esp against 1 rival): a race replays from its seed, the context still scales
//! the rivals' speed, and every way the agent can be missing or unfit is refused by name.

use ctxrace_config::{Context, RaceConfig, RivalDriverKind};
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::{BaselineEgo, Ego};
use ctxrace_sim::rival::drive_solo_lap;
use ctxrace_sim::RaceEnv;
use ctxrace_tracks::files::shared_reference;
use ctxrace_tracks::{Track, TrackOptions};
use std::path::PathBuf;
use std::sync::Arc;

fn f1_esp() -> Arc<Track> {
    let dir = shared_reference("tracks").unwrap_or_else(|e| panic!("{e}"));
    let opts = TrackOptions {
        tracks_dir: dir,
        ..Default::default()
    };
    Arc::new(Track::load("f1_esp", &opts).unwrap())
}

/// The trained cMask agent of the table's first record (its best checkpoint).
fn agent() -> PathBuf {
    let run =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../docs/table2/1r/cmask/seed10000");
    assert!(
        run.join("checkpoints/best/policy.safetensors").exists(),
        "{} has no best checkpoint: the table's records are part of the repository",
        run.display()
    );
    run
}

fn policy_race(rivals: usize) -> RaceConfig {
    let mut cfg = RaceConfig {
        rivals,
        ..RaceConfig::default()
    };
    cfg.rival.driver = RivalDriverKind::Policy;
    cfg.rival.policy = Some(agent());
    cfg
}

/// Every car's position after `decisions` decisions (or the end) of an episode with the
/// pure-pursuit ego, and the episode's return.
fn positions(env: &mut RaceEnv, seed: u64, ctx: Context, decisions: usize) -> (Vec<f64>, f64) {
    let mut ego = BaselineEgo::new(BaselineKind::PurePursuit, env);
    let mut obs = env.reset(seed, ctx);
    ego.reset(env, seed);
    for _ in 0..decisions {
        let Ok((action, _)) = ego.act(env, &obs);
        let step = env.step(action).unwrap();
        obs = step.obs;
        if step.terminated || step.truncated {
            break;
        }
    }
    let cars = env.cars().iter();
    let xy = cars.flat_map(|c| [c.vehicle.position().x, c.vehicle.position().y]);
    (xy.collect(), env.metrics().episode_return)
}

#[test]
fn a_race_against_trained_rivals_replays_from_its_seed() {
    let mut env = RaceEnv::new(f1_esp(), policy_race(2)).unwrap();
    let ctx = Context::default();
    let first = positions(&mut env, 7, ctx, 80);
    let again = positions(&mut env, 7, ctx, 80);
    assert_eq!(first, again, "the same seed, the same race");
    // a fresh environment (the agent read again) races the same
    let mut fresh = RaceEnv::new(f1_esp(), policy_race(2)).unwrap();
    assert_eq!(positions(&mut fresh, 7, ctx, 80), first);
    // the rivals drove off (they start 2 and 4 grid places ahead of the ego)
    for rival in &env.cars()[1..] {
        assert!(rival.travelled > rival.furthest - 1e-9 && rival.travelled > 10.0);
    }
    // another seed samples other actions
    assert_ne!(positions(&mut env, 8, ctx, 80).0, first.0);
}

#[test]
fn the_context_scales_a_trained_rivals_speed() {
    let track = f1_esp();
    let mut env = RaceEnv::new(track, policy_race(1)).unwrap();
    let mut travelled = |speed| {
        positions(&mut env, 3, Context { speed, steer: 0.0 }, 30);
        env.cars()[1].travelled
    };
    let (slow, fast) = (travelled(-0.3), travelled(0.3));
    assert!(
        fast > slow + 2.0,
        "c_v = +0.3: {fast} m, c_v = -0.3: {slow} m"
    );
}

#[test]
fn a_trained_rival_drives_a_solo_lap() {
    let track = f1_esp();
    let lap = drive_solo_lap(&track, &policy_race(1), Context::default(), 0.0).unwrap();
    assert!(lap.samples.len() > 20 && lap.samples.last().unwrap().travelled > 20.0);
}

#[test]
fn a_policy_trained_elsewhere_drives_a_rival_from_its_mlp_file() {
    use ctxrace_nn::policy::mlp::{Linear, MlpPolicy};
    // straight ahead at 70% of the speed range, down the start straight
    let beams = RaceConfig::default().lidar.beams;
    let layers = vec![Linear {
        weight: vec![0.0; 2 * beams],
        bias: vec![0.0, 0.4],
    }];
    let policy = MlpPolicy::named(layers, "tanh", "scan", "clip", beams).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("rival.safetensors");
    std::fs::write(&file, policy.to_safetensors().unwrap()).unwrap();
    let mut cfg = policy_race(1);
    cfg.rival.policy = Some(file);
    let mut env = RaceEnv::new(f1_esp(), cfg).unwrap();
    let start = positions(&mut env, 1, Context::default(), 0).0;
    let after = positions(&mut env, 1, Context::default(), 10).0;
    let rival = &env.cars()[1];
    assert!(rival.vehicle.speed() > 2.0, "{}", rival.vehicle.speed());
    assert!(
        after[2] - start[2] > 1.0,
        "the rival drove along the straight: {start:?} {after:?}"
    );
}

#[test]
fn a_missing_or_unfit_agent_is_refused_by_name() {
    let track = f1_esp();
    let mut cfg = policy_race(1);
    cfg.rival.policy = None;
    let err = RaceEnv::new(track.clone(), cfg).err().unwrap().to_string();
    assert!(err.contains("[rival] policy = \"RUN_DIR\""), "{err}");

    let mut cfg = policy_race(1);
    cfg.rival.policy = Some(PathBuf::from("no/such/run"));
    let err = RaceEnv::new(track.clone(), cfg).err().unwrap();
    let chain = anyhow_like(&err);
    assert!(chain.contains("[rival] policy = no/such/run"), "{chain}");
    assert!(chain.contains("neither a checkpoint"), "{chain}");

    let mut cfg = policy_race(1);
    cfg.lidar.beams = 54;
    let err = RaceEnv::new(track, cfg).err().unwrap();
    let chain = anyhow_like(&err);
    assert!(chain.contains("[lidar] beams"), "{chain}");
}

/// An error and its sources, as the binary prints them.
fn anyhow_like(err: &dyn std::error::Error) -> String {
    let mut text = err.to_string();
    let mut source = err.source();
    while let Some(s) = source {
        text += &format!(": {s}");
        source = s.source();
    }
    text
}
