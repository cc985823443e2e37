//! DreamerV3 (Hafner et al. 2023) with the context-aware variants cRSSM (Prasanna et al. 2024) and
//! cMask (the paper's), as the paper's code ran them (REFERENCE §5).
//!
//! A training step reads as two steps: the world model ([`crate::world_model`]: encoder, RSSM,
//! decoder, reward and continue heads) on the batch, then behaviour learning in imagination from
//! its posterior states; cMask adds a step of its mask SAC ([`crate::cmask`]).
//!
//! **Behaviour.** From every posterior state (detached, `B·T` starts) the actor imagines through
//! the prior, with the context unchanged: `H` states with the start (`H − 1` steps) as the
//! paper's code (dreamerv3-torch) counts its horizon. With rewards `r`, continue probabilities
//! `c` and critic values `v` of the imagined states, the λ-returns `R_t` ([`crate::returns`]) are
//! normalised by the percentile scale `S`; the actor minimises `−w_t (R_t − v_t) / S − η H[π(·|s_t)]`,
//! backpropagating through the world model into the reparameterised actions from every use of
//! an imagined state (the returns' rewards, continue probabilities and values, the baseline
//! `v_t`, the entropy), as the code's autograd does (only the actor's parameters are stepped);
//! the critic regresses `sg R_t` and its slow EMA copy's value (two-hot), with
//! `w_t = Π_{k<t} γ c(s_k)` the stop-gradient discount weight. `[agent.dreamer] imagination =
//! "dreamerv3"` selects the form ctxrace had before (`H` steps, a stop-gradient baseline, no
//! gradient through `c`, the entropy weighted by `w_t`; [`crate::behaviour`] states both). The
//! actor is `Normal(tanh μ, σ)`, `σ = (σ_max − σ_min) sigmoid(x + 2) + σ_min`; samples are scaled
//! back into `[−1, 1]` with a stop-gradient factor `1 / max(1, |a|)` (dreamerv3-torch's
//! `absmax`) so that imagined actions match the environment's.
//!
//! **Context.** cRSSM feeds `c / range` (`range` = the training range 0.15, so `c ∈ [−1, 1]`) to
//! the sequence model and every head; cMask replaces it by `c_m = m_t ⊙ c / range` with
//! `m_t ~ π(m | o_t)` from a mask SAC trained on the extrinsic reward ([`crate::cmask`]: its
//! critics learn from the mask stored with each step, the one that acted). The world model and
//! imagination use one fresh (stop-gradient) mask per `o_t`, as the paper's code does. Three deliberate departures from the paper's code:
//! 1. `m = (tanh u + 1)/2`, which reaches 0 and 1 (the code's `sigmoid(tanh u)` stays in
//!    `[0.27, 0.73]`, so it can neither mask nor pass the context fully; `[agent.dreamer.mask]
//!    mask_space = "paper-code"` restores it);
//! 2. the SAC transition takes the reward of that transition (the code paired `(o_t, m_t)` with
//!    `r_{t+2}`, one step late: `reward_delay = 1`); transitions into a new episode, and those
//!    whose action no mask chose (random prefill steps), are dropped (the mask SAC's other
//!    paper-code keys: [`crate::cmask`]);
//! 3. imagination carries the *masked* context of each start state (the code used the unmasked one;
//!    `[agent.dreamer.mask] imagination_context = "raw"` restores it).
//!
//! **Parameters.** The networks are plain structs trained in place, saved in four groups:
//! "policy" ([`PolicyNets`]: `encoder`, `rssm`, `actor` and, for cMask, the mask actor `mask`:
//! everything [`DreamerPolicy`] (in `ctxrace_nn::policy`) needs, serialised whole by
//! [`Algorithm::policy_weights`]), "heads" (`decoder`, `reward`, `cont`), "critic" and its slow
//! copy; cMask adds its critics, their targets and the temperature. Optimisers: Adam
//! ([`crate::adam::Adam`], whose moments are saved with the weights), one each for world model
//! (encoder, RSSM, heads), actor and critic, after global-norm clipping. Noise (Gumbel uniforms,
//! Gaussian actions and masks) comes from a ChaCha8 stream per sequence of each training step,
//! so a run is reproducible from its seed, whatever the number of worker threads.
//!
//! **Speed.** The world model ([`crate::world_model`]) and behaviour learning (imagination,
//! heads, λ-returns, actor and critic losses, [`crate::behaviour`]) are differentiated by hand on
//! plain buffers (`ctxrace_nn`): they compute the gradients the optimisers need
//! and no others (as PyTorch's `requires_grad = False` on the frozen networks), with no graph
//! bookkeeping, in buffers kept from step to step. Each step splits its batch into one shard of
//! sequences per worker thread ([`Dreamer::set_workers`], [`crate::shards`]): the shards run the
//! world-model, imagination, actor, critic and mask-SAC passes in parallel, each loss scaled by
//! its shard's share of the batch, and the optimisers step on the summed gradients, which are the
//! batch's.

use crate::adam::Adam;
use crate::algorithm::{Algorithm, Batch, Metrics};
use crate::behaviour::{self, Imagination, Setting};
use crate::checkpoint;
use crate::cmask::MaskSac;
use crate::error::{LearnerError, Result};
use crate::returns::ReturnNorm;
use crate::shards::{add_part, in_parallel, on_shards_with, weighted_mean};
use crate::world_model::{zero_tensor, Starts, WorldModel};
use ctxrace_config::agents::{DreamerConfig, ImaginationContext, CONTEXT_DIM};
use ctxrace_nn::dreamer::{mask_value, normal_rows, state_head, PolicyNets};
use ctxrace_nn::initial_weights::init_dreamer;
use ctxrace_nn::kernels::matmul_flops;
use ctxrace_nn::parameters::{load_safetensors, polyak, to_safetensors};
use ctxrace_nn::policy::DreamerPolicy;
use ctxrace_nn::tanh_gaussian::squash_rows;
use ctxrace_nn::{Mlp, MlpGrads, MlpTrace, Parameters, TwoHot, Weights};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// On-disk counters of a [`Dreamer`].
#[derive(Serialize, Deserialize)]
struct TrainState {
    step: u64,
    return_norm: ReturnNorm,
}

/// DreamerV3 / cRSSM / cMask (see the module doc).
pub struct Dreamer {
    cfg: DreamerConfig,
    obs_dim: usize,
    act_dim: usize,
    /// Encoder, RSSM, actor and (cMask) mask actor.
    policy: PolicyNets,
    world_model: WorldModel,
    critic: Mlp,
    slow_critic: Mlp,
    twohot: TwoHot,
    actor_opt: Adam,
    critic_opt: Adam,
    mask_sac: Option<MaskSac>,
    return_norm: ReturnNorm,
    step: u64,
    /// Worker threads a batch is split over.
    workers: usize,
    /// The steps that compute the costly diagnostics ([`Algorithm::set_diagnostics_every`]).
    diagnostics_every: u64,
    /// Each shard's imagination, its buffers kept from one step to the next.
    imaginations: Vec<Imagination>,
    /// The mask actor's buffers for the batch's masks.
    mask_trace: MlpTrace,
}

