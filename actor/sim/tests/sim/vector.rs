//! `RaceVector`: each env races as a lone `RaceEnv` reset with the same seed, whatever the
//! number of threads; ended episodes reset on the next step, or in the same step when asked; bad
//! calls step nothing.

use ctxrace_config::{Context, RaceConfig};
use ctxrace_sim::vector::{Autoreset, EnvOutcome, RaceVector, VectorError};
use ctxrace_sim::RaceEnv;
use ctxrace_tracks::{Track, TrackOptions};
use std::sync::Arc;

fn generated() -> Arc<Track> {
    Arc::new(Track::load("generated:1", &TrackOptions::default()).unwrap())
}

/// Steps `vector` with a fixed action per env `steps` times; returns every observation and outcome.
fn run(vector: &mut RaceVector, steps: usize) -> (Vec<f32>, Vec<EnvOutcome>) {
    let n = vector.len();
    let mut obs = vec![0.0; n * vector.obs_dim()];
    let mut out = vec![EnvOutcome::default(); n];
    let (mut all_obs, mut all_out) = (Vec::new(), Vec::new());
    vector.reset(5, None, &mut obs, &mut out).unwrap();
    let actions: Vec<[f64; 2]> = (0..n).map(|i| [0.1 * i as f64 - 0.2, 0.8]).collect();
    for _ in 0..steps {
        vector.step(&actions, &mut obs, &mut out).unwrap();
        all_obs.extend_from_slice(&obs);
        all_out.extend_from_slice(&out);
    }
    (all_obs, all_out)
}

#[test]
fn each_env_is_the_lone_race_of_its_seed() {
    let cfg = RaceConfig {
        rivals: 2,
        ..Default::default()
    };
    let track = generated();
    let contexts = [
        Context::new(0.3, -0.2).unwrap(),
        Context::new(-0.1, 0.0).unwrap(),
    ];
    let mut vector = RaceVector::new(track.clone(), &cfg, 2, 0.15, 2).unwrap();
    let dim = vector.obs_dim();
    let mut obs = vec![0.0; 2 * dim];
    let mut out = vec![EnvOutcome::default(); 2];
    vector
        .reset(40, Some(&contexts), &mut obs, &mut out)
        .unwrap();
    let mut lone = RaceEnv::new(track, cfg).unwrap();
    assert_eq!(lone.reset(41, contexts[1]), obs[dim..]);
    assert_eq!(out[1].context, contexts[1]);
    for k in 0..30 {
        let action = [0.05 * (k % 7) as f64 - 0.15, 0.6];
        vector
            .step(&[[0.0, 0.0], action], &mut obs, &mut out)
            .unwrap();
        let step = lone.step(action).unwrap();
        assert_eq!(step.obs, obs[dim..], "step {k}");
        assert_eq!(step.reward.to_bits(), out[1].reward.to_bits());
        assert_eq!(step.terminated, out[1].terminated);
        if step.terminated {
            break;
        }
    }
}

#[test]
fn threads_change_nothing_and_ended_episodes_reset_on_the_next_step() {
    let cfg = RaceConfig::default();
    let track = generated();
    let mut one = RaceVector::new(track.clone(), &cfg, 5, 0.15, 1).unwrap();
    let mut two = RaceVector::new(track, &cfg, 5, 0.15, 2).unwrap();
    let (obs_one, out_one) = run(&mut one, 80);
    let (obs_two, out_two) = run(&mut two, 80);
    assert_eq!(obs_one, obs_two);
    assert_eq!(out_one, out_two);
    // full speed at a steady steering angle ends in a wall well within 80 decisions
    let ended = out_one
        .iter()
        .position(|o| o.terminated)
        .expect("an episode ends");
    let next = out_one[ended + 5];
    assert_eq!(
        (next.reward, next.terminated, next.progress),
        (0.0, false, 0.0)
    );
    assert!(next.context.within(0.15));
    assert_ne!(
        next.context, out_one[ended].context,
        "a fresh context is drawn"
    );
}

/// Same-step autoreset is next-step autoreset without the reset step: the ended episode's last
/// observation goes to `final_obs`, the step returns the next episode's first, and the races go
/// on as they would have.
#[test]
fn same_step_autoreset_is_next_step_without_the_reset_step() {
    let (cfg, track) = (RaceConfig::default(), generated());
    let mut next = RaceVector::new(track.clone(), &cfg, 1, 0.15, 1).unwrap();
    let mut same = RaceVector::new(track, &cfg, 1, 0.15, 1)
        .unwrap()
        .with_autoreset(Autoreset::SameStep);
    let dim = next.obs_dim();
    let (mut obs_next, mut out_next) = (vec![0.0; dim], vec![EnvOutcome::default()]);
    let (mut obs_same, mut out_same) = (vec![0.0; dim], vec![EnvOutcome::default()]);
    next.reset(5, None, &mut obs_next, &mut out_next).unwrap();
    same.reset(5, None, &mut obs_same, &mut out_same).unwrap();
    let action = [[-0.2, 0.8]];
    let mut ended = 0;
    for _ in 0..200 {
        next.step(&action, &mut obs_next, &mut out_next).unwrap();
        same.step(&action, &mut obs_same, &mut out_same).unwrap();
        assert_eq!(out_same, out_next);
        if out_next[0].terminated || out_next[0].truncated {
            ended += 1;
            assert_eq!(same.final_obs(), obs_next.as_slice());
            // the step next-step autoreset spends on the reset
            next.step(&action, &mut obs_next, &mut out_next).unwrap();
            assert_eq!(same.contexts().next(), Some(out_next[0].context));
        }
        assert_eq!(obs_same, obs_next);
    }
    assert!(ended >= 2, "{ended} episodes ended");
}

#[test]
fn bad_calls_are_refused_and_step_nothing() {
    let mut vector = RaceVector::new(generated(), &RaceConfig::default(), 2, 0.15, 1).unwrap();
    let dim = vector.obs_dim();
    let (mut obs, mut out) = (vec![0.0; 2 * dim], vec![EnvOutcome::default(); 2]);
    let err = vector.step(&[[0.0; 2]; 2], &mut obs, &mut out).unwrap_err();
    assert!(matches!(err, VectorError::NotReset), "{err}");
    vector.reset(0, None, &mut obs, &mut out).unwrap();
    let first = obs.clone();
    let err = vector
        .step(&[[0.0, 1.0], [f64::NAN, 0.0]], &mut obs, &mut out)
        .unwrap_err();
    assert!(err.to_string().contains("env 1's action"), "{err}");
    assert_eq!(obs, first);
    let err = vector.step(&[[0.0; 2]], &mut obs, &mut out).unwrap_err();
    assert!(
        err.to_string()
            .contains("actions holds 1 values where 2 envs need 2"),
        "{err}"
    );
    assert!(RaceVector::new(generated(), &RaceConfig::default(), 0, 0.15, 1).is_err());
    assert!(RaceVector::new(generated(), &RaceConfig::default(), 1, 1.5, 1).is_err());
}
