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

    /// The actor: a ReLU MLP from the stacked frames to the means, then the log-σs.
    pub fn actor(&self) -> &Mlp {
        &self.actor
    }

    /// Frames stacked into the actor's input (oldest first).
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Values in one frame.
    pub fn frame_dim(&self) -> usize {
        self.frame_dim
    }

    /// Standard deviation of the noise added to every action, deterministic ones too (0: none).
    pub fn explore_noise(&self) -> f32 {
        self.explore_noise
    }

    /// Whether [`SacPolicy::reset`] empties the frame stack (else it carries on into the next
    /// episode).
    pub fn resets_frame_stack(&self) -> bool {
        self.reset_frame_stack
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

    /// Its noise's position and the frames it keeps ([`super::CarriedState`]).
    pub fn carried(&self) -> super::CarriedState {
        super::CarriedState {
            rng_words: self.rng.get_word_pos(),
            frames: self.stack.iter().cloned().collect(),
        }
    }

    /// Takes up what a policy of the same architecture carried ([`SacPolicy::carried`]).
    pub fn carry(&mut self, state: &super::CarriedState) {
        self.rng.set_word_pos(state.rng_words);
        self.stack = state.frames.iter().cloned().collect();
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