impl Dreamer {
    /// A freshly initialised agent for observations of `obs_dim` and actions of `act_dim`
    /// (reward and critic output layers start at zero, as in DreamerV3).
    pub fn new(cfg: DreamerConfig, obs_dim: usize, act_dim: usize) -> Result<Self> {
        cfg.validate()?;
        if obs_dim == 0 || act_dim == 0 {
            return Err(LearnerError::Sizes {
                obs: obs_dim,
                action: act_dim,
            });
        }
        let mut policy = PolicyNets::initial(&cfg, obs_dim, act_dim)?;
        let world_model = WorldModel::new(&cfg, (obs_dim, act_dim), &mut policy)?;
        let head = (cfg.head_units, cfg.head_layers);
        let mut critic = state_head(&cfg, &mut Weights::initial(), "critic.", head, cfg.bins)?;
        init_dreamer(
            &mut critic,
            cfg.seed.wrapping_add(2),
            &cfg,
            (obs_dim, act_dim),
        );
        zero_tensor(&mut critic, "critic.out.weight");
        let slow_critic = critic.clone();
        let actor_opt = Adam::new(&policy.actor, cfg.ac_lr, cfg.ac_eps, cfg.ac_clip);
        let critic_opt = Adam::new(&critic, cfg.ac_lr, cfg.ac_eps, cfg.ac_clip);
        let mask_sac = match &policy.mask {
            Some(mask) => Some(MaskSac::new(&cfg, obs_dim, mask)?),
            None => None,
        };
        Ok(Self {
            twohot: TwoHot::new(cfg.bins, -20.0, 20.0),
            return_norm: ReturnNorm::new(cfg.return_decay, cfg.return_low, cfg.return_high),
            cfg,
            obs_dim,
            act_dim,
            policy,
            world_model,
            critic,
            slow_critic,
            actor_opt,
            critic_opt,
            mask_sac,
            step: 0,
            workers: 1,
            diagnostics_every: 1,
            imaginations: Vec::new(),
            mask_trace: MlpTrace::default(),
        })
    }

    /// Splits each batch over `n` worker threads (default: one); the
    /// step computes the same losses and gradients whatever `n`, up to the order of float sums.
    pub fn set_workers(&mut self, n: usize) {
        self.workers = n.max(1);
    }

    /// The configuration.
    pub fn config(&self) -> &DreamerConfig {
        &self.cfg
    }

    /// The acting policy with the current weights, its noise seeded by `seed`.
    pub fn policy(&self, seed: u64) -> Result<DreamerPolicy> {
        let weights = to_safetensors(&self.policy)?;
        Ok(DreamerPolicy::new(&self.cfg, self.obs_dim, &weights, seed)?)
    }

    /// One noise stream per sequence of this step's batch (Gumbel uniforms, actor and mask
    /// noise), so that a step draws the same noise however many workers share the batch.
    fn sequence_rngs(&self, batch: usize) -> Vec<ChaCha8Rng> {
        (0..batch as u64)
            .map(|b| {
                let mut rng = ChaCha8Rng::seed_from_u64(
                    self.cfg.seed ^ (b + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15),
                );
                rng.set_stream(self.step);
                rng
            })
            .collect()
    }

    /// The cMask masks `[B·T, 2]` of the batch's observations `obs` (`[B·T, O]`), one sample
    /// each, with each sequence's noise from its stream in `rngs` (none without a mask actor).
    fn draw_masks(&mut self, obs: &[f32], rngs: &mut [ChaCha8Rng]) -> Option<Vec<f32>> {
        let actor = self.policy.mask.as_ref()?;
        let rows = obs.len() / self.obs_dim;
        let noise = normal_rows(rngs, rows / rngs.len().max(1), CONTEXT_DIM);
        actor.fit(&mut self.mask_trace, rows);
        actor.forward(obs, &mut self.mask_trace, 0..rows);
        let out = actor.output(&self.mask_trace, 0..rows);
        let mut masks = vec![0f32; rows * CONTEXT_DIM];
        let clamp = self.cfg.mask.log_std_clamp.map(|b| b as f32);
        squash_rows(out, &noise, clamp, &mut masks, &mut vec![0f32; rows]);
        let space = self.cfg.mask.mask_space;
        masks.iter_mut().for_each(|m| *m = mask_value(*m, space));
        Some(masks)
    }

    /// The model's context of the batch's raw contexts `raw` (`[B·T, 2]`), divided by the
    /// context divisor and (cMask) times the masks, `[B·T, c]` values (none without a context).
    fn model_context(&self, raw: &[f32], masks: Option<&[f32]>) -> Vec<f32> {
        if self.cfg.context.context_dim() == 0 {
            return Vec::new();
        }
        // as candle divides by a scalar: times its reciprocal, plus zero
        let scale = (1.0 / self.cfg.context_divisor()) as f32;
        let scaled = raw.iter().map(|&c| c * scale + 0.0);
        match masks {
            Some(m) => scaled.zip(m).map(|(c, m)| c * m).collect(),
            None => scaled.collect(),
        }
    }

    /// One actor and one critic step on imagined trajectories from each shard's `starts`
    /// ([`crate::behaviour`]): the shards imagine in parallel, the return scale is updated with
    /// every shard's returns, then the shards' backward passes run in parallel and their
    /// gradients are summed. `phase` marks the end of imagination (the forward passes).
    fn behaviour_step(
        &mut self,
        starts: &[Starts],
        rngs: &mut [ChaCha8Rng],
        metrics: &mut Metrics,
        phase: &mut dyn FnMut(&mut Metrics, &str),
    ) -> Result<()> {
        let heads = &self.world_model.heads;
        let nets = behaviour::Nets {
            rssm: &self.policy.rssm,
            actor: &self.policy.actor,
            reward: &heads.reward,
            cont: &heads.cont,
            critic: &self.critic,
            slow: &self.slow_critic,
        };
        let set = Setting {
            cfg: &self.cfg,
            act_dim: self.act_dim,
            twohot: &self.twohot,
        };
        let mut work = std::mem::take(&mut self.imaginations);
        work.resize_with(starts.len(), Imagination::default);
        let shares = on_shards_with(
            self.workers,
            rngs.len(),
            rngs,
            &mut work,
            |shard, rngs, im| {
                im.forward(&nets, &set, &starts[shard.index], rngs);
                Ok(shard.weight)
            },
        )?;
        phase(metrics, "imagination");
        let all_returns: Vec<f32> = work.iter().flat_map(|im| im.returns().to_vec()).collect();
        self.return_norm.update(&all_returns);
        let scale = self.return_norm.scale();
        let parts = in_parallel(&mut work[..shares.len()], |i, im| {
            Ok(im.backward(&nets, &set, scale as f32, shares[i] as f32))
        })?;
        self.imaginations = work;
        let (mut actor, mut critic) = (None, None);
        let mut shard_metrics = Vec::with_capacity(parts.len());
        for (part, &w) in parts.into_iter().zip(&shares) {
            add_part(&mut actor, part.actor, MlpGrads::add);
            add_part(&mut critic, part.critic, MlpGrads::add);
            let mut m = Metrics::new();
            m.insert("actor/loss".into(), part.actor_loss);
            m.insert("critic/loss".into(), part.critic_loss);
            m.insert("actor/entropy".into(), part.entropy);
            m.insert("imag/reward".into(), part.reward);
            m.insert("imag/return".into(), part.ret);
            shard_metrics.push((w, m));
        }
        let (Some(actor), Some(critic)) = (actor, critic) else {
            return Err(LearnerError::NoImaginedStates);
        };
        let actor = actor.into_tensors(&self.policy.actor);
        let critic = critic.into_tensors(&self.critic);
        metrics.extend(weighted_mean(&shard_metrics));
        metrics.insert("imag/return_scale".into(), scale);
        let actor_norm = self.actor_opt.step(&mut self.policy.actor, &actor);
        metrics.insert("actor/grad_norm".into(), actor_norm?);
        let critic_norm = self.critic_opt.step(&mut self.critic, &critic);
        metrics.insert("critic/grad_norm".into(), critic_norm?);
        polyak(
            &mut self.slow_critic,
            &self.critic,
            self.cfg.slow_critic_rate,
        );
        Ok(())
    }

    /// Every optimiser with its file name, for reading.
    fn optimisers_ref(&self) -> Vec<(&'static str, &Adam)> {
        let mut v = vec![
            ("opt_model", &self.world_model.opt),
            ("opt_actor", &self.actor_opt),
            ("opt_critic", &self.critic_opt),
        ];
        if let Some(sac) = &self.mask_sac {
            v.push(("opt_mask_actor", &sac.core.actor_opt));
            v.push(("opt_mask_critic", &sac.core.critic_opt));
            v.push(("opt_mask_alpha", &sac.core.alpha_opt));
        }
        v
    }

