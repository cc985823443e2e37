//! Multi-agent races (`RaceEnv::set_agents`, `step_agents`) on a generated track: one agent is
//! the single-agent race bit for bit, two pure-pursuit agents race until the first completes
//! the lap, an agent that crashes drops out while the race goes on, and wrong counts are
//! refused by name.

use ctxrace_config::{Context, RaceConfig};
use ctxrace_sim::rival::PurePursuit;
use ctxrace_sim::{AgentStep, RaceEnv};
use ctxrace_tracks::{Track, TrackOptions};
use std::sync::Arc;

fn race(rivals: usize) -> RaceEnv {
    let track = Arc::new(Track::load("generated:1", &TrackOptions::default()).unwrap());
    let cfg = RaceConfig {
        rivals,
        ..RaceConfig::default()
    };
    RaceEnv::new(track, cfg).unwrap()
}

/// A pure-pursuit driver for each agent, at the line's speed capped at 4 m/s.
fn drivers(env: &RaceEnv) -> Vec<PurePursuit> {
    let cfg = env.config();
    let wheelbase = env.vehicle_params().wheelbase();
    (0..env.agents())
        .map(|_| PurePursuit::full_speed(&cfg.rival, 4.0, wheelbase, cfg.max_steer))
        .collect()
}

/// Each agent's pure-pursuit action.
fn actions(env: &RaceEnv, drivers: &mut [PurePursuit]) -> Vec<[f64; 2]> {
    let raceline = &env.track().raceline;
    drivers
        .iter_mut()
        .zip(env.cars())
        .map(|(d, car)| {
            let (steer, speed) = d.command(raceline, &car.vehicle.state);
            env.command_to_action(steer, speed)
        })
        .collect()
}

/// Races every agent with pure pursuit from `seed` to the end; every step's outcomes.
fn pure_pursuit_race(env: &mut RaceEnv, seed: u64) -> Vec<Vec<AgentStep>> {
    env.reset(seed, Context::default());
    let mut pp = drivers(env);
    let mut steps = Vec::new();
    while !env.is_finished() {
        let a = actions(env, &mut pp);
        steps.push(env.step_agents(&a).unwrap());
    }
    steps
}

#[test]
fn one_agent_is_the_single_agent_race_bit_for_bit() {
    let (mut single, mut multi) = (race(2), race(2));
    multi.set_agents(1).unwrap();
    let ctx = Context {
        speed: 0.2,
        steer: -0.1,
    };
    assert_eq!(single.reset(5, ctx), multi.reset(5, ctx));
    let mut pp = drivers(&single);
    while !single.is_finished() {
        let a = actions(&single, &mut pp);
        let s = single.step(a[0]).unwrap();
        let m = multi.step_agents(&a).unwrap().remove(0);
        assert_eq!(s.obs, m.obs);
        assert_eq!(s.reward.to_bits(), m.reward.to_bits());
        assert_eq!((s.terminated, s.truncated), (m.terminated, m.truncated));
        assert_eq!(s.info, m.info);
        assert_eq!(single.is_finished(), multi.is_finished());
    }
}

#[test]
fn two_agents_race_until_the_first_completes_the_lap() {
    let mut env = race(2);
    env.set_agents(2).unwrap();
    let steps = pure_pursuit_race(&mut env, 3);
    let last = steps.last().unwrap();
    assert!(last.iter().any(|o| o.info.lap_complete), "{last:?}");
    assert!(last.iter().all(|o| o.terminated && !o.truncated));
    // the agent starting ahead (car 1) has the head start and keeps it at the same speed
    assert!(last[1].info.lap_complete && last[1].info.progress == 1.0);
    assert!(last[0].info.progress > 0.8 && !last[0].info.lap_complete);
    // the same seed races the same
    let again = pure_pursuit_race(&mut env, 3);
    assert_eq!(steps.len(), again.len());
    for (a, b) in steps.iter().flatten().zip(again.iter().flatten()) {
        assert_eq!((&a.obs, a.reward.to_bits()), (&b.obs, b.reward.to_bits()));
    }
    // each agent's scan sees the other: their observations differ
    assert_ne!(steps[5][0].obs, steps[5][1].obs);
}

#[test]
fn an_agent_that_crashes_drops_out_and_the_race_goes_on() {
    let mut env = race(1);
    env.set_agents(2).unwrap();
    env.reset(1, Context::default());
    let mut pp = drivers(&env);
    let mut crashed_at = None;
    for k in 0..400 {
        let mut a = actions(&env, &mut pp);
        a[0] = [1.0, 1.0]; // the ego at full right lock, full speed: into the wall
        let out = env.step_agents(&a).unwrap();
        if crashed_at.is_none() && out[0].terminated {
            assert!(
                out[0].info.wall_crash && out[0].reward < 0.0,
                "{:?}",
                out[0]
            );
            crashed_at = Some(k);
        } else if crashed_at.is_some() {
            assert!(out[0].terminated && out[0].reward == 0.0);
            assert!(out[0].obs.iter().all(|&v| v == 0.0));
            assert!(!out[1].terminated || out[1].info.lap_complete);
        }
        if env.is_finished() {
            break;
        }
    }
    assert!(crashed_at.is_some(), "the ego never reached the wall");
    // the race's metrics are the ego's: what ended its episode, and how far it got
    assert!(env.metrics().wall_crash && env.metrics().lap_time.is_none());
    assert_eq!(env.metrics().ended_by(), "wall crash");
    let other = &env.cars()[1];
    assert!(
        !other.crashed && other.travelled > 30.0,
        "agent 1 raced on: {}",
        other.travelled
    );
}

#[test]
fn wrong_agent_counts_are_refused_by_name() {
    let mut env = race(1);
    for bad in [0, 3] {
        let err = env.set_agents(bad).unwrap_err().to_string();
        assert!(
            err.contains(&format!("agents = {bad} must be 1 to 2")),
            "{err}"
        );
    }
    env.set_agents(2).unwrap();
    env.reset(0, Context::default());
    let err = env.step([0.0, 0.0]).unwrap_err().to_string();
    assert!(err.contains("step_agents"), "{err}");
    let err = env.step_agents(&[[0.0, 0.0]]).unwrap_err().to_string();
    assert!(
        err.contains("1 action(s) for a race of 2 agent(s)"),
        "{err}"
    );
    let err = env.step_agents(&[[0.0, 0.0], [f64::NAN, 0.0]]).unwrap_err();
    assert!(err.to_string().contains("not finite"), "{err}");
}
