//! SAC's core, written once for SAC ([`crate::sac`]) and cMask's mask SAC ([`crate::cmask`]):
//! the twin critics `Q_1, Q_2` and their Polyak targets, the temperature `log α`, the three
//! Adam optimisers (actor, critics, temperature) and one step of the losses of
//! [`crate::sac`]'s module doc, in that order: critics, actor (through the critics just
//! updated), temperature (with the step's `α` from before its update), targets.
//!
//! The actor is the caller's (SAC's own network, cMask's mask head in its policy): a step is
//! given it, with its log-std bounds, and steps it in place. Where the passes run and which
//! noise they draw is the caller's too ([`Passes`]): SAC's on its whole batch, the mask SAC's on
//! shards of masked transitions in parallel. The passes ([`Workspace::critic_pass`],
//! [`Workspace::actor_pass`]) differentiate the losses by hand on the networks' own buffers
//! (`ctxrace_nn`, the squashing's backward pass in
//! `ctxrace_nn::tanh_gaussian`): at SAC's batch of 100 rows the matrix products are small
//! and candle's per-operation bookkeeping was a third of a step. candle is the tests' oracle.

use crate::adam::Adam;
use crate::checkpoint;
use crate::error::SacError;
use ctxrace_nn::parameters::{init_with, polyak, to_safetensors, update_each, Draw};
use ctxrace_nn::tanh_gaussian::{squash_rows, squash_rows_backward};
use ctxrace_nn::{
    Activation, InputGrad, Mlp, MlpGrads, MlpShape, MlpTrace, NamedTensor, Parameters, Weights,
    WeightsError,
};
use std::path::Path;

/// Twin critics `Q_1, Q_2 (o, a)`: two ReLU MLPs `q1`, `q2` on `[o, a]` (SAC's, and the mask
/// SAC's with the mask as the action), their tensors named `q1.l0.fc.weight`, ….
#[derive(Clone)]
pub(crate) struct TwinCritics {
    /// `[Q_1, Q_2]`.
    pub(crate) q: [Mlp; 2],
}

impl TwinCritics {
    /// Critics on inputs `[o, a]` of `input` values, `layers` hidden layers of `hidden` units,
    /// their weights drawn from `seed` as `draw` says ([`init_with`], both critics as one store).
    pub(crate) fn new(
        input: usize,
        hidden: usize,
        layers: usize,
        seed: u64,
        draw: &dyn Fn(&NamedTensor) -> Draw,
    ) -> Result<Self, WeightsError> {
        let shape = MlpShape {
            input,
            units: hidden,
            layers,
            out: Some(1),
            act: Activation::Relu,
        };
        let mut weights = Weights::initial();
        let mut critics = Self {
            q: [
                Mlp::from_weights(&mut weights, "q1.", &shape)?,
                Mlp::from_weights(&mut weights, "q2.", &shape)?,
            ],
        };
        init_with(&mut critics, seed, draw);
        Ok(critics)
    }

    /// The critics' gradients `[Q_1's, Q_2's]` in the order of [`Parameters::tensors`].
    pub(crate) fn grad_tensors(&self, grads: [MlpGrads; 2]) -> Vec<Vec<f32>> {
        let mut out = Vec::new();
        for (g, q) in grads.into_iter().zip(&self.q) {
            g.push_tensors(q, &mut out);
        }
        out
    }
}

impl Parameters for TwinCritics {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        self.q.iter().flat_map(|q| q.tensors()).collect()
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        update_each(self.q.iter_mut().map(|q| q as &mut dyn Parameters), f);
    }
}

/// The temperature's logarithm `log α`, one value named `log_alpha`.
pub(crate) struct LogAlpha([f32; 1]);

impl LogAlpha {
    /// `log α = ln alpha`.
    pub(crate) fn new(alpha: f64) -> Self {
        Self([alpha.ln() as f32])
    }

    /// `α`.
    pub(crate) fn alpha(&self) -> f64 {
        self.0[0].exp() as f64
    }
}