    /// Every optimiser with its file name, for restoring.
    fn optimisers(&mut self) -> Vec<(&'static str, &mut Adam)> {
        let mut v = vec![
            ("opt_model", &mut self.world_model.opt),
            ("opt_actor", &mut self.actor_opt),
            ("opt_critic", &mut self.critic_opt),
        ];
        if let Some(sac) = &mut self.mask_sac {
            v.push(("opt_mask_actor", &mut sac.core.actor_opt));
            v.push(("opt_mask_critic", &mut sac.core.critic_opt));
            v.push(("opt_mask_alpha", &mut sac.core.alpha_opt));
        }
        v
    }

    /// Every group of networks with its file name, for reading.
    fn stores(&self) -> Vec<(&'static str, &dyn Parameters)> {
        let mut v: Vec<(&'static str, &dyn Parameters)> = vec![
            ("policy", &self.policy),
            ("heads", &self.world_model.heads),
            ("critic", &self.critic),
            ("slow_critic", &self.slow_critic),
        ];
        if let Some(sac) = &self.mask_sac {
            v.push(("mask_critic", &sac.core.critics));
            v.push(("mask_target", &sac.core.targets));
            v.push(("mask_alpha", &sac.core.log_alpha));
        }
        v
    }

    /// Every group of networks with its file name, for restoring.
    fn stores_mut(&mut self) -> Vec<(&'static str, &mut dyn Parameters)> {
        let mut v: Vec<(&'static str, &mut dyn Parameters)> = vec![
            ("policy", &mut self.policy),
            ("heads", &mut self.world_model.heads),
            ("critic", &mut self.critic),
            ("slow_critic", &mut self.slow_critic),
        ];
        if let Some(sac) = &mut self.mask_sac {
            v.push(("mask_critic", &mut sac.core.critics));
            v.push(("mask_target", &mut sac.core.targets));
            v.push(("mask_alpha", &mut sac.core.log_alpha));
        }
        v
    }
}

/// Sets the contexts of the starts of imagination to `ctx` (`[B·T, c]`, batch-major rows, the
/// shards' starts in order): cMask imagining with the unmasked context
/// (`imagination_context = "raw"`, the paper's code).
fn set_start_contexts(starts: &mut [Starts], ctx: &[f32]) {
    let mut rest = ctx;
    for start in starts {
        let (own, more) = rest.split_at(start.ctx.len().min(rest.len()));
        if own.len() == start.ctx.len() {
            start.ctx.copy_from_slice(own);
        }
        rest = more;
    }
}

impl Algorithm for Dreamer {
    /// One world-model step, one actor and one critic step on imagined trajectories from every
    /// posterior state, and (cMask) one mask-SAC step, all on `batch`.
    fn train_step(&mut self, batch: &Batch) -> Result<Metrics> {
        let Batch::Sequence(seq) = batch else {
            return Err(LearnerError::Transitions);
        };
        seq.validate(self.obs_dim, self.act_dim)?;
        let mut rngs = self.sequence_rngs(seq.batch);
        let mut metrics = Metrics::new();
        // the matrix-product FLOPs (the process's counter; one step at a time) and the wall
        // time of each phase
        let (mut counted, mut since) = (matmul_flops(), std::time::Instant::now());
        let mut phase_flops = |metrics: &mut Metrics, phase: &str| {
            let now = matmul_flops();
            metrics.insert(format!("flops/{phase}"), now.saturating_sub(counted) as f64);
            metrics.insert(format!("seconds/{phase}"), since.elapsed().as_secs_f64());
            (counted, since) = (now, std::time::Instant::now());
        };

        let masks = self.draw_masks(&seq.obs, &mut rngs);
        let ctx = self.model_context(&seq.context, masks.as_deref());
        let mut starts = self.world_model.step(
            &mut self.policy,
            seq,
            (&ctx, self.workers),
            &mut rngs,
            &mut metrics,
        )?;
        if masks.is_some() && self.cfg.mask.imagination_context == ImaginationContext::Raw {
            set_start_contexts(&mut starts, &self.model_context(&seq.context, None));
        }
        phase_flops(&mut metrics, "model");
        self.behaviour_step(&starts, &mut rngs, &mut metrics, &mut phase_flops)?;
        phase_flops(&mut metrics, "actor_critic");
        if let (Some(sac), Some(actor), Some(masks)) =
            (&mut self.mask_sac, &mut self.policy.mask, &masks)
        {
            let mean = masks.iter().map(|&m| f64::from(m)).sum::<f64>() / masks.len() as f64;
            metrics.insert("mask/mean".into(), mean);
            let logged = (self.step + 1).is_multiple_of(self.diagnostics_every);
            sac.step(
                actor,
                seq,
                (self.step, self.workers, logged),
                &mut rngs,
                &mut metrics,
            )?;
            phase_flops(&mut metrics, "mask");
        }
        self.step += 1;
        Ok(metrics)
    }

    /// The "policy" weights: encoder, RSSM, actor and (cMask) mask actor, for [`DreamerPolicy`].
    fn policy_weights(&self) -> Result<Vec<u8>> {
        Ok(to_safetensors(&self.policy)?)
    }

    /// Writes every group of networks and optimiser (`<name>.safetensors`) and the counters (step
    /// and return normaliser).
    fn save(&self, dir: &Path) -> checkpoint::Result<()> {
        let mut blobs = Vec::new();
        for (name, nets) in self.stores() {
            let bytes = to_safetensors(nets)
                .map_err(|e| checkpoint::io_error("serialising the agent for", dir, e))?;
            blobs.push((name, bytes));
        }
        for (name, opt) in self.optimisers_ref() {
            blobs.push((
                name,
                opt.to_bytes()
                    .map_err(|e| checkpoint::io_error("serialising the agent for", dir, e))?,
            ));
        }
        let state = TrainState {
            step: self.step,
            return_norm: self.return_norm.clone(),
        };
        checkpoint::save(dir, &blobs, &state)
    }

    fn load(&mut self, dir: &Path) -> checkpoint::Result<()> {
        for (name, nets) in self.stores_mut() {
            checkpoint::load_blob(dir, name, |b| load_safetensors(nets, b))?;
        }
        for (name, opt) in self.optimisers() {
            checkpoint::load_blob(dir, name, |b| opt.load_bytes(b))?;
        }
        let state: TrainState = checkpoint::load_state(dir)?;
        self.step = state.step;
        self.return_norm = state.return_norm;
        Ok(())
    }

    fn steps(&self) -> u64 {
        self.step
    }

