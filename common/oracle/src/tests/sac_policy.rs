use crate::{ParamStore, TanhGaussianActor};
use candle_core::{Device, Tensor};
use ctxrace_config::agents::SacConfig;
use ctxrace_nn::policy::{PolicyError, SacPolicy};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// The actor acts as the candle module the learner's weights come from (the
/// oracle), deterministic and sampled, at batch 1.
#[test]
fn acts_as_the_candle_actor() {
    let cfg = SacConfig {
        hidden: 8,
        ..SacConfig::default()
    };
    let store = ParamStore::new();
    let oracle = TanhGaussianActor::new(6, 2, 8, cfg.layers, store.builder())
        .unwrap()
        .with_log_std_clamp(cfg.log_std_clamp);
    store.init(5).unwrap();
    let mut policy = SacPolicy::new(&cfg, 3, 2, &store.to_bytes().unwrap(), 9).unwrap();
    let frame = [0.1, -0.4, 0.7];
    let x = Tensor::from_slice(&[frame, frame].concat(), (1, 6), &Device::Cpu).unwrap();
    let values = |t: Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let noise: Vec<f32> = (0..2).map(|_| rng.sample(StandardNormal)).collect();
    let noise = Tensor::from_vec(noise, (1, 2), &Device::Cpu).unwrap();
    let want = [
        values(oracle.mean_action(&x).unwrap()),
        values(oracle.sample(&x, &noise).unwrap().0),
    ];
    for (deterministic, want) in [true, false].into_iter().zip(want) {
        policy.reset();
        policy.reseed(9);
        let got = policy.act(&frame, deterministic).unwrap();
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() <= 1e-6, "{got:?} vs {want:?}");
        }
    }
}

fn policy(frames: usize) -> SacPolicy {
    policy_of(SacConfig {
        frames,
        ..SacConfig::default()
    })
}

/// The policy of `cfg` (8 hidden units) for frames of 3 values and actions of 2.
fn policy_of(cfg: SacConfig) -> SacPolicy {
    let cfg = SacConfig { hidden: 8, ..cfg };
    let frames = cfg.frames;
    let store = ParamStore::new();
    TanhGaussianActor::new(3 * frames, 2, 8, 2, store.builder()).unwrap();
    store.init(5).unwrap();
    SacPolicy::new(&cfg, 3, 2, &store.to_bytes().unwrap(), 0).unwrap()
}

#[test]
fn first_frame_fills_the_stack_and_reset_clears_it() {
    let mut p = policy(2);
    let a = p.act(&[0.1, 0.2, 0.3], true).unwrap();
    let b = p.act(&[0.1, 0.2, 0.3], true).unwrap();
    assert_eq!(a, b, "a repeated frame equals the filled stack");
    let c = p.act(&[0.9, 0.9, 0.9], true).unwrap();
    p.reset();
    let d = p.act(&[0.9, 0.9, 0.9], true).unwrap();
    assert_ne!(c, d, "after reset the stack holds only the new frame");
    assert_eq!(
        p.act(&[0.0; 2], true),
        Err(PolicyError::Observation { found: 2, want: 3 }),
        "an observation of another size is refused, naming both sizes"
    );
}

/// With `reset_frame_stack = false` (the paper's code) an episode's first observation is
/// stacked behind the previous episode's last: the first action after the reset is the one
/// of the stack `[old, new]`, not of `[new, new]`.
#[test]
fn the_paper_codes_frame_stack_carries_across_an_episode_boundary() {
    let cfg = SacConfig {
        reset_frame_stack: false,
        ..SacConfig::default()
    };
    let (old, new) = ([0.1, 0.2, 0.3], [0.9, 0.9, 0.9]);
    let mut kept = policy_of(cfg);
    kept.act(&old, true).unwrap();
    kept.reset();
    let carried = kept.act(&new, true).unwrap();
    let mut fresh = policy(2);
    fresh.act(&old, true).unwrap();
    let across = fresh.act(&new, true).unwrap();
    fresh.reset();
    let restarted = fresh.act(&new, true).unwrap();
    assert_eq!(carried, across, "the stack [old, new] survives the reset");
    assert_ne!(carried, restarted);
}

/// `explore_noise` moves even the deterministic action by about its standard deviation and
/// keeps it in `[−1, 1]`; without it the deterministic action is repeatable.
#[test]
fn exploration_noise_perturbs_every_action_within_the_bounds() {
    let frame = [0.1, 0.2, 0.3];
    let mean = policy(2).act(&frame, true).unwrap();
    for deterministic in [true, false] {
        let mut quiet = policy(2);
        let mut noisy = policy_of(SacConfig {
            explore_noise: 0.1,
            ..SacConfig::default()
        });
        let mut sq = 0.0;
        for _ in 0..400 {
            let (q, n) = (
                quiet.act(&frame, deterministic).unwrap(),
                noisy.act(&frame, deterministic).unwrap(),
            );
            assert!(n.iter().all(|a| (-1.0..=1.0).contains(a)));
            if deterministic {
                assert_eq!(q, mean);
                sq += n.iter().zip(&q).map(|(n, q)| (n - q).powi(2)).sum::<f32>();
            }
        }
        if deterministic {
            let std = (sq / 800.0).sqrt();
            assert!((std - 0.1).abs() < 0.02, "noise std {std}");
        }
    }
}