impl Parameters for LogAlpha {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        vec![NamedTensor {
            name: "log_alpha",
            shape: vec![1],
            values: &self.0,
        }]
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        f(0, &mut self.0)
    }
}

/// The learning rates of the three optimisers (Adam with PyTorch's defaults, no clipping).
#[derive(Clone, Copy)]
pub(crate) struct LearningRates {
    /// The actor's.
    pub(crate) actor: f64,
    /// The critics'.
    pub(crate) critic: f64,
    /// The temperature's.
    pub(crate) alpha: f64,
}

/// What a [`SacCore`] is: its critics' sizes and seed, its temperature, optimisers and targets,
/// and the soft target's discount and action range.
#[derive(Clone, Copy)]
pub(crate) struct CoreConfig {
    /// The critics' input `[o, a]` width.
    pub(crate) input: usize,
    /// The critics' hidden units.
    pub(crate) hidden: usize,
    /// The critics' hidden layers.
    pub(crate) layers: usize,
    /// The seed the critics' weights are drawn from.
    pub(crate) seed: u64,
    /// `α` before the first step.
    pub(crate) initial_alpha: f64,
    /// The optimisers' learning rates.
    pub(crate) lr: LearningRates,
    /// Discount `γ`.
    pub(crate) gamma: f64,
    /// Polyak rate `τ`.
    pub(crate) tau: f64,
    /// The targets move on steps that are multiples of this.
    pub(crate) target_every: usize,
    /// Target entropy `H̄`.
    pub(crate) target_entropy: f64,
    /// The actor's actions' range after the tanh.
    pub(crate) range: ActionRange,
    /// The bounds the target critics' next actions are clamped to ([`SoftTarget::bounds`]).
    pub(crate) bounds: [f32; 2],
}

/// The file names (without `.safetensors`) a core's state is saved under in a checkpoint.
pub(crate) struct BlobNames {
    /// The critics' weights.
    pub(crate) critic: &'static str,
    /// The target critics' weights.
    pub(crate) target: &'static str,
    /// `log α`.
    pub(crate) alpha: &'static str,
    /// The actor's optimiser.
    pub(crate) opt_actor: &'static str,
    /// The critics' optimiser.
    pub(crate) opt_critic: &'static str,
    /// The temperature's optimiser.
    pub(crate) opt_alpha: &'static str,
}

/// Where a step's two passes run and which noise their samples take: over which transitions,
/// each weighted by its share of the losses' means (SAC's batch on one thread, the mask SAC's
/// shards in parallel, their results summed).
pub(crate) trait Passes {
    /// Why a pass failed (a step fails with it too).
    type Error: From<SacError>;

    /// [`Workspace::critic_pass`] on the transitions with `nets` and `soft` (the smoothing noise
    /// the passes' own, if any), summed.
    fn critic(
        &mut self,
        nets: (&[Mlp; 2], &[Mlp; 2], ActorNet),
        soft: SoftTarget,
    ) -> Result<CriticPass, Self::Error>;

    /// [`Workspace::actor_pass`] on the transitions with `nets`, the temperature and range
    /// `with`, summed.
    fn actor(
        &mut self,
        nets: (&[Mlp; 2], ActorNet),
        with: (f32, ActionRange),
    ) -> Result<ActorPass, Self::Error>;
}

/// What a step measured: the `α` it used, `L_Q`, the sum of `Q_1` and `Q_2` over the rows,
/// `L_π` and the weighted sum of `log π` (the mean, for weights summing to one).
#[derive(Clone, Copy, Debug)]
pub(crate) struct StepLosses {
    /// The `α` of the step (before its temperature update).
    pub(crate) alpha: f64,
    /// `L_Q`.
    pub(crate) critic_loss: f64,
    /// `Σ_rows (Q_1 + Q_2)`.
    pub(crate) q_sum: f64,
    /// `L_π`.
    pub(crate) actor_loss: f64,
    /// `Σ_rows w log π`.
    pub(crate) log_prob: f64,
}