    fn set_diagnostics_every(&mut self, every: u64) {
        self.diagnostics_every = every.max(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algorithm::scalar;
    use crate::world_model::oracle;
    use candle_core::{Device, Module, Tensor};
    use ctxrace_config::agents::{ContextMode, ImaginationLoss, MaskConfig, MaskSpace};
    use ctxrace_config::SequenceBatch;
    use ctxrace_oracle::dreamer::{normals_per, uniforms_per};
    use ctxrace_oracle::kernels::soft_cross_entropy;
    use ctxrace_oracle::{DreamerNets, Mlp as CandleMlp, ParamStore, RssmState, TwoHotTensors};
    use rand::Rng;

    fn tiny(context: ContextMode) -> DreamerConfig {
        DreamerConfig {
            context,
            units: 32,
            layers: 2,
            deter: 32,
            hidden: 32,
            stoch: 4,
            classes: 4,
            head_units: 32,
            head_layers: 2,
            batch: 4,
            length: 16,
            mask: MaskConfig {
                units: 32,
                ..MaskConfig::default()
            },
            ..DreamerConfig::default()
        }
    }

    const EPISODE: usize = 16;

    /// 1-D point mass: `x' = clip(x + 0.2 a_0, −1, 1)`, reward `−|x'|`, observation `[x, 1 − |x|]`.
    fn obs_of(x: f32) -> [f32; 2] {
        [x, 1.0 - x.abs()]
    }

    fn step_x(x: f32, a: [f32; 2]) -> f32 {
        (x + 0.2 * a[0].clamp(-1.0, 1.0)).clamp(-1.0, 1.0)
    }

    /// Random-policy episodes concatenated into one stream of steps; every action but the
    /// first of an episode comes with a random mask, as if a mask policy had chosen it.
    #[derive(Default)]
    struct Stream {
        obs: Vec<f32>,
        action: Vec<f32>,
        reward: Vec<f32>,
        first: Vec<f32>,
        context: Vec<f32>,
        mask: Vec<f32>,
    }

    fn collect(episodes: usize, rng: &mut ChaCha8Rng) -> Stream {
        let mut s = Stream::default();
        for _ in 0..episodes {
            let mut x: f32 = rng.random_range(-1.0..1.0);
            let c = [rng.random_range(-0.15..0.15), rng.random_range(-0.15..0.15)];
            let mut push = |x: f32, a: [f32; 2], m: [f32; 2], r: f32, first: f32| {
                s.obs.extend(obs_of(x));
                s.action.extend(a);
                s.reward.push(r);
                s.first.push(first);
                s.context.extend(c);
                s.mask.extend(m);
            };
            push(x, [0.0; 2], [0.0; 2], 0.0, 1.0);
            for _ in 0..EPISODE {
                let a = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
                let m = [rng.random_range(0.0..1.0), rng.random_range(0.0..1.0)];
                x = step_x(x, a);
                push(x, a, m, -x.abs(), 0.0);
            }
        }
        s
    }

    fn sample(s: &Stream, b: usize, t: usize, rng: &mut ChaCha8Rng) -> Batch {
        let mut out = SequenceBatch {
            batch: b,
            length: t,
            obs_dim: 2,
            act_dim: 2,
            ..SequenceBatch::default()
        };
        for _ in 0..b {
            let i = rng.random_range(0..=s.reward.len() - t);
            out.obs.extend(&s.obs[2 * i..2 * (i + t)]);
            out.action.extend(&s.action[2 * i..2 * (i + t)]);
            out.reward.extend(&s.reward[i..i + t]);
            out.is_first.extend(&s.first[i..i + t]);
            out.is_terminal.extend(std::iter::repeat_n(0.0, t));
            out.context.extend(&s.context[2 * i..2 * (i + t)]);
            out.mask.extend(&s.mask[2 * i..2 * (i + t)]);
            out.has_mask
                .extend(s.first[i..i + t].iter().map(|f| 1.0 - f));
        }
        Batch::Sequence(out)
    }

    /// Trains cMask's mask SAC alone on a contextual bandit whose reward depends only on the mask
    /// that acted, `r_{t+1} = −(m_{t,0} − 1)² − m_{t,1}²`, with observations drawn at random:
    /// `(1, 0)` is the best mask. Each step acts with the current mask actor on a fresh batch of
    /// 8 × 16 steps and takes one SAC step on it, its critics fitted on the acting masks or, with
    /// `fresh_masks`, on masks drawn anew for every `o_t` (ctxrace before it stored the masks).
    /// The mask SAC's form is `form` applied to the bandit's learning rates. Returns the
    /// critics' `Q(o, best) − Q(o, worst)` for the best and worst masks the form can act with
    /// (`(1, 0)` and `(0, 1)`; `(σ(1), σ(−1))` and `(σ(−1), σ(1))` for the paper's code's
    /// `sigmoid(tanh u)`) and the mask actor's mode, both averaged over 64 observations.
    fn mask_bandit(fresh_masks: bool, form: MaskForm) -> (f64, [f64; 2]) {
        let mask = form(MaskConfig {
            units: 32,
            lr: 3e-3,
            gamma: 0.9,
            ..MaskConfig::default()
        });
        let space = mask.mask_space;
        let cfg = DreamerConfig {
            mask,
            ..tiny(ContextMode::Cmask)
        };
        let mut agent = Dreamer::new(cfg, 2, 2).unwrap();
        let (b, t) = (8, 16);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for step in 0..600u64 {
            let obs: Vec<f32> = (0..b * t * 2)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let mut noise = ChaCha8Rng::seed_from_u64(1000 + step);
            let mut draw = || {
                agent
                    .draw_masks(&obs, std::slice::from_mut(&mut noise))
                    .unwrap()
            };
            let acted = draw();
            let stored = if fresh_masks { draw() } else { acted.clone() };
            let mut seq = SequenceBatch {
                batch: b,
                length: t,
                obs_dim: 2,
                act_dim: 2,
                obs,
                action: vec![0.0; b * t * 2],
                is_terminal: vec![0.0; b * t],
                context: vec![0.1; b * t * 2],
                ..SequenceBatch::default()
            };
            for k in 0..b * t {
                // row k holds what the mask acted at row k − 1 earned, and that mask
                let first = k % t == 0;
                let (m, s) = if first {
                    ([0.0; 2], [0.0; 2])
                } else {
                    let (m, s) = (&acted[2 * k - 2..], &stored[2 * k - 2..]);
                    ([m[0], m[1]], [s[0], s[1]])
                };
                let r = if first {
                    0.0
                } else {
                    -(m[0] - 1.0).powi(2) - m[1].powi(2)
                };
                seq.reward.push(r);
                seq.is_first.push(f32::from(u8::from(first)));
                seq.mask.extend(s);
                seq.has_mask.push(f32::from(u8::from(!first)));
            }
            let mut rngs = agent.sequence_rngs(b);
            let mut m = Metrics::new();
            let (sac, actor) = (
                agent.mask_sac.as_mut().unwrap(),
                agent.policy.mask.as_mut().unwrap(),
            );
            sac.step(actor, &seq, (agent.step, 1, true), &mut rngs, &mut m)
                .unwrap();
            agent.step += 1;
        }
        let probe: Vec<f32> = (0..128).map(|_| rng.random_range(-1.0..1.0)).collect();
        let sac = agent.mask_sac.as_ref().unwrap();
        let q_of = |m: [f32; 2]| {
            let x: Vec<f32> = probe
                .chunks(2)
                .flat_map(|o| [o[0], o[1], m[0], m[1]])
                .collect();
            let [q1, q2] = &sac.core.critics.q;
            let (q1, q2) = (outputs(q1, &x, 64), outputs(q2, &x, 64));
            let min = q1.iter().zip(&q2).map(|(a, b)| f64::from(a.min(*b)));
            min.sum::<f64>() / 64.0
        };
        let (hi, lo) = match space {
            MaskSpace::Unit => (1.0, 0.0),
            MaskSpace::PaperCode => (sigmoid(1.0), sigmoid(-1.0)),
        };
        let gap = q_of([hi, lo]) - q_of([lo, hi]);
        let out = outputs(agent.policy.mask.as_ref().unwrap(), &probe, 64);
        let mut mode = [0f32; 2];
        for row in out.chunks(4) {
            for (m, mean) in mode.iter_mut().zip(row) {
                *m += mask_value(mean.tanh(), space) / 64.0;
            }
        }
        eprintln!(
            "mask bandit ({space:?}, fresh masks: {fresh_masks}): Q gap {gap:.3}, \
             mode ({:.3}, {:.3})",
            mode[0], mode[1]
        );
        (gap, [mode[0] as f64, mode[1] as f64])
    }

    /// The outputs of `net` on `rows` rows `x`.
    fn outputs(net: &Mlp, x: &[f32], rows: usize) -> Vec<f32> {
        let mut trace = net.trace(rows);
        net.forward(x, &mut trace, 0..rows);
        net.output(&trace, 0..rows).to_vec()
    }

    /// `σ(x)`.
    fn sigmoid(x: f32) -> f32 {
        1.0 / (1.0 + (-x).exp())
    }

    #[test]
    fn the_mask_critic_learns_from_the_mask_that_acted() {
        // the best and worst masks differ by 2 in reward; the actor starts at the mode (½, ½)
        let (gap, mode) = mask_bandit(false, |m| m);
        assert!(gap > 1.0, "Q gap {gap}");
        assert!(mode[0] > 0.7 && mode[1] < 0.3, "mode {mode:?}");
        // a critic fitted on freshly drawn masks cannot tell them apart: the actor stays put
        let (gap, mode) = mask_bandit(true, |m| m);
        assert!(gap.abs() < 0.5, "fresh-mask Q gap {gap}");
        assert!((mode[0] - 0.5).abs() < 0.15, "fresh-mask mode {mode:?}");
    }

    /// Whether the bandit's critics tell the best reachable mask from the worst and the actor's
    /// mode moved towards the best (from `(½, ½)`): `Some(true)` learnt, `Some(false)` stayed
    /// put, `None` neither clearly.
    fn learnt((gap, mode): (f64, [f64; 2])) -> Option<bool> {
        if gap > 0.3 && mode[0] > 0.6 && mode[1] < 0.4 {
            Some(true)
        } else if gap.abs() < 0.3 && mode.iter().all(|m| (m - 0.5).abs() < 0.1) {
            Some(false)
        } else {
            None
        }
    }

    /// The paper's code's mask SAC, reward pairing aside, learns the bandit within the masks it
    /// can act with, `sigmoid(tanh u) ∈ (0.27, 0.73)`: its critics, fitted there, are evaluated
    /// by the actor's loss at `tanh u ∈ (−1, 1)`, where they extrapolate the right slope
    /// (the best reachable mask `(0.73, 0.27)` earns 0.92 more than the worst; Q gap 0.57,
    /// mode (0.67, 0.33) here). With the code's reward pairing it cannot: `m_t` is paired with
    /// `r_{t+2}`, the next mask's reward, which the bandit draws independently of `m_t` (on a
    /// race track, where rewards persist from step to step, it carries some signal).
    #[test]
    fn the_paper_codes_mask_sac_learns_the_bandit_only_without_its_late_reward() {
        let on_time = mask_bandit(false, |m| MaskConfig {
            reward_delay: 0,
            ..m.with_paper_code_mask()
        });
        assert_eq!(learnt(on_time), Some(true), "{on_time:?}");
        let coded = mask_bandit(false, MaskConfig::with_paper_code_mask);
        assert_eq!(learnt(coded), Some(false), "{coded:?}");
    }

    /// A change to the bandit's mask SAC configuration.
    type MaskForm = fn(MaskConfig) -> MaskConfig;

    /// Each paper-code key alone on ctxrace's mask SAC: only the late reward stops it from
    /// learning the bandit (the bandit has no terminals, so `bootstrap_terminals` changes
    /// nothing there; its effect is `paper_code_transitions_take_the_next_reward_and_bootstrap_terminals`).
    #[test]
    fn each_paper_code_mask_key_alone_on_the_bandit() {
        let forms: [(&str, MaskForm, bool); 5] = [
            (
                "mask_space",
                |m| MaskConfig {
                    mask_space: MaskSpace::PaperCode,
                    ..m
                },
                true,
            ),
            (
                "bootstrap_terminals",
                |m| MaskConfig {
                    bootstrap_terminals: true,
                    ..m
                },
                true,
            ),
            (
                "target_every",
                |m| MaskConfig {
                    target_every: 2,
                    ..m
                },
                true,
            ),
            (
                "log_std_clamp",
                |m| MaskConfig {
                    log_std_clamp: [-20.0, 2.0],
                    ..m
                },
                true,
            ),
            (
                "reward_delay",
                |m| MaskConfig {
                    reward_delay: 1,
                    ..m
                },
                false,
            ),
        ];
        for (key, form, learns) in forms {
            let result = mask_bandit(false, form);
            assert_eq!(learnt(result), Some(learns), "{key}: {result:?}");
        }
    }

    #[test]
    fn the_default_config_has_the_papers_sizes() {
        let paper = DreamerConfig::default();
        assert_eq!(
            (paper.deter, paper.stoch, paper.classes, paper.layers),
            (256, 16, 16, 3)
        );
    }

    /// A fresh agent's every group of networks is, to the byte, the candle store that ctxrace
    /// built for the same seed before the networks were plain: the same names, groups, seeds and
    /// draws, the reward and critic output layers zero, the slow critic and the mask SAC's
    /// targets copies, `log α` at `ln init_alpha`.
    #[test]
    fn fresh_networks_are_the_candle_stores_of_the_same_seed() {
        let cfg = tiny(ContextMode::Cmask);
        let agent = Dreamer::new(cfg.clone(), 3, 2).unwrap();
        let seeded = |seed: u64, build: &dyn Fn(candle_nn::VarBuilder)| {
            let store = ParamStore::new();
            build(store.builder());
            store.init(seed).unwrap();
            store
        };
        let zero = |store: &ParamStore, name: &str| {
            let (_, v) = store.named().into_iter().find(|(n, _)| n == name).unwrap();
            v.set(&v.zeros_like().unwrap()).unwrap();
        };
        let size = (cfg.head_units, cfg.head_layers);
        let policy = seeded(cfg.seed, &|vb| {
            DreamerNets::new(&cfg, 3, 2, vb).unwrap();
        });
        let heads = seeded(cfg.seed + 1, &|vb| {
            oracle::head(&cfg, vb.pp("decoder"), (cfg.units, cfg.layers), 3);
            oracle::head(&cfg, vb.pp("reward"), size, cfg.bins);
            oracle::head(&cfg, vb.pp("cont"), size, 1);
        });
        zero(&heads, "reward.out.weight");
        let critic = seeded(cfg.seed + 2, &|vb| {
            oracle::head(&cfg, vb.pp("critic"), size, cfg.bins);
        });
        zero(&critic, "critic.out.weight");
        let critics = seeded(cfg.seed + 3, &|vb| {
            crate::candle_sac::TwinQ::new(3 + CONTEXT_DIM, cfg.mask.units, cfg.mask.layers, vb)
                .unwrap();
        });
        let alpha = ParamStore::new();
        let init = candle_nn::Init::Const(cfg.mask.init_alpha.ln());
        alpha
            .builder()
            .get_with_hints(1, "log_alpha", init)
            .unwrap();
        let want = [
            ("policy", &policy),
            ("heads", &heads),
            ("critic", &critic),
            ("slow_critic", &critic),
            ("mask_critic", &critics),
            ("mask_target", &critics),
            ("mask_alpha", &alpha),
        ];
        let got = agent.stores();
        assert_eq!(got.len(), want.len());
        for ((name, nets), (want_name, store)) in got.into_iter().zip(want) {
            assert_eq!(name, want_name);
            let bytes = to_safetensors(nets).unwrap();
            assert!(bytes == store.to_bytes().unwrap(), "{name} differs");
        }
    }

    /// The learner feeds its networks the context at the agent's scale, as the acting policy
    /// does (`ctxrace_nn::policy::dreamer`'s `acting_feeds_the_context_at_its_scale`): both
    /// build their networks from [`ctxrace_config::AgentConfig::dreamer`].
    #[test]
    fn training_feeds_the_context_at_the_agents_scale() {
        use ctxrace_config::{AgentConfig, AlgoKind, ContextScale};
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let data = collect(2, &mut rng);
        let Batch::Sequence(seq) = sample(&data, 2, 8, &mut rng) else {
            unreachable!()
        };
        for (scale, divisor) in [(ContextScale::Raw, 1.0), (ContextScale::Normalised, 0.15)] {
            let agent = AgentConfig {
                algo: AlgoKind::Crssm,
                context_scale: scale,
                dreamer: tiny(ContextMode::None),
                ..AgentConfig::default()
            };
            let learner = Dreamer::new(agent.dreamer(), 2, 2).unwrap();
            let fed = learner.model_context(&seq.context, None);
            assert_eq!(fed.len(), seq.context.len());
            for (f, c) in fed.iter().zip(&seq.context) {
                assert!(
                    (f - c / divisor as f32).abs() < 1e-6,
                    "{scale:?}: {f} vs {c}"
                );
            }
        }
    }

    #[test]
    fn world_model_losses_fall_on_point_mass_data() {
        ctxrace_oracle::candle_on_one_thread();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let data = collect(40, &mut rng);
        // the best constant reward prediction scores the entropy of the mean two-hot target
        let targets = TwoHot::dreamer()
            .encode(&Tensor::new(data.reward.as_slice(), &Device::Cpu).unwrap())
            .unwrap();
        let marginal: Vec<f32> = targets.mean(0).unwrap().to_vec1().unwrap();
        let constant: f64 = marginal
            .iter()
            .filter(|&&q| q > 0.0)
            .map(|&q| -(q as f64) * (q as f64).ln())
            .sum();
        let cfg = DreamerConfig {
            model_lr: 3e-3,
            ..tiny(ContextMode::Crssm)
        };
        let mut agent = Dreamer::new(cfg, 2, 2).unwrap();
        let mut history = Vec::new();
        for _ in 0..200 {
            // the world-model part of `train_step`
            let Batch::Sequence(seq) = sample(&data, 4, 16, &mut rng) else {
                unreachable!()
            };
            let ctx = agent.model_context(&seq.context, None);
            let mut m = Metrics::new();
            let mut rngs = agent.sequence_rngs(seq.batch);
            let policy = &mut agent.policy;
            let model = &mut agent.world_model;
            model
                .step(policy, &seq, (&ctx, 1), &mut rngs, &mut m)
                .unwrap();
            assert!(m.values().all(|v| v.is_finite()), "{m:?}");
            history.push((m["model/recon"], m["model/reward"]));
        }
        let mean = |xs: &[(f64, f64)]| {
            let n = xs.len() as f64;
            (
                xs.iter().map(|x| x.0).sum::<f64>() / n,
                xs.iter().map(|x| x.1).sum::<f64>() / n,
            )
        };
        let (r0, w0) = mean(&history[..10]);
        let (r1, w1) = mean(&history[190..]);
        eprintln!("recon {r0:.4} -> {r1:.4}, reward {w0:.3} -> {w1:.3} (constant {constant:.3})");
        assert!(r1 < 0.5 * r0, "recon {r0} -> {r1}");
        assert!(
            w1 < 0.5 * w0 && w1 < 0.75 * constant,
            "reward {w0} -> {w1}, constant {constant}"
        );
    }

    /// The agent's networks as candle modules holding its weights: the tests' oracle.
    struct Oracle {
        policy: ParamStore,
        nets: DreamerNets,
        reward: CandleMlp,
        cont: CandleMlp,
        critic_store: ParamStore,
        critic: CandleMlp,
        slow: CandleMlp,
    }

    impl Oracle {
        fn of(agent: &Dreamer) -> Self {
            let (cfg, dims) = (&agent.cfg, (agent.obs_dim, agent.act_dim));
            let (policy, nets) = oracle::policy(cfg, dims, &agent.policy);
            let (_, [_, reward, cont]) = oracle::heads(cfg, dims, &agent.world_model.heads);
            let critic_of = |vb: candle_nn::VarBuilder| {
                let size = (cfg.head_units, cfg.head_layers);
                oracle::head(cfg, vb.pp("critic"), size, cfg.bins)
            };
            let (critic_store, critic) = oracle::store_of(&agent.critic, critic_of);
            let (_, slow) = oracle::store_of(&agent.slow_critic, critic_of);
            Self {
                policy,
                nets,
                reward,
                cont,
                critic_store,
                critic,
                slow,
            }
        }
    }

    /// The behaviour losses of one shard of `start` composed of candle operations, autograd's
    /// statement of what [`crate::behaviour`] differentiates by hand in the config's form:
    /// `(actor, critic)` losses, each a mean over the `T N` terms, for the return scale `scale`.
    /// The paper's code's form reads as its dreamerv3-torch `ImagBehavior`: `H` states with the
    /// start, gradients through every use of an imagined state.
    fn candle_behaviour_losses(
        agent: &Dreamer,
        oracle: &Oracle,
        start: &Starts,
        rngs: &mut [ChaCha8Rng],
        scale: f64,
    ) -> (Tensor, Tensor) {
        let cfg = &agent.cfg;
        let paper = cfg.imagination == ImaginationLoss::PaperCode;
        let h = behaviour::imagined_steps(cfg);
        let (n, a) = (start.n, agent.act_dim);
        let per_sequence = n / rngs.len();
        let rows = |v: &[f32]| Tensor::from_slice(v, (n, v.len() / n), &Device::Cpu).unwrap();
        let ctx = (!start.ctx.is_empty()).then(|| rows(&start.ctx));
        let ctx = ctx.as_ref();
        let start_cont = Tensor::from_slice(&start.cont, n, &Device::Cpu).unwrap();
        let rssm = oracle.nets.rssm.frozen();
        let (reward_head, cont_head) = (oracle.reward.frozen(), oracle.cont.frozen());
        let mut state = RssmState {
            deter: rows(&start.deter),
            stoch: rows(&start.stoch),
        };
        let mut xs = vec![state.head_input(ctx).unwrap()];
        let mut entropies = Vec::new();
        for t in 0..h {
            // the actor sees stop-gradient states; its actions carry gradients into the model
            let (mean, std) = oracle.nets.actor_dist(&xs[t].detach()).unwrap();
            let noise = normals_per(rngs, per_sequence, a).unwrap();
            let action = DreamerNets::sample_action(&mean, &std, &noise).unwrap();
            let gauss = 0.5 * (1.0 + (2.0 * std::f64::consts::PI).ln());
            // the paper's code takes the entropy of the actor on the states themselves
            let std = match paper {
                true => oracle.nets.actor_dist(&xs[t]).unwrap().1,
                false => std,
            };
            entropies.push((std.log().unwrap().sum(1).unwrap() + a as f64 * gauss).unwrap());
            let uniform = uniforms_per(rngs, per_sequence, (cfg.stoch, cfg.classes)).unwrap();
            let deter = rssm.deter_step(&state, &action, ctx).unwrap();
            let prior = rssm.prior_logits(&deter).unwrap();
            let stoch = rssm.sample(&prior, &uniform).unwrap();
            state = RssmState { deter, stoch };
            xs.push(state.head_input(ctx).unwrap());
        }
        let x = Tensor::cat(&xs, 0).unwrap();
        let entropy = Tensor::stack(&entropies, 0).unwrap();
        let later = x.narrow(0, n, h * n).unwrap();
        let decode = |l: &Tensor| agent.twohot.decode(l).unwrap();
        let reward = decode(&reward_head.forward(&later).unwrap())
            .reshape((h, n))
            .unwrap();
        let cont_input = if paper { x.clone() } else { x.detach() };
        let cont_all = cont_head.forward(&cont_input).unwrap();
        let cont_all = candle_nn::ops::sigmoid(&cont_all)
            .unwrap()
            .reshape((h + 1, n))
            .unwrap();
        let cont = cont_all.narrow(0, 1, h).unwrap();
        let value = decode(&oracle.critic.frozen().forward(&x).unwrap())
            .reshape((h + 1, n))
            .unwrap();
        let returns =
            crate::returns::lambda_returns(&reward, &cont, &value, cfg.gamma, cfg.lambda).unwrap();
        // w_t = w_{t−1} γ c(s_{t−1}) from 1 (paper's code), or w_{t−1} γ c(s_t) from the start's
        let (mut w, lag) = match paper {
            true => (start_cont.ones_like().unwrap(), 1),
            false => (start_cont, 0),
        };
        let mut weights = vec![w.clone()];
        for t in 1..h {
            let c = cont_all.get(t - lag).unwrap().detach();
            w = (w.mul(&c).unwrap() * cfg.gamma).unwrap();
            weights.push(w.clone());
        }
        let weights = Tensor::stack(&weights, 0).unwrap();
        let base = value.narrow(0, 0, h).unwrap();
        let base = if paper { base } else { base.detach() };
        let adv = ((&returns - base).unwrap() / scale).unwrap();
        let bonus = (&entropy * cfg.entropy).unwrap();
        let objective = match paper {
            true => (adv.mul(&weights).unwrap() + bonus).unwrap(),
            false => (adv + bonus).unwrap().mul(&weights).unwrap(),
        };
        let actor = objective.neg().unwrap().mean_all().unwrap();
        let now = x.narrow(0, 0, h * n).unwrap().detach();
        let slow = decode(&oracle.slow.forward(&now).unwrap()).detach();
        let encode = |y: &Tensor| agent.twohot.encode(&y.flatten_all().unwrap()).unwrap();
        let target =
            (encode(&returns.detach()) + (encode(&slow) * cfg.slow_critic_reg).unwrap()).unwrap();
        let logits = oracle.critic.forward(&now).unwrap();
        let critic = soft_cross_entropy(&logits, &target)
            .unwrap()
            .mul(&weights.detach().flatten_all().unwrap())
            .unwrap()
            .mean_all()
            .unwrap();
        (actor, critic)
    }

    /// The hand-differentiated behaviour step ([`crate::behaviour`]) computes the losses and the
    /// actor's and critic's gradients of the candle composition, with and without a context,
    /// and without the entropy bonus (the actor's gradient then comes through the world model
    /// alone); no gradient reaches another network.
    #[test]
    fn the_behaviour_step_differentiates_the_candle_composition() {
        let settings = [
            (ContextMode::None, 0.0),
            (ContextMode::Cmask, 0.0),
            (ContextMode::Cmask, 0.05),
        ];
        let forms = [ImaginationLoss::PaperCode, ImaginationLoss::Dreamerv3];
        for ((mode, entropy), imagination) in forms
            .into_iter()
            .flat_map(|form| settings.map(|s| (s, form)))
        {
            let mut rng = ChaCha8Rng::seed_from_u64(2);
            let data = collect(10, &mut rng);
            let cfg = DreamerConfig {
                model_lr: 1e-3,
                ac_lr: 1e-3,
                entropy,
                imagination,
                ..tiny(mode)
            };
            let mut agent = Dreamer::new(cfg, 2, 2).unwrap();
            // reward and value heads that are not (nearly) zero, so that every path of the
            // gradient weighs: their output layers start at zero
            oracle::randomise_outputs(&mut agent.world_model.heads, 0.3, 1);
            oracle::randomise_outputs(&mut agent.critic, 0.3, 2);
            oracle::randomise_outputs(&mut agent.slow_critic, 0.3, 3);
            for _ in 0..3 {
                agent.train_step(&sample(&data, 4, 16, &mut rng)).unwrap();
            }
            let Batch::Sequence(seq) = sample(&data, 3, 16, &mut rng) else {
                unreachable!()
            };
            let mut rngs = agent.sequence_rngs(seq.batch);
            let masks = agent.draw_masks(&seq.obs, &mut rngs);
            let ctx = agent.model_context(&seq.context, masks.as_deref());
            let mut m = Metrics::new();
            let starts = agent
                .world_model
                .step(&mut agent.policy, &seq, (&ctx, 1), &mut rngs, &mut m)
                .unwrap();
            let scale = 1.7;
            let oracle = Oracle::of(&agent);
            let (actor, critic) =
                candle_behaviour_losses(&agent, &oracle, &starts[0], &mut rngs.clone(), scale);
            let want = (&actor + &critic).unwrap().backward().unwrap();

            let heads = &agent.world_model.heads;
            let nets = behaviour::Nets {
                rssm: &agent.policy.rssm,
                actor: &agent.policy.actor,
                reward: &heads.reward,
                cont: &heads.cont,
                critic: &agent.critic,
                slow: &agent.slow_critic,
            };
            let set = Setting {
                cfg: &agent.cfg,
                act_dim: agent.act_dim,
                twohot: &agent.twohot,
            };
            let mut im = Imagination::default();
            im.forward(&nets, &set, &starts[0], &mut rngs);
            let got = im.backward(&nets, &set, scale as f32, 1.0);
            let value = |t: &Tensor| scalar(t).unwrap();
            let case = format!("{imagination:?} {mode:?} entropy {entropy}");
            let (actor_loss, critic_loss) = (value(&actor), value(&critic));
            assert!(
                (got.actor_loss - actor_loss).abs() < 1e-4 * (1.0 + actor_loss.abs()),
                "{case}: actor loss {} by hand, {actor_loss} by candle",
                got.actor_loss
            );
            assert!(
                (got.critic_loss - critic_loss).abs() < 1e-4 * (1.0 + critic_loss.abs()),
                "{case}: critic loss {} by hand, {critic_loss} by candle",
                got.critic_loss
            );
            // the actor's and the critic's gradients are autograd's; autograd gives none to
            // the networks the step does not train (the frozen RSSM, the encoder, the mask)
            for (name, _) in oracle.policy.named() {
                if !name.starts_with("actor.") {
                    assert!(
                        oracle::grad(&want, &oracle.policy, &name).is_none(),
                        "{case}: {name} has a gradient"
                    );
                }
            }
            let hand = [
                (
                    got.actor.into_tensors(nets.actor),
                    nets.actor,
                    &oracle.policy,
                ),
                (
                    got.critic.into_tensors(nets.critic),
                    nets.critic,
                    &oracle.critic_store,
                ),
            ];
            for (grads, net, store) in hand {
                for (g, t) in grads.iter().zip(net.tensors()) {
                    let name = t.name;
                    let w = oracle::grad(&want, store, name)
                        .unwrap_or_else(|| panic!("{case} {name}: no candle gradient"));
                    assert_eq!(g.len(), w.len(), "{case} {name}");
                    let scale = w.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
                    assert!(w.iter().any(|&v| v != 0.0), "{case} {name}: zero gradient");
                    for (i, (a, b)) in g.iter().zip(&w).enumerate() {
                        assert!(
                            (a - b).abs() <= 2e-3 * scale,
                            "{case} {name}[{i}]: {a} vs {b}"
                        );
                    }
                }
            }
        }
    }

    /// cMask's costly diagnostic, the mask critics' spread, is computed on the logged steps only.
    #[test]
    fn the_mask_q_spread_is_computed_on_the_logged_steps_only() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let data = collect(6, &mut rng);
        let batch = sample(&data, 4, 16, &mut rng);
        let mut agent = Dreamer::new(tiny(ContextMode::Cmask), 2, 2).unwrap();
        agent.set_diagnostics_every(2);
        let first = agent.train_step(&batch).unwrap();
        let second = agent.train_step(&batch).unwrap();
        assert!(first.contains_key("mask/q_loss") && !first.contains_key("mask/q_spread"));
        assert!(second["mask/q_spread"] > 0.0, "{second:?}");
    }

    #[test]
    fn cmask_imagines_with_the_raw_context_only_when_asked() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let data = collect(6, &mut rng);
        let batch = sample(&data, 4, 16, &mut rng);
        let step = |imagination_context| {
            let mut cfg = tiny(ContextMode::Cmask);
            cfg.mask.imagination_context = imagination_context;
            Dreamer::new(cfg, 2, 2).unwrap().train_step(&batch).unwrap()
        };
        let (masked, raw) = (
            step(ImaginationContext::Masked),
            step(ImaginationContext::Raw),
        );
        // the world model saw the masked context either way; imagination did not
        for key in ["model/loss", "model/kl", "mask/mean"] {
            assert_eq!(masked[key], raw[key], "{key}");
        }
        assert_ne!(masked["actor/loss"], raw["actor/loss"]);
        let mut starts = [1, 2].map(|n| Starts {
            n,
            deter: Vec::new(),
            stoch: Vec::new(),
            cont: Vec::new(),
            ctx: vec![0.0; 2 * n],
        });
        set_start_contexts(&mut starts, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        assert_eq!(starts[0].ctx, [1.0, 2.0]);
        assert_eq!(starts[1].ctx, [3.0, 4.0, 5.0, 6.0]);
    }

    #[test]
    fn policy_weights_and_save_load_round_trip() {
        let dir = std::env::temp_dir().join(format!("ctxrace-dreamer-{}", std::process::id()));
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let data = collect(6, &mut rng);
        for mode in [ContextMode::None, ContextMode::Crssm, ContextMode::Cmask] {
            let cfg = tiny(mode);
            let mut a = Dreamer::new(cfg.clone(), 2, 2).unwrap();
            for _ in 0..2 {
                a.train_step(&sample(&data, 4, 16, &mut rng)).unwrap();
            }
            let mut b = Dreamer::new(
                DreamerConfig {
                    seed: 9,
                    ..cfg.clone()
                },
                2,
                2,
            )
            .unwrap();
            assert_ne!(a.policy_weights().unwrap(), b.policy_weights().unwrap());
            // a policy made with other weights acts as a's once a's are loaded into it (its
            // networks are read again)
            let mut r = b.policy(0).unwrap();
            r.load(&a.policy_weights().unwrap()).unwrap();
            a.save(&dir).unwrap();
            b.load(&dir).unwrap();
            assert_eq!(a.policy_weights().unwrap(), b.policy_weights().unwrap());
            for ((_, sa), (_, sb)) in a.stores().iter().zip(b.stores()) {
                assert_eq!(to_safetensors(*sa).unwrap(), to_safetensors(sb).unwrap());
            }
            assert_eq!((b.steps(), &b.return_norm), (2, &a.return_norm));

            let mut p = a.policy(0).unwrap();
            let mut q = DreamerPolicy::new(&cfg, 2, &b.policy_weights().unwrap(), 0).unwrap();
            let mut x = 0.7;
            let ctx = [0.1, -0.05];
            for t in 0..12 {
                if t == 6 {
                    p.reset();
                    q.reset();
                    r.reset();
                }
                let (ap, mp) = p.act(&obs_of(x), ctx, true).unwrap();
                let (aq, mq) = q.act(&obs_of(x), ctx, true).unwrap();
                assert_eq!((ap, mp), (aq, mq));
                assert_eq!((ap, mp), r.act(&obs_of(x), ctx, true).unwrap());
                assert_eq!(mp.is_some(), mode == ContextMode::Cmask);
                assert!(ap.iter().all(|v| v.abs() <= 1.0));
                x = step_x(x, ap);
            }
            // sampled actions stay in the box; the context reaches the policy
            for _ in 0..20 {
                let (a_s, m_s) = p.act(&obs_of(x), ctx, false).unwrap();
                assert!(a_s
                    .iter()
                    .chain(m_s.iter().flatten())
                    .all(|v| v.abs() <= 1.0));
            }
            p.reset();
            let (lo, _) = p.act(&obs_of(0.3), [-0.15, -0.15], true).unwrap();
            p.reset();
            let (hi, _) = p.act(&obs_of(0.3), [0.15, 0.15], true).unwrap();
            assert_eq!(lo != hi, mode != ContextMode::None, "{mode:?}");
            assert!(p.act(&[0.0; 3], ctx, true).is_err());
            let other = Dreamer::new(tiny(ContextMode::Cmask), 2, 2).unwrap();
            if mode != ContextMode::Cmask {
                assert!(p.load(&other.policy_weights().unwrap()).is_err());
            }
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn cmask_masks_saturate_and_the_mask_sac_learns() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let data = collect(6, &mut rng);
        let mut agent = Dreamer::new(tiny(ContextMode::Cmask), 2, 2).unwrap();
        let set_bias = |agent: &mut Dreamer, value: [f32; 4]| {
            let mask = agent.policy.mask.as_mut().unwrap();
            let i = mask
                .tensors()
                .iter()
                .position(|t| t.name == "mask.out.bias");
            mask.update(&mut |j, v| {
                if Some(j) == i {
                    v.copy_from_slice(&value);
                }
            });
        };
        for (push, check) in [(20f32, 0.999f32), (-20.0, 0.001)] {
            set_bias(&mut agent, [push, push, 0.0, 0.0]);
            let mut p = agent.policy(0).unwrap();
            let (_, m) = p.act(&obs_of(0.5), [0.1, 0.1], true).unwrap();
            let m = m.unwrap();
            assert!(
                m.iter()
                    .all(|&v| if push > 0.0 { v >= check } else { v <= check }),
                "{m:?}"
            );
        }
        set_bias(&mut agent, [0.0; 4]);

        let bytes = |agent: &Dreamer| {
            let sac = agent.mask_sac.as_ref().unwrap();
            let mask = agent.policy.mask.as_ref().unwrap();
            let nets: [&dyn Parameters; 4] = [
                &sac.core.critics,
                &sac.core.targets,
                &sac.core.log_alpha,
                mask,
            ];
            nets.map(|n| to_safetensors(n).unwrap())
        };
        let before = bytes(&agent);
        let mut last = Metrics::new();
        for _ in 0..3 {
            last = agent.train_step(&sample(&data, 4, 16, &mut rng)).unwrap();
        }
        // critics, targets, temperature and mask actor all moved
        for (name, (a, b)) in ["critics", "targets", "log α", "mask actor"]
            .iter()
            .zip(before.iter().zip(bytes(&agent)))
        {
            assert_ne!(*a, b, "{name}");
        }
        for key in [
            "mask/q_loss",
            "mask/actor_loss",
            "mask/alpha",
            "mask/entropy",
            "mask/mean",
        ] {
            assert!(last[key].is_finite(), "{key}: {last:?}");
        }
        assert!((0.0..=1.0).contains(&last["mask/mean"]));
    }

    /// Mean return of `policy` over episodes from the starts `x0`.
    fn evaluate(mut act: impl FnMut(&[f32], bool) -> [f32; 2], starts: &[f32]) -> f64 {
        let mut total = 0.0;
        for &x0 in starts {
            let mut x = x0;
            for t in 0..EPISODE {
                x = step_x(x, act(&obs_of(x), t == 0));
                total += -x.abs() as f64;
            }
        }
        total / starts.len() as f64
    }

    #[test]
    fn a_step_split_over_workers_computes_the_same_losses_and_gradients() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let data = collect(10, &mut rng);
        let batch = sample(&data, 5, 16, &mut rng);
        for mode in [ContextMode::None, ContextMode::Cmask] {
            let run = |workers: usize| {
                let mut agent = Dreamer::new(tiny(mode), 2, 2).unwrap();
                agent.set_workers(workers);
                agent.train_step(&batch).unwrap()
            };
            let (one, three) = (run(1), run(3));
            assert_eq!(
                one.keys().collect::<Vec<_>>(),
                three.keys().collect::<Vec<_>>()
            );
            // every metric but the phases' wall times and FLOPs (the FLOP counter is the
            // process's, shared with the tests running beside this one)
            let measured = |k: &str| k.starts_with("seconds/") || k.starts_with("flops/");
            for (key, a) in one.iter().filter(|(k, _)| !measured(k)) {
                let b = three[key];
                assert!(
                    (a - b).abs() <= 1e-4 * (1.0 + a.abs()),
                    "{mode:?} {key}: {a} vs {b}"
                );
            }
        }
    }

    /// Trains an agent of `mode` for 300 steps on random point-mass data and returns the mean
    /// returns of its deterministic policy and of a random one over the same starts.
    fn point_mass_returns(mode: ContextMode) -> (f64, f64) {
        ctxrace_oracle::candle_on_one_thread();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let data = collect(60, &mut rng);
        let cfg = DreamerConfig {
            model_lr: 3e-3,
            ac_lr: 1e-3,
            ..tiny(mode)
        };
        let mut agent = Dreamer::new(cfg, 2, 2).unwrap();
        for _ in 0..300 {
            agent.train_step(&sample(&data, 4, 16, &mut rng)).unwrap();
        }
        let starts: Vec<f32> = (0..20).map(|i| -0.95 + 0.1 * i as f32).collect();
        let mut policy = agent.policy(0).unwrap();
        let learned = evaluate(
            |o, first| {
                if first {
                    policy.reset();
                }
                policy.act(o, [0.1, -0.1], true).unwrap().0
            },
            &starts,
        );
        let mut noise = ChaCha8Rng::seed_from_u64(6);
        let random = evaluate(
            |_, _| [noise.random_range(-1.0..1.0), noise.random_range(-1.0..1.0)],
            &starts.repeat(10),
        );
        eprintln!("{mode:?} return: learned {learned:.3}, random {random:.3}");
        (learned, random)
    }

    #[test]
    fn dreamer_learns_to_hold_the_point_mass_at_the_origin() {
        // seeds 0..=9 all reach returns of −1.0 to −2.1 by step 200–300 (random: about −8.2); with
        // a world-model rate of 1e-3 the reward head stays at its marginal for ~300 steps first
        let (learned, random) = point_mass_returns(ContextMode::None);
        assert!(learned > random + 4.0, "learned {learned}, random {random}");
    }

    #[test]
    fn cmask_learns_to_hold_the_point_mass_at_the_origin() {
        let (learned, random) = point_mass_returns(ContextMode::Cmask);
        assert!(learned > random + 4.0, "learned {learned}, random {random}");
    }
}
