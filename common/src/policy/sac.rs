//! SAC's acting side: the tanh-Gaussian actor on the last `frames` LiDAR frames stacked
//! (oldest first; at an episode's start the first frame fills the stack).

use crate::agents::SacConfig;
use crate::nn::{ParamStore, TanhGaussianActor};
use candle_core::{bail, Device, Result, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::collections::VecDeque;

/// The SAC actor at batch 1 with its frame stack.
pub struct SacPolicy {
    store: ParamStore,
    actor: TanhGaussianActor,
    frame_dim: usize,
    act_dim: usize,
    frames: usize,
    stack: VecDeque<Vec<f32>>,
    rng: ChaCha8Rng,
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
        let store = ParamStore::new();
        let actor = TanhGaussianActor::new(
            frame_dim * cfg.frames,
            act_dim,
            cfg.hidden,
            cfg.layers,
            store.builder(),
        )?;
        store.load_bytes(weights)?;
        Ok(Self {
            store,
            actor,
            frame_dim,
            act_dim,
            frames: cfg.frames,
            stack: VecDeque::with_capacity(cfg.frames),
            rng: ChaCha8Rng::seed_from_u64(seed),
        })
    }

    /// Replaces the weights (same architecture) without clearing the frame stack.
    pub fn load(&mut self, weights: &[u8]) -> Result<()> {
        self.store.load_bytes(weights)
    }

    /// Restarts the sampling noise from `seed`.
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// Starts a new episode: empties the frame stack.
    pub fn reset(&mut self) {
        self.stack.clear();
    }

    /// The action in `[−1, 1]^A` for the newest frame `obs`: `tanh μ` if `deterministic`, else a
    /// sample.
    pub fn act(&mut self, obs: &[f32], deterministic: bool) -> Result<Vec<f32>> {
        if obs.len() != self.frame_dim {
            bail!(
                "observation has {} values, the SAC policy expects {}",
                obs.len(),
                self.frame_dim
            );
        }
        while self.stack.len() < self.frames - 1 {
            self.stack.push_back(obs.to_vec());
        }
        if self.stack.len() == self.frames {
            self.stack.pop_front();
        }
        self.stack.push_back(obs.to_vec());
        let stacked: Vec<f32> = self.stack.iter().flatten().copied().collect();
        let x = Tensor::from_vec(stacked, (1, self.frame_dim * self.frames), &Device::Cpu)?;
        let action = if deterministic {
            self.actor.mean_action(&x)?
        } else {
            let noise: Vec<f32> = (0..self.act_dim)
                .map(|_| self.rng.sample(StandardNormal))
                .collect();
            let noise = Tensor::from_vec(noise, (1, self.act_dim), &Device::Cpu)?;
            self.actor.sample(&x, &noise)?.0
        };
        action.flatten_all()?.to_vec1::<f32>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn policy(frames: usize) -> SacPolicy {
        let cfg = SacConfig {
            hidden: 8,
            frames,
            ..SacConfig::default()
        };
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
        assert!(p.act(&[0.0; 2], true).is_err());
    }
}