/// SAC's twin critics, their targets, `log α` and the three optimisers (see the module doc).
pub(crate) struct SacCore {
    /// `Q_1, Q_2`.
    pub(crate) critics: TwinCritics,
    /// `Q̄_1, Q̄_2`.
    pub(crate) targets: TwinCritics,
    /// `log α`.
    pub(crate) log_alpha: LogAlpha,
    /// The actor's optimiser (over the network a step is given).
    pub(crate) actor_opt: Adam,
    /// The critics' optimiser.
    pub(crate) critic_opt: Adam,
    /// The temperature's optimiser.
    pub(crate) alpha_opt: Adam,
    /// What it was built with.
    pub(crate) cfg: CoreConfig,
}

impl SacCore {
    /// A fresh core for `actor` (the network its actor optimiser steps): critics drawn from
    /// `cfg.seed` as `draw` says, targets equal to them, `α = cfg.initial_alpha` (positive: the callers'
    /// configurations check it, naming their key).
    pub(crate) fn new(
        cfg: CoreConfig,
        actor: &Mlp,
        draw: &dyn Fn(&NamedTensor) -> Draw,
    ) -> Result<Self, WeightsError> {
        let critics = TwinCritics::new(cfg.input, cfg.hidden, cfg.layers, cfg.seed, draw)?;
        let targets = critics.clone();
        let log_alpha = LogAlpha::new(cfg.initial_alpha);
        let adam = |nets: &dyn Parameters, lr| Adam::new(nets, lr, 1e-8, f64::INFINITY);
        Ok(Self {
            actor_opt: adam(actor, cfg.lr.actor),
            critic_opt: adam(&critics, cfg.lr.critic),
            alpha_opt: adam(&log_alpha, cfg.lr.alpha),
            critics,
            targets,
            log_alpha,
            cfg,
        })
    }

    /// The current temperature `α`.
    pub(crate) fn alpha(&self) -> f64 {
        self.log_alpha.alpha()
    }

    /// One step (see the module doc) of the critics, `actor` (its network and log-std bounds,
    /// stepped in place), the temperature and, when `step` is a multiple of `target_every`,
    /// the targets, on the transitions of `passes`.
    pub(crate) fn step<P: Passes>(
        &mut self,
        (actor, log_std_clamp): (&mut Mlp, [f32; 2]),
        passes: &mut P,
        step: u64,
    ) -> Result<StepLosses, P::Error> {
        let alpha = self.alpha();
        let soft = SoftTarget {
            alpha: alpha as f32,
            gamma: self.cfg.gamma as f32,
            range: self.cfg.range,
            bounds: self.cfg.bounds,
            smoothing: &[],
        };
        let view = ActorNet {
            net: actor,
            log_std_clamp,
        };
        let critic = passes.critic((&self.critics.q, &self.targets.q, view), soft)?;
        let grads = self.critics.grad_tensors(critic.grads);
        self.critic_opt
            .step(&mut self.critics, &grads)
            .map_err(SacError::from)?;
        let pass = passes.actor((&self.critics.q, view), (alpha as f32, self.cfg.range))?;
        let grads = pass.grads.into_tensors(actor);
        self.actor_opt.step(actor, &grads).map_err(SacError::from)?;
        // temperature: L_α = −log α (mean log π + H̄), log π detached
        let gap = (pass.log_prob + self.cfg.target_entropy) as f32;
        self.alpha_opt
            .step(&mut self.log_alpha, &[vec![-gap]])
            .map_err(SacError::from)?;
        if step.is_multiple_of(self.cfg.target_every as u64) {
            polyak(&mut self.targets, &self.critics, self.cfg.tau);
        }
        Ok(StepLosses {
            alpha,
            critic_loss: critic.loss,
            q_sum: critic.q_sum,
            actor_loss: pass.loss,
            log_prob: pass.log_prob,
        })
    }

