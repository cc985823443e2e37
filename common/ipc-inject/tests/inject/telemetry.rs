//! The launcher's telemetry under falsified records: implausible episode reports, heartbeats
//! and replay statuses, and plausible ones forged without the run's key, are rejected by
//! reason; the real ones before and after are taken.

use ctxrace_ipc::wire::{Sealed, FORMAT_VERSION, REASONS};
use ctxrace_ipc::{
    EpisodeReport, Heartbeat, ReplayStatus, RunBounds, RunTransport, TelemetrySubscriber,
};
use ctxrace_ipc_inject::Injector;

use crate::test_key;

use ctxrace_ipc::wire::named_reasons;
use ctxrace_ipc::{Isolated, RunKey};
use std::collections::BTreeMap;

const BOUNDS: RunBounds = RunBounds {
    max_policy_version: 1000,
    max_episode_steps: 2400,
    context_range: 0.15,
    replay_capacity: 5000,
    rivals: 1,
};

/// The launcher's telemetry and an injector on a run of `actors` actors of the test's own
/// prefix `name`, the prefix first: bound in this order, it is dropped (and cleaned up)
/// last.
fn launcher_view(
    name: &str,
    actors: usize,
) -> (Isolated, RunTransport, TelemetrySubscriber, Injector) {
    let isolated = Isolated::new(name);
    let t = RunTransport::open(&isolated.0, actors, "launcher", &test_key()).unwrap();
    let telemetry = TelemetrySubscriber::new(&t, BOUNDS).unwrap();
    let inject = Injector::new(&t).unwrap();
    (isolated, t, telemetry, inject)
}

fn reasons(t: &TelemetrySubscriber) -> BTreeMap<&'static str, u64> {
    named_reasons(&t.rejected_by_reason())
}

/// `m` sealed with the run's key, as a process of the run sends it.
fn seal<T: Sealed>(m: T) -> T {
    m.seal_with(&test_key(), &[])
}

/// `m` sealed by a process without the run's key: its CRC-32 right, its tag not.
fn forged<T: Sealed>(m: T) -> T {
    m.seal_with(&RunKey::from_bytes([3; ctxrace_ipc::KEY_LEN]), &[])
}

/// Issue 47's falsified records: episode reports claiming env steps 9.2e17 or 2^64-1, PG
/// 2.97e34 and other values no actor produces are rejected by reason, and none of them
/// becomes a record; so are a plausible report forged without the run's key and one of
/// another process than the actor's; the actor's real reports before and after are taken.
#[test]
fn implausible_episode_reports_are_rejected_and_the_real_ones_taken() {
    let (_isolated, _t, mut telemetry, inject) = launcher_view("telemetry-episodes", 2);
    let real = |env_steps, steps| EpisodeReport {
        format_version: FORMAT_VERSION,
        actor_id: 0,
        episode_id: 0,
        env_steps,
        steps,
        context: [0.15, -0.1],
        progress: 0.4,
        overtakes: 1,
        episode_return: 12.5,
        pid: 4242,
        ..Default::default()
    };
    inject.episode(seal(real(100, 100))).unwrap();
    // before its start is known
    assert_eq!(telemetry.episodes().unwrap(), vec![]);
    telemetry.actor_started(0, 4242);
    let hostile = [
        real(9_200_000_000_000_000_000, 100),
        real(u64::MAX, 100),
        EpisodeReport {
            progress: 2.97e34,
            ..real(200, 100)
        },
        real(200, 0),
        real(200, 2401),
        EpisodeReport {
            context: [0.5, 0.0],
            ..real(200, 100)
        },
        EpisodeReport {
            overtakes: 101,
            ..real(200, 100)
        },
        EpisodeReport {
            episode_return: 1e30,
            ..real(200, 100)
        },
        EpisodeReport {
            progress: f32::NAN,
            ..real(200, 100)
        },
        EpisodeReport {
            actor_id: 7,
            ..real(200, 100)
        },
        EpisodeReport {
            pid: 1,
            ..real(200, 100)
        },
    ];
    inject.episode(seal(real(100, 100))).unwrap();
    for m in hostile {
        inject.episode(seal(m)).unwrap();
    }
    inject.episode(forged(real(200, 100))).unwrap();
    // env steps going back, then the actor's next real episode
    inject.episode(seal(real(150, 100))).unwrap();
    inject.episode(seal(real(300, 200))).unwrap();
    let got: Vec<u64> = telemetry
        .episodes()
        .unwrap()
        .iter()
        .map(|m| m.env_steps)
        .collect();
    assert_eq!(got, vec![100, 300]);
    let want = [
        ("implausible", 10),
        ("value", 1),
        ("unknown_actor", 1),
        ("backwards", 1),
        ("unauthenticated", 1),
    ];
    assert_eq!(reasons(&telemetry), want.into_iter().collect());
    assert_eq!(telemetry.rejected(), 14);
}

