//! DreamerV3's acting networks (encoder, RSSM, actor and cMask's mask actor) and the batch-1
//! policy that runs them in the actors: at each step the observation updates the posterior
//! state, the actor reads `[h, z, c]` and (cMask) the mask actor masks the context first.
//! The learner trains the same [`PolicyNets`] and ships their weights ("policy"); the policy
//! reads them by name and acts with the networks' forward passes at batch 1.

use super::{PolicyError, Result, ACT_DIM};
use crate::dreamer::{mask_value, uniform_rows, PolicyNets};
use crate::tanh_gaussian::squash_rows;
use crate::{sigmoid, symlog_value, MlpTrace, ObserveTrace, Weights, WeightsError};
use ctxrace_config::agents::{DreamerConfig, StepAlignment, CONTEXT_DIM};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// The networks that act, read by name from the policy weights `bytes` of `cfg` for
/// observations of `obs_dim` (safetensors, the names [`PolicyNets`] gives), every tensor used.
fn read_nets(
    cfg: &DreamerConfig,
    obs_dim: usize,
    bytes: &[u8],
) -> std::result::Result<PolicyNets, WeightsError> {
    let mut weights = Weights::from_safetensors(bytes)?;
    let nets = PolicyNets::from_weights(cfg, obs_dim, ACT_DIM, &mut weights)?;
    weights.finish()?;
    Ok(nets)
}

/// The buffers of one step, kept from step to step.
#[derive(Debug, Default)]
struct ActingTraces {
    /// `symlog o` (`symlog [o, a_{t−1}]` with [`StepAlignment::PaperCode`]).
    input: Vec<f32>,
    encoder: MlpTrace,
    rssm: ObserveTrace,
    /// `[h, z, c]`.
    head_input: Vec<f32>,
    actor: MlpTrace,
    mask: MlpTrace,
}

/// The acting side of DreamerV3 at batch 1: keeps the recurrent state and the previous action.
pub struct DreamerPolicy {
    cfg: DreamerConfig,
    obs_dim: usize,
    nets: PolicyNets,
    traces: ActingTraces,
    /// The state episodes start from, `(h_0, z_0)` ([`crate::Rssm::initial_state`] of the
    /// loaded weights).
    zero: (Vec<f32>, Vec<f32>),
    /// The posterior state `(h, z)`.
    state: (Vec<f32>, Vec<f32>),
    prev_action: [f32; ACT_DIM],
    /// Equal Gumbel noise (the sample is the most likely class), `[Z]`.
    uniform_mode: Vec<f32>,
    rng: ChaCha8Rng,
    /// cMask's mask when fixed instead of chosen ([`DreamerPolicy::fix_mask`]).
    fixed_mask: Option<[f32; CONTEXT_DIM]>,
}

impl DreamerPolicy {
    /// A policy of the architecture `cfg` for observations of `obs_dim`, with the bytes of
    /// the learner's policy weights; `seed` seeds its sampling noise.
    pub fn new(cfg: &DreamerConfig, obs_dim: usize, weights: &[u8], seed: u64) -> Result<Self> {
        cfg.validate()?;
        let nets = read_nets(cfg, obs_dim, weights)?;
        let mut policy = Self {
            cfg: cfg.clone(),
            obs_dim,
            nets,
            traces: ActingTraces::default(),
            zero: (Vec::new(), Vec::new()),
            state: (Vec::new(), Vec::new()),
            prev_action: [0.0; ACT_DIM],
            uniform_mode: vec![0.5; cfg.stoch * cfg.classes],
            rng: ChaCha8Rng::seed_from_u64(seed),
            fixed_mask: None,
        };
        policy.start_from_loaded();
        policy.reset();
        Ok(policy)
    }

    /// The initial state of the loaded weights, and the traces sized for them.
    fn start_from_loaded(&mut self) {
        let (nets, tr) = (&self.nets, &mut self.traces);
        let (h, z) = nets.rssm.initial_state(&mut tr.rssm);
        self.zero = (h.to_vec(), z.to_vec());
        tr.encoder = nets.encoder.trace(1);
        tr.actor = nets.actor.trace(1);
        if let Some(mask) = &nets.mask {
            tr.mask = mask.trace(1);
        }
    }

    /// Replaces the weights (same architecture) without resetting the state (the next
    /// episode starts from the new weights' initial state).
    pub fn load(&mut self, weights: &[u8]) -> Result<()> {
        self.nets = read_nets(&self.cfg, self.obs_dim, weights)?;
        self.start_from_loaded();
        Ok(())
    }

    /// Restarts the sampling noise from `seed`.
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// Words its sampling noise's stream has given.
    pub fn rng_words(&self) -> u128 {
        self.rng.get_word_pos()
    }

    /// Moves its sampling noise's stream to word `words` (from [`DreamerPolicy::rng_words`]).
    pub fn set_rng_words(&mut self, words: u128) {
        self.rng.set_word_pos(words);
    }

    /// Starts a new episode: the initial state and a zero previous action.
    pub fn reset(&mut self) {
        self.state = self.zero.clone();
        self.prev_action = [0.0; ACT_DIM];
    }

    /// The posterior state `(h, z)` after the last step (the initial state after a reset).
    pub fn state(&self) -> (&[f32], &[f32]) {
        (&self.state.0, &self.state.1)
    }

    /// The state `(h_0, z_0)` an episode starts from (with a zero previous action).
    pub fn initial_state(&self) -> (&[f32], &[f32]) {
        (&self.zero.0, &self.zero.1)
    }