    /// The critics, targets, `log α` and optimisers as safetensors files named by `names`.
    pub(crate) fn blobs(
        &self,
        names: &BlobNames,
    ) -> Result<Vec<(&'static str, Vec<u8>)>, SacError> {
        Ok(vec![
            (names.critic, to_safetensors(&self.critics)?),
            (names.target, to_safetensors(&self.targets)?),
            (names.alpha, to_safetensors(&self.log_alpha)?),
            (names.opt_actor, self.actor_opt.to_bytes()?),
            (names.opt_critic, self.critic_opt.to_bytes()?),
            (names.opt_alpha, self.alpha_opt.to_bytes()?),
        ])
    }

    /// Restores what [`SacCore::blobs`] wrote into `dir` under `names`.
    pub(crate) fn load(&mut self, dir: &Path, names: &BlobNames) -> checkpoint::Result<()> {
        use ctxrace_nn::parameters::load_safetensors as load;
        checkpoint::load_blob(dir, names.critic, |b| load(&mut self.critics, b))?;
        checkpoint::load_blob(dir, names.target, |b| load(&mut self.targets, b))?;
        checkpoint::load_blob(dir, names.alpha, |b| load(&mut self.log_alpha, b))?;
        checkpoint::load_blob(dir, names.opt_actor, |b| self.actor_opt.load_bytes(b))?;
        checkpoint::load_blob(dir, names.opt_critic, |b| self.critic_opt.load_bytes(b))?;
        checkpoint::load_blob(dir, names.opt_alpha, |b| self.alpha_opt.load_bytes(b))
    }
}

/// Transitions as plain rows for a hand-differentiated pass, with the share of the losses' means
/// each row carries: `1/B` for SAC's batch, `valid / count` for a shard of cMask's masked
/// transitions.
pub(crate) struct WeightedTransitions<'a> {
    pub(crate) obs: &'a [f32],
    pub(crate) action: &'a [f32],
    pub(crate) reward: &'a [f32],
    pub(crate) next_obs: &'a [f32],
    pub(crate) terminal: &'a [f32],
    pub(crate) weight: &'a [f32],
}

/// The actions' range after the tanh, `a = scale · tanh(u) + shift`, which lowers `log π` by
/// `A log scale`.
#[derive(Clone, Copy)]
pub(crate) struct ActionRange {
    scale: f32,
    shift: f32,
}

impl ActionRange {
    /// `[−1, 1]`: SAC's actions.
    pub(crate) const SYMMETRIC: Self = Self {
        scale: 1.0,
        shift: 0.0,
    };
    /// `[0, 1]`: cMask's mask (the oracle's `mask_sample`).
    pub(crate) const UNIT: Self = Self {
        scale: 0.5,
        shift: 0.5,
    };

    /// The action at `tanh(u) = t`: `scale · t + shift`.
    pub(crate) fn at(self, t: f32) -> f32 {
        self.scale * t + self.shift
    }
}

/// What the soft target `y` is made of: the temperature, the discount, the next actions' range,
/// the bounds they are clamped to after the smoothing noise, and that noise.
#[derive(Clone, Copy)]
pub(crate) struct SoftTarget<'a> {
    pub(crate) alpha: f32,
    pub(crate) gamma: f32,
    pub(crate) range: ActionRange,
    /// `[lower, upper]` of the next actions the target critics see (no-op bounds of `range`,
    /// or cMask's paper-code `[0, 1]` on `tanh u`).
    pub(crate) bounds: [f32; 2],
    /// Clipped noise `[B, A]` added to the next actions before the clamp (TD3's smoothing);
    /// empty for none.
    pub(crate) smoothing: &'a [f32],
}

/// An actor's network with the bounds of its log standard deviation.
#[derive(Clone, Copy)]
pub(crate) struct ActorNet<'a> {
    pub(crate) net: &'a Mlp,
    pub(crate) log_std_clamp: [f32; 2],
}

/// The critics' side of a pass: their gradients, `L_Q` and the sum of `Q_1` and `Q_2` over the
/// rows.
pub(crate) struct CriticPass {
    pub(crate) grads: [MlpGrads; 2],
    pub(crate) loss: f64,
    pub(crate) q_sum: f64,
}