/// Heartbeats of another process than the actor's, with a policy version ahead of the
/// learner's newest (2^64-1 among them), more steps than an actor takes in the time, or more
/// dropped than taken are rejected, and so is a plausible one forged without the run's key;
/// the real ones are taken, and a restart starts the actor's history again.
#[test]
fn implausible_heartbeats_are_rejected() {
    let (_isolated, _t, mut telemetry, inject) = launcher_view("telemetry-heartbeats", 1);
    telemetry.actor_started(0, 4242);
    let real = |env_steps, policy_version| Heartbeat {
        format_version: FORMAT_VERSION,
        actor_id: 0,
        pid: 4242,
        env_steps,
        policy_version,
        ..Default::default()
    };
    let beats = [
        real(500, 20),
        Heartbeat {
            pid: 1,
            ..real(600, 20)
        },
        real(600, u64::MAX),
        real(600, 31),
        real(u64::MAX, 20),
        real(9_200_000_000_000_000_000, 20),
        Heartbeat {
            dropped_steps: 700,
            ..real(600, 20)
        },
        real(400, 20),
        real(700, 30),
    ];
    for b in beats {
        inject.heartbeat(seal(b)).unwrap();
    }
    inject.heartbeat(forged(real(600, 20))).unwrap();
    let mut asked = 0;
    let got: Vec<(u64, u64)> = telemetry
        .heartbeats(|| {
            asked += 1;
            30
        })
        .unwrap()
        .iter()
        .map(|b| (b.env_steps, b.policy_version))
        .collect();
    assert_eq!(got, vec![(500, 20), (700, 30)]);
    assert_eq!(asked, 1);
    let want = [("implausible", 6), ("backwards", 1), ("unauthenticated", 1)];
    assert_eq!(reasons(&telemetry), want.into_iter().collect());
    // a restarted actor counts from 0 again, as a new process
    telemetry.actor_started(0, 4343);
    inject
        .heartbeat(seal(Heartbeat {
            pid: 4343,
            ..real(10, 30)
        }))
        .unwrap();
    assert_eq!(telemetry.heartbeats(|| 30).unwrap().len(), 1);
}

/// Replay statuses with 4.3e9 dropped chunks, inserts going back or faster than the actors
/// step, another capacity or rejections that do not add up are rejected; the replay's real
/// statuses before and after are taken, and neither a status forged without the run's key
/// nor one of another process than the replay's moves its history. A restarted replay
/// restores at most what the one before had stored.
#[test]
fn implausible_replay_statuses_are_rejected() {
    let (_isolated, _t, mut telemetry, inject) = launcher_view("telemetry-status", 2);
    telemetry.replay_started(77);
    let real = |inserted| ReplayStatus {
        format_version: FORMAT_VERSION,
        pid: 77,
        inserted,
        fill: inserted.min(5000),
        capacity: 5000,
        sampled: inserted,
        batches: inserted / 10,
        ..Default::default()
    };
    let mut by_reason = [0; REASONS.len()];
    by_reason[3] = 1;
    let statuses = [
        real(1000),
        ReplayStatus {
            dropped_chunks: 4_300_000_000,
            ..real(1100)
        },
        real(900),
        real(u64::MAX),
        ReplayStatus {
            capacity: 1 << 40,
            ..real(1100)
        },
        ReplayStatus {
            rejected: 7,
            rejected_by_reason: by_reason,
            ..real(1100)
        },
        ReplayStatus {
            fill: 5001,
            ..real(6000)
        },
        ReplayStatus {
            pid: 78,
            ..real(1100)
        },
        forged(real(1100)),
        real(1200),
    ];
    let mut taken = Vec::new();
    for s in statuses {
        // the forged one is sealed already (sealing it again would make it real)
        let s = if s.tag == [0; ctxrace_ipc::wire::TAG_LEN] {
            seal(s)
        } else {
            s
        };
        inject.status(s).unwrap();
        if let Some(s) = telemetry.replay_status().unwrap() {
            taken.push(s.inserted);
        }
    }
    assert_eq!(taken, vec![1000, 1200]);
    let want = [("implausible", 6), ("backwards", 1), ("unauthenticated", 1)];
    assert_eq!(reasons(&telemetry), want.into_iter().collect());
    telemetry.replay_started(78);
    inject
        .status(seal(ReplayStatus {
            restored_inserts: 5000,
            pid: 78,
            ..real(5000)
        }))
        .unwrap();
    assert_eq!(telemetry.replay_status().unwrap(), None);
    // a copy of the replay's predecessor's status, then the restarted replay's own
    inject.status(seal(real(1180))).unwrap();
    assert_eq!(telemetry.replay_status().unwrap(), None);
    inject
        .status(seal(ReplayStatus {
            restored_inserts: 1100,
            pid: 78,
            ..real(1150)
        }))
        .unwrap();
    assert_eq!(
        telemetry.replay_status().unwrap().map(|s| s.inserted),
        Some(1150)
    );
}
