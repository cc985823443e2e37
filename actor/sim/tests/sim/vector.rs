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

/// Resets `vector` from `seed` and steps it `steps` times with `actions` (one per lane); every
/// observation and outcome, the reset's first.
fn run(
    vector: &mut RaceVector,
    seed: u64,
    actions: &[[f64; 2]],
    steps: usize,
) -> (Vec<f32>, Vec<EnvOutcome>) {
    let lanes = vector.lanes();
    let mut obs = vec![0.0; lanes * vector.obs_dim()];
    let mut out = vec![EnvOutcome::default(); lanes];
    vector.reset(seed, None, &mut obs, &mut out).unwrap();
    let (mut all_obs, mut all_out) = (obs.clone(), out.clone());
    for _ in 0..steps {
        vector.step(actions, &mut obs, &mut out).unwrap();
        all_obs.extend_from_slice(&obs);
        all_out.extend_from_slice(&out);
    }
    (all_obs, all_out)
}

/// A steady action per env, each steering differently at 80% speed.
fn steady(envs: usize) -> Vec<[f64; 2]> {
    (0..envs).map(|i| [0.1 * i as f64 - 0.2, 0.8]).collect()
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
    let (obs_one, out_one) = run(&mut one, 5, &steady(5), 80);
    let (obs_two, out_two) = run(&mut two, 5, &steady(5), 80);
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

/// With two agents a race, each race's lanes are a lone two-agent race of its seed, but for
/// black death: an agent that crashed reports zeros, reward 0 and no flag until the race ends,
/// when every lane of it reports the end; the next step restarts every lane. Threads change
/// nothing, and same-step autoreset keeps the ended lanes' last observations.
#[test]
fn lanes_are_the_races_agents_with_black_death_until_the_race_ends() {
    let (cfg, track) = (RaceConfig::default(), generated());
    let vector = |threads| {
        RaceVector::new(track.clone(), &cfg, 2, 0.15, threads)
            .unwrap()
            .with_agents(2)
            .unwrap()
    };
    let mut two = vector(2);
    assert_eq!((two.len(), two.agents(), two.lanes()), (2, 2, 4));
    // the ego at full right lock and full speed (into the wall), the other agent straight
    let actions = [[1.0, 1.0], [0.0, 0.3], [1.0, 1.0], [0.0, 0.3]];
    let steps = 120;
    let (obs, out) = run(&mut two, 40, &actions, steps);
    let again = run(&mut vector(1), 40, &actions, steps);
    assert_eq!(again, (obs.clone(), out.clone()));
    let dim = two.obs_dim();
    let (row, lane) = (
        |k: usize, l: usize| &obs[(k * 4 + l) * dim..][..dim],
        |k: usize, l| out[k * 4 + l],
    );
    // race 1 (lanes 2, 3) against a lone race of seed 41 in the context it drew
    let mut lone = RaceEnv::new(track.clone(), cfg.clone()).unwrap();
    lone.set_agents(2).unwrap();
    let first = lone.reset(41, lane(0, 2).context);
    assert_eq!(first, row(0, 2));
    assert_eq!(lone.observe_agent(1), row(0, 3));
    let (mut crashed, mut black) = (false, 0);
    let mut k = 1;
    while !lone.is_finished() {
        let step = lone.step_agents(&[[1.0, 1.0], [0.0, 0.3]]).unwrap();
        for (i, s) in step.iter().enumerate() {
            let o = lane(k, 2 + i);
            assert_eq!(s.obs, row(k, 2 + i), "step {k} agent {i}");
            assert_eq!(s.reward.to_bits(), o.reward.to_bits());
        }
        let ego = lane(k, 2);
        if crashed && !lone.is_finished() {
            assert!(
                !ego.terminated && !ego.truncated && ego.reward == 0.0,
                "{ego:?}"
            );
            assert!(row(k, 2).iter().all(|&v| v == 0.0));
            black += 1;
        }
        crashed |= step[0].terminated;
        if lone.is_finished() {
            assert!((2..4).all(|l| lane(k, l).terminated || lane(k, l).truncated));
        }
        k += 1;
    }
    assert!(
        crashed && black > 0,
        "the ego crashed before the race ended: {black} steps"
    );
    // the step after the end restarts both lanes
    assert!((2..4).all(|l| lane(k, l).reward == 0.0 && !lane(k, l).terminated));
    assert!(k < steps, "the race ended within the run");

    let mut same = vector(2).with_autoreset(Autoreset::SameStep);
    let mut obs_same = vec![0.0; 4 * dim];
    let mut out_same = vec![EnvOutcome::default(); 4];
    same.reset(40, None, &mut obs_same, &mut out_same).unwrap();
    for j in 1..k {
        same.step(&actions, &mut obs_same, &mut out_same).unwrap();
        assert_eq!(out_same[2..], out[j * 4 + 2..j * 4 + 4]);
    }
    assert_eq!(
        &same.final_obs()[2 * dim..],
        &obs[((k - 1) * 4 + 2) * dim..][..2 * dim]
    );
    assert_eq!(&obs_same[2 * dim..], &obs[(k * 4 + 2) * dim..][..2 * dim]);
}

#[test]
fn too_many_agents_for_the_race_are_refused() {
    let vector = RaceVector::new(generated(), &RaceConfig::default(), 2, 0.15, 1).unwrap();
    let err = vector.with_agents(3).err().unwrap().to_string();
    assert!(err.contains("agent"), "{err}");
}