/// The actor's side of a pass: its gradients, `L_π` and the weighted sum of `log π`.
pub(crate) struct ActorPass {
    pub(crate) grads: MlpGrads,
    pub(crate) loss: f64,
    pub(crate) log_prob: f64,
}

/// A pass's results over some rows, which add up over the shards of a batch.
pub(crate) trait PassSum {
    /// Adds the results of `other` (other rows of the same batch) into these.
    fn add(&mut self, other: &Self);
}

impl PassSum for CriticPass {
    fn add(&mut self, other: &Self) {
        self.loss += other.loss;
        self.q_sum += other.q_sum;
        for (g, o) in self.grads.iter_mut().zip(&other.grads) {
            g.add(o);
        }
    }
}

impl PassSum for ActorPass {
    fn add(&mut self, other: &Self) {
        self.loss += other.loss;
        self.log_prob += other.log_prob;
        self.grads.add(&other.grads);
    }
}

/// The buffers of a SAC pass on plain rows, kept from one step to the next.
#[derive(Default)]
pub(crate) struct Workspace {
    actor: MlpTrace,
    q1: MlpTrace,
    q2: MlpTrace,
    /// The critics' input `[o, a]`.
    x: Vec<f32>,
    /// The actions before their range, `tanh u`.
    tanh: Vec<f32>,
}

impl Workspace {
    /// The critics' gradients of `L_Q = Σ_i w_i Σ_k (Q_k(o_i, a_i) − y_i)²` with
    /// `y = r + γ (1 − d) (min_k Q̄_k(o', a') − α log π(a' | o'))`, `a'` drawn with `noise`,
    /// the smoothing noise added and clamped to the target's bounds.
    pub(crate) fn critic_pass(
        &mut self,
        (critics, targets, actor): (&[Mlp; 2], &[Mlp; 2], ActorNet),
        tr: &WeightedTransitions,
        noise: &[f32],
        soft: SoftTarget,
    ) -> CriticPass {
        let b = tr.weight.len();
        let (mut next_action, next_logp) = self.sample(actor, tr.next_obs, noise, soft.range);
        for (k, a) in next_action.iter_mut().enumerate() {
            let smoothed = *a + soft.smoothing.get(k).copied().unwrap_or(0.0);
            *a = smoothed.clamp(soft.bounds[0], soft.bounds[1]);
        }
        self.join(tr.next_obs, &next_action, b);
        let target_q =
            [(&targets[0], &mut self.q1), (&targets[1], &mut self.q2)].map(|(q, trace)| {
                q.fit(trace, b);
                q.forward(&self.x, trace, 0..b);
                q.output(trace, 0..b).to_vec()
            });
        let y: Vec<f32> = (0..b)
            .map(|i| {
                let min_q = target_q[0][i].min(target_q[1][i]);
                let keep = soft.gamma * (1.0 - tr.terminal[i]);
                tr.reward[i] + keep * (min_q - soft.alpha * next_logp[i])
            })
            .collect();
        self.join(tr.obs, tr.action, b);
        let (mut loss, mut q_sum) = (0f64, 0f64);
        let grads = [(&critics[0], &mut self.q1), (&critics[1], &mut self.q2)].map(|(q, trace)| {
            q.forward(&self.x, trace, 0..b);
            let values = q.output(trace, 0..b);
            let mut dq = vec![0f32; b];
            for i in 0..b {
                let gap = values[i] - y[i];
                dq[i] = 2.0 * tr.weight[i] * gap;
                loss += (tr.weight[i] * gap * gap) as f64;
                q_sum += values[i] as f64;
            }
            let mut g = q.zero_grads();
            q.backward(&self.x, trace, 0..b, &dq, Some(&mut g), None);
            g
        });
        CriticPass { grads, loss, q_sum }
    }

