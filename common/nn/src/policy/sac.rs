//! SAC's acting side: the tanh-Gaussian actor on the last `frames` LiDAR frames stacked
//! (oldest first; at an episode's start the first frame fills the stack, or with
//! `reset_frame_stack = false` the stack carries on from the previous episode as in the paper's
//! code), plus Gaussian exploration noise `explore_noise` (the code's `N(0, 0.1)`, then clipped
//! to `[−1, 1]`) when configured, in training and evaluation alike.
//!
//! The actor runs on the network the learner trains ([`Mlp`]), read from the
//! learner's weights by name ([`Weights`]).

use super::{PolicyError, Result};
use crate::tanh_gaussian::squash_rows;
use crate::{Activation, Mlp, MlpShape, MlpTrace, Weights};
use ctxrace_config::agents::SacConfig;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::collections::VecDeque;

/// The SAC actor at batch 1 with its frame stack.
pub struct SacPolicy {
    /// The actor's sizes, to read new weights with.
    shape: MlpShape,
    actor: Mlp,
    /// The actor's buffers for one row.
    trace: MlpTrace,
    /// Bounds of `log σ`.
    log_std_clamp: [f32; 2],
    frame_dim: usize,
    act_dim: usize,
    frames: usize,
    stack: VecDeque<Vec<f32>>,
    rng: ChaCha8Rng,
    /// Standard deviation of the noise added to every action (0: none).
    explore_noise: f32,
    /// Whether [`SacPolicy::reset`] empties the frame stack.
    reset_frame_stack: bool,
}

/// The actor of `shape` from the learner's weights (safetensors bytes).
fn read_actor(shape: &MlpShape, weights: &[u8]) -> Result<Mlp> {
    let mut weights = Weights::from_safetensors(weights)?;
    let actor = Mlp::from_weights(&mut weights, "", shape)?;
    weights.finish()?;
    Ok(actor)
}

impl SacPolicy {
    /// A policy of the architecture `cfg` for single frames of `frame_dim` values and actions of
    /// `act_dim`, with the learner's actor weights; `seed` seeds its sampling noise.
    pub fn new(
        cfg: &SacConfig,
        frame_dim: usize,
        act_dim: usize,
        weights: &[u8],
        seed: u64,
    ) -> Result<Self> {
        cfg.validate()?;
        // the learner's TanhGaussianActor: a ReLU MLP to the means, then the log-σs
        let shape = MlpShape {
            input: frame_dim * cfg.frames,
            units: cfg.hidden,
            layers: cfg.layers,
            out: Some(2 * act_dim),
            act: Activation::Relu,
        };
        let actor = read_actor(&shape, weights)?;
        Ok(Self {
            trace: actor.trace(1),
            actor,
            shape,
            log_std_clamp: cfg.log_std_clamp.map(|b| b as f32),
            frame_dim,
            act_dim,
            frames: cfg.frames,
            stack: VecDeque::with_capacity(cfg.frames),
            rng: ChaCha8Rng::seed_from_u64(seed),
            explore_noise: cfg.explore_noise as f32,
            reset_frame_stack: cfg.reset_frame_stack,
        })
    }

    /// Replaces the weights (same architecture) without clearing the frame stack.
    pub fn load(&mut self, weights: &[u8]) -> Result<()> {
        self.actor = read_actor(&self.shape, weights)?;
        Ok(())
    }

    /// Restarts the sampling noise from `seed`.
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// Starts a new episode: empties the frame stack (unless `reset_frame_stack` is off).
    pub fn reset(&mut self) {
        if self.reset_frame_stack {
            self.stack.clear();
        }
    }

    /// The action in `[−1, 1]^A` for the newest frame `obs`: `tanh μ` if `deterministic`, else a
    /// sample; plus the exploration noise, if any, clipped to `[−1, 1]`.
    pub fn act(&mut self, obs: &[f32], deterministic: bool) -> Result<Vec<f32>> {
        if obs.len() != self.frame_dim {
            return Err(PolicyError::Observation {
                found: obs.len(),
                want: self.frame_dim,
            });
        }
        while self.stack.len() < self.frames - 1 {
            self.stack.push_back(obs.to_vec());
        }
        if self.stack.len() == self.frames {
            self.stack.pop_front();
        }
        self.stack.push_back(obs.to_vec());
        let stacked: Vec<f32> = self.stack.iter().flatten().copied().collect();
        self.actor
            .forward(stacked.as_slice(), &mut self.trace, 0..1);
        let out = self.actor.output(&self.trace, 0..1);
        let mut action = vec![0f32; self.act_dim];
        if deterministic {
            for (a, mean) in action.iter_mut().zip(out) {
                *a = mean.tanh();
            }
        } else {
            let noise: Vec<f32> = (0..self.act_dim)
                .map(|_| self.rng.sample(StandardNormal))
                .collect();
            squash_rows(out, &noise, self.log_std_clamp, &mut action, &mut [0.0]);
        }
        if self.explore_noise > 0.0 {
            for a in &mut action {
                let n: f32 = self.rng.sample(StandardNormal);
                *a = (*a + self.explore_noise * n).clamp(-1.0, 1.0);
            }
        }
        Ok(action)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::oracle::{ParamStore, TanhGaussianActor};
    use candle_core::{Device, Tensor};

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
}