    /// The networks it acts with.
    pub fn nets(&self) -> &PolicyNets {
        &self.nets
    }

    /// Its architecture.
    pub fn config(&self) -> &DreamerConfig {
        &self.cfg
    }

    /// The factor `1 / context_divisor` the raw context is multiplied by before the networks
    /// read it (then by cMask's mask).
    pub fn context_scale(&self) -> f32 {
        (1.0 / self.cfg.context_divisor()) as f32
    }

    /// Fixes cMask's mask at `mask` (`None`: chosen again); an error for an agent without a
    /// mask network.
    pub fn fix_mask(&mut self, mask: Option<[f32; CONTEXT_DIM]>) -> Result<()> {
        if mask.is_some() && self.nets.mask.is_none() {
            return Err(PolicyError::NoMask);
        }
        self.fixed_mask = mask;
        Ok(())
    }

    /// cMask's mask for observation `obs` (`None` for the other agents): the mask of `tanh μ`
    /// if `deterministic`, else of a sample (the oracle's `mask_sample`).
    fn mask(&mut self, obs: &[f32], deterministic: bool) -> Option<[f32; CONTEXT_DIM]> {
        let net = self.nets.mask.as_ref()?;
        let trace = &mut self.traces.mask;
        net.forward(obs, trace, 0..1);
        let out = net.output(trace, 0..1);
        let mut a = [0f32; CONTEXT_DIM];
        if deterministic {
            a.iter_mut()
                .zip(out)
                .for_each(|(a, &mean)| *a = mean.tanh());
        } else {
            let noise: [f32; CONTEXT_DIM] =
                std::array::from_fn(|_| self.rng.sample(StandardNormal));
            let clamp = self.cfg.mask.log_std_clamp.map(|b| b as f32);
            squash_rows(out, &noise, clamp, &mut a, &mut [0.0]);
        }
        Some(a.map(|a| mask_value(a, self.cfg.mask.mask_space)))
    }

    /// The action in `[−1, 1]²` for observation `obs` and raw context `[c_v, c_θ]`, and (cMask) the
    /// mask used. Deterministic: the mean action, the most likely latent and the mask of
    /// `tanh μ` (the oracle's `mask_of`); otherwise samples.
    pub fn act(
        &mut self,
        obs: &[f32],
        context: [f32; 2],
        deterministic: bool,
    ) -> Result<([f32; 2], Option<[f32; 2]>)> {
        if obs.len() != self.obs_dim {
            return Err(PolicyError::Observation {
                found: obs.len(),
                want: self.obs_dim,
            });
        }
        // a fixed mask replaces the chosen one after its noise is drawn
        let mask = self
            .mask(obs, deterministic)
            .map(|chosen| self.fixed_mask.unwrap_or(chosen));
        // the model's context: the raw one scaled (and masked), or none
        let scale = self.context_scale();
        let ctx: [f32; CONTEXT_DIM] =
            std::array::from_fn(|i| context[i] * scale * mask.map_or(1.0, |m| m[i]));
        let ctx = &ctx[..self.nets.rssm.config().context_dim];
        let z = self.cfg.stoch * self.cfg.classes;
        let (uniform, noise) = if deterministic {
            (None, None)
        } else {
            let u = uniform_rows(std::slice::from_mut(&mut self.rng), 1, z);
            let n: [f32; ACT_DIM] = std::array::from_fn(|_| self.rng.sample(StandardNormal));
            (Some(u), Some(n))
        };
        let (nets, tr) = (&self.nets, &mut self.traces);
        // the embedding of symlog o (symlog [o, a_{t−1}] as the paper's code acts)
        tr.input.clear();
        tr.input.extend(obs.iter().map(|&v| symlog_value(v)));
        if self.cfg.step_alignment == StepAlignment::PaperCode {
            tr.input
                .extend(self.prev_action.iter().map(|&v| symlog_value(v)));
        }
        nets.encoder
            .forward(tr.input.as_slice(), &mut tr.encoder, 0..1);
        let embed = match nets.encoder.outputs() {
            0 => &tr.input[..],
            _ => nets.encoder.output(&tr.encoder, 0..1),
        };
        let (h, zs) = (&self.state.0[..], &self.state.1[..]);
        let uniform = uniform.as_deref().unwrap_or(&self.uniform_mode);
        let inputs = (&self.prev_action[..], ctx, embed);
        nets.rssm
            .posterior_step((h, zs), inputs, uniform, &mut tr.rssm);
        let (h, zs, _) = tr.rssm.states();
        self.state.0.copy_from_slice(h);
        self.state.1.copy_from_slice(zs);
        tr.head_input.clear();
        for part in [h, zs, ctx] {
            tr.head_input.extend_from_slice(part);
        }
        nets.actor
            .forward(tr.head_input.as_slice(), &mut tr.actor, 0..1);
        let out = nets.actor.output(&tr.actor, 0..1);
        let (lo, span) = (
            self.cfg.min_std as f32,
            (self.cfg.max_std - self.cfg.min_std) as f32,
        );
        let action: [f32; ACT_DIM] = std::array::from_fn(|j| {
            let mean = out[j].tanh();
            match noise {
                None => mean,
                Some(n) => {
                    let a = mean + (sigmoid(out[ACT_DIM + j] + 2.0) * span + lo) * n[j];
                    a * (1.0 / a.abs().max(1.0))
                }
            }
        });
        self.prev_action = action;
        Ok((action, mask))
    }
}