    /// The actor's gradients of `L_π = Σ_i w_i (α log π(ã_i | o_i) − min_k Q_k(o_i, ã_i))`
    /// through `critics`, `ã` drawn with `noise`; the observations `obs` and weights `w`.
    pub(crate) fn actor_pass(
        &mut self,
        (critics, actor): (&[Mlp; 2], ActorNet),
        (obs, weight): (&[f32], &[f32]),
        noise: &[f32],
        (alpha, range): (f32, ActionRange),
    ) -> ActorPass {
        let b = weight.len();
        let a = actor.net.outputs() / 2;
        let (action, logp) = self.sample(actor, obs, noise, range);
        self.join(obs, &action, b);
        let values =
            [(&critics[0], &mut self.q1), (&critics[1], &mut self.q2)].map(|(q, trace)| {
                q.fit(trace, b);
                q.forward(&self.x, trace, 0..b);
                q.output(trace, 0..b).to_vec()
            });
        // −w to the smaller critic (half each on a tie)
        let (mut loss, mut log_prob) = (0f64, 0f64);
        let mut dq = [vec![0f32; b], vec![0f32; b]];
        for i in 0..b {
            let (v1, v2, w) = (values[0][i], values[1][i], weight[i]);
            loss += (w * (alpha * logp[i] - v1.min(v2))) as f64;
            log_prob += (w * logp[i]) as f64;
            let share = if v1 == v2 { 0.5 } else { 1.0 };
            dq[0][i] = if v1 <= v2 { -share * w } else { 0.0 };
            dq[1][i] = if v2 <= v1 { -share * w } else { 0.0 };
        }
        let o = obs.len() / b.max(1);
        let mut d_action = vec![0f32; b * a];
        for (k, (q, trace)) in [(&critics[0], &mut self.q1), (&critics[1], &mut self.q2)]
            .into_iter()
            .enumerate()
        {
            let into = InputGrad::new(&mut d_action, a, o..o + a, k > 0);
            q.backward(&self.x, trace, 0..b, &dq[k], None, Some(into));
        }
        d_action.iter_mut().for_each(|d| *d *= range.scale);
        let d_logp: Vec<f32> = weight.iter().map(|w| alpha * w).collect();
        let mut d_out = vec![0f32; b * 2 * a];
        let out = actor.net.output(&self.actor, 0..b);
        let with = (noise, actor.log_std_clamp);
        squash_rows_backward(out, with, &self.tanh, (&d_action, &d_logp), &mut d_out);
        let mut grads = actor.net.zero_grads();
        actor
            .net
            .backward(obs, &mut self.actor, 0..b, &d_out, Some(&mut grads), None);
        ActorPass {
            grads,
            loss,
            log_prob,
        }
    }

    /// The actor on the rows `obs` with `noise`: the actions in `range` and their
    /// log-probabilities (the outputs kept in the actor's trace, `tanh u` in `self.tanh`).
    fn sample(
        &mut self,
        actor: ActorNet,
        obs: &[f32],
        noise: &[f32],
        range: ActionRange,
    ) -> (Vec<f32>, Vec<f32>) {
        let a = actor.net.outputs() / 2;
        let b = noise.len() / a.max(1);
        actor.net.fit(&mut self.actor, b);
        actor.net.forward(obs, &mut self.actor, 0..b);
        self.tanh.resize(b * a, 0.0);
        let mut logp = vec![0f32; b];
        let out = actor.net.output(&self.actor, 0..b);
        squash_rows(out, noise, actor.log_std_clamp, &mut self.tanh, &mut logp);
        let action = self.tanh.iter().map(|t| range.scale * t + range.shift);
        let shift = a as f32 * range.scale.ln();
        logp.iter_mut().for_each(|l| *l -= shift);
        (action.collect(), logp)
    }

    /// `x ← [obs, action]` row by row, for `rows` rows.
    fn join(&mut self, obs: &[f32], action: &[f32], rows: usize) {
        if rows == 0 {
            self.x.clear();
            return;
        }
        let (o, a) = (obs.len() / rows, action.len() / rows);
        self.x.resize(rows * (o + a), 0.0);
        let pairs = obs.chunks_exact(o).zip(action.chunks_exact(a));
        for ((ob, ac), row) in pairs.zip(self.x.chunks_exact_mut(o + a)) {
            row[..o].copy_from_slice(ob);
            row[o..].copy_from_slice(ac);
        }
    }
}
