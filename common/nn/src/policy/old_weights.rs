//! The acting policies on weights written by an older ctxrace (commit d6b5c40, the last before
//! the networks were rewritten over a named-parameter store): they must load, and act as that
//! code did. `testdata/d6b5c40/` holds each algorithm's `best/` policy from a tiny run of that
//! binary (its README says how they were made) and `expected.toml` the decisions that code
//! computed for the observations below.

use super::{Decision, Policy};
use ctxrace_config::agents::AgentConfig;
use std::collections::BTreeMap;
use std::path::PathBuf;

/// LiDAR values per frame in the fixture's runs.
const FRAME_DIM: usize = 108;
/// Decisions per episode.
const STEPS: usize = 4;
/// The raw context every decision sees.
const CONTEXT: [f32; 2] = [0.3, -0.1];
/// Seed of the sampled episode's noise.
const SEED: u64 = 7;
/// Largest difference allowed from the recorded decisions: what reordering a sum of floats
/// changes, far below what a different weight or a misread tensor changes.
const TOLERANCE: f32 = 1e-5;

/// The recorded decisions of one policy: each its action then, for cMask, its mask.
#[derive(Debug, serde::Deserialize, serde::Serialize)]
struct Recorded {
    deterministic: Vec<Vec<f32>>,
    sampled: Vec<Vec<f32>>,
}

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../testdata/d6b5c40")
}

/// A smooth, distinct observation for step `t`.
fn observation(t: usize) -> Vec<f32> {
    (0..FRAME_DIM)
        .map(|i| 0.5 + 0.4 * (0.37 * i as f32 + 1.3 * t as f32).sin())
        .collect()
}

fn flat(d: Decision) -> Vec<f32> {
    let mut v = d.action.to_vec();
    v.extend(d.mask.into_iter().flatten());
    v
}

/// An episode of [`STEPS`] decisions of `policy`, from a reset and reseeded policy.
fn episode(policy: &mut Policy, deterministic: bool) -> Vec<Vec<f32>> {
    policy.reset();
    policy.reseed(SEED);
    (0..STEPS)
        .map(|t| flat(policy.act(&observation(t), CONTEXT, deterministic).unwrap()))
        .collect()
}

/// The fixture's policy of `algo` as the current code acts with it.
fn act(algo: &str) -> Recorded {
    let dir = fixture().join(algo);
    let agent: AgentConfig =
        toml::from_str(&std::fs::read_to_string(dir.join("agent.toml")).unwrap()).unwrap();
    let weights = std::fs::read(dir.join("policy.safetensors")).unwrap();
    let mut policy = Policy::new(&agent, FRAME_DIM, &weights, 0).unwrap();
    Recorded {
        deterministic: episode(&mut policy, true),
        sampled: episode(&mut policy, false),
    }
}

#[test]
fn policies_written_by_d6b5c40_load_and_act_as_that_code_did() {
    let text = std::fs::read_to_string(fixture().join("expected.toml")).unwrap();
    let expected: BTreeMap<String, Recorded> = toml::from_str(&text).unwrap();
    assert_eq!(expected.len(), 4, "one record per algorithm");
    for (algo, want) in &expected {
        let got = act(algo);
        for (kind, got, want) in [
            ("deterministic", &got.deterministic, &want.deterministic),
            ("sampled", &got.sampled, &want.sampled),
        ] {
            assert_eq!(got.len(), STEPS, "{algo} {kind}");
            for (t, (g, w)) in got.iter().zip(want).enumerate() {
                assert_eq!(g.len(), w.len(), "{algo} {kind} step {t}: {g:?} vs {w:?}");
                let worst = g
                    .iter()
                    .zip(w)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f32::max);
                assert!(
                    worst <= TOLERANCE,
                    "{algo} {kind} step {t}: {g:?}, recorded {w:?}"
                );
            }
        }
    }
}
