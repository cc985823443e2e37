//! DreamerV3's behaviour learning in imagination, differentiated by hand on plain buffers
//! ([`ctxrace_nn`]): the forward pass of one shard of starts, then, once the
//! return scale is known from every shard, its backward pass to the actor's and the critic's
//! gradients. Two forms ([`ImaginationLoss`]); the default is the paper's code's.
//!
//! **Forward.** From `N` start states `s_0` (rows `[h, z, c]`), for `t = 0 … T−1` (`T = H − 1`
//! imagined steps in the paper's code, whose `H` states include the start; `T = H` in the
//! `dreamerv3` form): the actor's `Normal(tanh μ, σ)` on `s_t`,
//! `σ = (σ_max − σ_min) sigmoid(ρ + 2) + σ_min`; the action
//! `a_t = (μ + σ ε) / max(1, |μ + σ ε|)` (the factor a stop-gradient); the RSSM's prior step to
//! `s_{t+1}`. On the `T + 1` states: rewards `r` of `s_1 … s_T`, continue probabilities `c` of
//! `s_0 … s_T` (`s_1 … s_T` in the `dreamerv3` form, whose weights do not read `c(s_0)`), the
//! critic's values `v` of `s_0 … s_T` (one pass serves the λ-returns, the baseline and the
//! critic's loss), the slow critic's values of `s_0 … s_{T−1}`; the λ-returns `R`
//! ([`crate::returns`]) and the stop-gradient weights: `w_0 = 1`, `w_t = w_{t−1} γ c(s_{t−1})`
//! (paper's code), or `w_0 = 1 − terminal` of the start, `w_t = w_{t−1} γ c(s_t)` (`dreamerv3`).
//!
//! **Losses**, means over the `T N` terms: the actor's `−w (R − v)/S − η H[π]` (paper's code:
//! the gradient reaches the actor through every path of the imagined states, `R`'s rewards,
//! continue probabilities and values, the baseline `v`, and the entropy of `π(·|s_t)`), or
//! `−w ((R − sg v)/S + η H[π])` (`dreamerv3`: through `R`'s rewards and values only, the entropy
//! on stop-gradient states); the critic's `w CE(critic(sg s_t), twohot(R_t) + β twohot(v_slow))`;
//! each times the shard's share of the batch.
//!
//! **Backward.** `∂R = −w / S`, `∂H[π] = −η` (paper's code) or `−η w` (per term, times the share
//! over `T N`); the λ-returns pass theirs on: with `G_t` the total gradient of `R_t`,
//! `G_t = ∂R_t + λ γ c_t G_{t−1}` (from `R_{t−1}`), `∂r_{t+1} = G_t`,
//! `∂v_{t+1} += (1 − λ) γ c_{t+1} G_t`, at the end `∂v_T += λ γ c_T G_{T−1}`, and in the paper's
//! code `∂c_{t+1} = γ ((1 − λ) v_{t+1} + λ R_{t+1}) G_t` (`R_T = v_T`) and the baseline's
//! `∂v_t += w_t / S`. The reward and continue heads and the critic (frozen: their input's
//! gradient only) turn these into the gradients of `s_1 … s_T`, as does, in the paper's code,
//! the actor with the entropy's part of `∂ρ`; the RSSM's steps, from the last back, into those
//! of the earlier states and of the actions; the actions' into the actor's outputs,
//! `∂μ = ∂a (1 − tanh² μ)` and `∂ρ = (∂a ε + ∂H / σ)(σ_max − σ_min) s (1 − s)` with
//! `s = sigmoid(ρ + 2)` and the factor held fixed; and those into the actor's parameters, in
//! one pass over all `T N` rows (the actions read detached states). The critic's loss gives the
//! critic's parameters theirs. No gradient goes where none is read: the start states', the
//! critic's last row's, the frozen networks' weights'.

use crate::world_model::Starts;
use ctxrace_config::agents::{DreamerConfig, ImaginationLoss};
use ctxrace_nn::dreamer::{normal_rows, uniform_rows};
use ctxrace_nn::losses::{
    soft_cross_entropy, soft_cross_entropy_backward, twohot_decode, twohot_decode_backward,
};
use ctxrace_nn::{
    sigmoid, sized, InputGrad, Mlp, MlpGrads, MlpTrace, NonZeros, Rssm, StepScratch, StepTrace,
    TwoHot,
};
use rand_chacha::ChaCha8Rng;

/// The networks of a behaviour step (the actor's and the critic's weights as they are at its
/// start: the optimisers step after the backward passes).
pub(crate) struct Nets<'a> {
    pub(crate) rssm: &'a Rssm,
    pub(crate) actor: &'a Mlp,
    pub(crate) reward: &'a Mlp,
    pub(crate) cont: &'a Mlp,
    pub(crate) critic: &'a Mlp,
    pub(crate) slow: &'a Mlp,
}

/// The constants of a behaviour step.
pub(crate) struct Setting<'a> {
    pub(crate) cfg: &'a DreamerConfig,
    pub(crate) act_dim: usize,
    pub(crate) twohot: &'a TwoHot,
}

/// One shard's imagined trajectories, returns and what the backward pass needs, in buffers kept
/// from one training step to the next.
#[derive(Default)]
pub(crate) struct Imagination {
    /// Starts `N` and state width `F = D + Z + c`.
    n: usize,
    f: usize,
    /// The states `s_0 … s_T`, time-major rows `[(T + 1) N, F]`, and the non-zeros of their
    /// one-hot `z` (for every layer that reads them).
    states: Vec<f32>,
    non_zeros: NonZeros,
    /// Per action `[T N, A]`: the noise `ε`, `tanh μ`, `σ`, the factor `1 / max(1, |a|)`.
    noise: Vec<f32>,
    mean: Vec<f32>,
    std: Vec<f32>,
    shrink: Vec<f32>,
    actions: Vec<f32>,
    /// Gumbel uniforms of a step `[N, Z]`.
    uniform: Vec<f32>,
    actor: MlpTrace,
    steps: Vec<StepTrace>,
    reward_head: MlpTrace,
    cont_head: MlpTrace,
    critic: MlpTrace,
    slow: MlpTrace,
    /// `[T N]`: `r_{t+1}`, the slow critic's `v(s_t)`, `R_t`, `w_t`, `H[π(·|s_t)]`.
    reward: Vec<f32>,
    slow_value: Vec<f32>,
    returns: Vec<f32>,
    weights: Vec<f32>,
    entropy: Vec<f32>,
    /// `v(s_0) … v(s_T)` and `c(s_0) … c(s_T)` `[(T + 1) N]` (`c(s_0) = 0` in the `dreamerv3`
    /// form, which does not compute it).
    value: Vec<f32>,
    cont: Vec<f32>,
    /// Backward: the states' gradients `[(T + 1) N, F]`, the actions' `[T N, A]`, the actor's
    /// outputs' `[T N, 2 A]`, the heads' logits', the CE targets `[T N, K]`.
    d_states: Vec<f32>,
    d_actions: Vec<f32>,
    d_actor_out: Vec<f32>,
    d_logits: Vec<f32>,
    targets: Vec<f32>,
    step_scratch: StepScratch,
}

/// What a shard's backward pass gives: its parameters' gradients and its metrics.
pub(crate) struct ShardGrads {
    pub(crate) actor: MlpGrads,
    pub(crate) critic: MlpGrads,
    pub(crate) actor_loss: f64,
    pub(crate) critic_loss: f64,
    pub(crate) entropy: f64,
    pub(crate) reward: f64,
    pub(crate) ret: f64,
}

/// The mean of `x` (0 if empty).
fn mean(x: &[f32]) -> f64 {
    x.iter().map(|&v| v as f64).sum::<f64>() / x.len().max(1) as f64
}

/// The imagined steps `T` of a horizon `H`: `H − 1` in the paper's code, whose `H` states
/// include the start, `H` in the `dreamerv3` form.
pub(crate) fn imagined_steps(cfg: &DreamerConfig) -> usize {
    match cfg.imagination {
        ImaginationLoss::PaperCode => cfg.horizon.saturating_sub(1),
        ImaginationLoss::Dreamerv3 => cfg.horizon,
    }
}

impl Imagination {
    /// The λ-returns `R` `[T N]` of the last [`Imagination::forward`].
    pub(crate) fn returns(&self) -> &[f32] {
        &self.returns
    }

    /// Imagines `T` steps ([`imagined_steps`]) from `start` with the noise of the sequences'
    /// streams `rngs` (a start per step of each sequence), and computes the heads, the λ-returns
    /// and the weights.
    pub(crate) fn forward(
        &mut self,
        nets: &Nets,
        set: &Setting,
        start: &Starts,
        rngs: &mut [ChaCha8Rng],
    ) {
        let cfg = set.cfg;
        let (h, a) = (imagined_steps(cfg), set.act_dim);
        let (deter, stoch, ctx) = (&start.deter, &start.stoch, &start.ctx);
        let n = start.n;
        let (d, z) = (deter.len() / n.max(1), stoch.len() / n.max(1));
        let c = ctx.len() / n.max(1);
        let f = d + z + c;
        let per_sequence = n / rngs.len().max(1);
        (self.n, self.f) = (n, f);
        let hn = h * n;
        let states = sized(&mut self.states, (h + 1) * n * f);
        for (i, row) in states[..n * f].chunks_exact_mut(f).enumerate() {
            row[..d].copy_from_slice(&deter[i * d..(i + 1) * d]);
            row[d..d + z].copy_from_slice(&stoch[i * z..(i + 1) * z]);
            row[d + z..].copy_from_slice(&ctx[i * c..(i + 1) * c]);
        }
        self.non_zeros.reset(d..d + z);
        self.non_zeros.push(&states[..n * f], f);
        nets.actor.fit(&mut self.actor, hn);
        self.steps.resize_with(h, StepTrace::default);
        for buf in [
            &mut self.mean,
            &mut self.std,
            &mut self.shrink,
            &mut self.actions,
        ] {
            sized(buf, hn * a);
        }
        self.noise.clear();
        self.entropy.clear();
        let gauss = 0.5 * (1.0 + (2.0 * std::f32::consts::PI).ln());
        let (lo, span) = (cfg.min_std as f32, (cfg.max_std - cfg.min_std) as f32);
        for t in 0..h {
            let rows = t * n..(t + 1) * n;
            let (now, later) = self.states.split_at_mut((t + 1) * n * f);
            let state = &now[t * n * f..];
            let state = &state[..n * f];
            let input = self.non_zeros.rows(state, rows.clone());
            nets.actor.forward(input, &mut self.actor, rows.clone());
            let out = nets.actor.output(&self.actor, rows.clone());
            self.noise.extend(normal_rows(rngs, per_sequence, a));
            for i in 0..n {
                let (o, k) = (&out[i * 2 * a..(i + 1) * 2 * a], (t * n + i) * a);
                let mut log_std = 0.0;
                for j in 0..a {
                    let m = o[j].tanh();
                    let s = span * sigmoid(o[a + j] + 2.0) + lo;
                    let raw = m + s * self.noise[k + j];
                    let shrink = 1.0 / raw.abs().max(1.0);
                    self.mean[k + j] = m;
                    self.std[k + j] = s;
                    self.shrink[k + j] = shrink;
                    self.actions[k + j] = raw * shrink;
                    log_std += s.ln();
                }
                self.entropy.push(log_std + a as f32 * gauss);
            }
            self.uniform = uniform_rows(rngs, per_sequence, z);
            let action = &self.actions[t * n * a..(t + 1) * n * a];
            let next = &mut later[..n * f];
            nets.rssm
                .step(state, action, &self.uniform, &mut self.steps[t], next);
            self.non_zeros.push(next, f);
        }
        self.heads(nets, set, &start.cont);
    }

    /// The heads on the imagined states, the λ-returns and the weights.
    fn heads(&mut self, nets: &Nets, set: &Setting, start_cont: &[f32]) {
        let cfg = set.cfg;
        let (h, n, f) = (imagined_steps(cfg), self.n, self.f);
        let hn = h * n;
        let bins = set.twohot.bins();
        let nz = &self.non_zeros;
        let now = nz.rows(&self.states[..hn * f], 0..hn);
        let later = nz.rows(&self.states[n * f..], n..hn + n);
        let all = nz.rows(&self.states, 0..hn + n);
        nets.reward.fit(&mut self.reward_head, hn);
        nets.reward.forward(later, &mut self.reward_head, 0..hn);
        let logits = nets.reward.output(&self.reward_head, 0..hn);
        twohot_decode(logits, bins, sized(&mut self.reward, hn));
        // c(s_0) only for the paper's code's weights; the dreamerv3 form leaves it 0
        let paper = cfg.imagination == ImaginationLoss::PaperCode;
        let first = if paper { 0 } else { n };
        nets.cont.fit(&mut self.cont_head, hn + n);
        let input = if paper { all } else { later };
        nets.cont.forward(input, &mut self.cont_head, first..hn + n);
        let cont = sized(&mut self.cont, hn + n);
        cont[..first].fill(0.0);
        for (c, &l) in cont[first..]
            .iter_mut()
            .zip(nets.cont.output(&self.cont_head, first..hn + n))
        {
            *c = sigmoid(l);
        }
        nets.critic.fit(&mut self.critic, hn + n);
        nets.critic.forward(all, &mut self.critic, 0..hn + n);
        let logits = nets.critic.output(&self.critic, 0..hn + n);
        twohot_decode(logits, bins, sized(&mut self.value, hn + n));
        nets.slow.fit(&mut self.slow, hn);
        nets.slow.forward(now, &mut self.slow, 0..hn);
        let logits = nets.slow.output(&self.slow, 0..hn);
        twohot_decode(logits, bins, sized(&mut self.slow_value, hn));
        // R_T = v_T; R_t = r_{t+1} + γ c_{t+1} ((1 − λ) v_{t+1} + λ R_{t+1})
        let (gamma, lambda) = (cfg.gamma as f32, cfg.lambda as f32);
        let returns = sized(&mut self.returns, hn);
        for i in 0..n {
            let mut next = self.value[hn + i];
            for t in (0..h).rev() {
                let k = t * n + i;
                let blend = (1.0 - lambda) * self.value[k + n] + lambda * next;
                next = self.reward[k] + gamma * self.cont[k + n] * blend;
                returns[k] = next;
            }
        }
        // w_t = w_{t−1} γ c(s_{t−1}) from 1 (paper's code), or w_{t−1} γ c(s_t) from the start's
        let weights = sized(&mut self.weights, hn);
        if paper {
            weights[..n].fill(1.0);
        } else {
            weights[..n].copy_from_slice(start_cont);
        }
        let lag = if paper { n } else { 0 };
        for k in n..hn {
            weights[k] = weights[k - n] * self.cont[k - lag] * gamma;
        }
    }

    /// The backward pass of the shard's losses times `share` (its part of the batch), with the
    /// return scale `scale`: the actor's and the critic's gradients, and the shard's metrics.
    pub(crate) fn backward(
        &mut self,
        nets: &Nets,
        set: &Setting,
        scale: f32,
        share: f32,
    ) -> ShardGrads {
        let cfg = set.cfg;
        let (h, n, f, a) = (imagined_steps(cfg), self.n, self.f, set.act_dim);
        let (hn, k) = (h * n, set.twohot.count());
        let per_term = share / hn as f32;
        let (gamma, lambda, eta) = (cfg.gamma as f32, cfg.lambda as f32, cfg.entropy as f32);
        let paper = cfg.imagination == ImaginationLoss::PaperCode;
        // the λ-returns' gradients into r (held in `reward_grad`), v (in `value_grad`) and, in
        // the paper's code, c (in `cont_grad`, at the logits) and the baseline v
        let mut reward_grad = vec![0f32; hn];
        let mut value_grad = vec![0f32; hn + n];
        let mut cont_grad = vec![0f32; if paper { hn } else { 0 }];
        for i in 0..n {
            let mut carried = 0.0;
            for t in 0..h {
                let j = t * n + i;
                let d_return = -self.weights[j] / scale * per_term;
                let g = d_return + carried;
                reward_grad[j] = g;
                let c = self.cont[j + n];
                value_grad[j + n] += (1.0 - lambda) * gamma * c * g;
                carried = lambda * gamma * c * g;
                if paper {
                    value_grad[j] -= d_return;
                    let next_return = if t + 1 < h {
                        self.returns[j + n]
                    } else {
                        self.value[j + n]
                    };
                    let blend = (1.0 - lambda) * self.value[j + n] + lambda * next_return;
                    cont_grad[j] = gamma * blend * g * c * (1.0 - c);
                }
            }
            value_grad[hn + i] += carried;
        }
        let bins = set.twohot.bins();
        let nz = &self.non_zeros;
        let later = nz.rows(&self.states[n * f..], n..hn + n);
        let now = nz.rows(&self.states[..hn * f], 0..hn);
        // the states' gradients from the reward head and the critic (frozen), s_1 … s_T
        let d_states = sized(&mut self.d_states, (h + 1) * n * f);
        let d_logits = sized(&mut self.d_logits, hn * k);
        let logits = nets.reward.output(&self.reward_head, 0..hn);
        twohot_decode_backward(logits, bins, &reward_grad, d_logits);
        // h and z; the context is fixed
        let columns = 0..f - cfg.context.context_dim();
        let d_later = &mut d_states[n * f..];
        let target = InputGrad::new(d_later, f, columns.clone(), false);
        nets.reward.backward(
            later,
            &mut self.reward_head,
            0..hn,
            d_logits,
            None,
            Some(target),
        );
        let logits = nets.critic.output(&self.critic, n..hn + n);
        twohot_decode_backward(logits, bins, &value_grad[n..], d_logits);
        let target = InputGrad::new(d_later, f, columns.clone(), true);
        nets.critic.backward(
            later,
            &mut self.critic,
            n..hn + n,
            d_logits,
            None,
            Some(target),
        );
        // the paper's code: the continue head's (s_1 … s_T) and the entropy's (s_1 … s_{T−1})
        let span = (cfg.max_std - cfg.min_std) as f32;
        let d_entropy = |r: usize| match paper {
            true => -eta * per_term,
            false => -self.weights[r] * eta * per_term,
        };
        // ∂ρ from the gradient of σ
        let d_rho = |q: usize, d_std: f32| {
            let s = (self.std[q] - cfg.min_std as f32) / span;
            d_std * span * s * (1.0 - s)
        };
        let d_out = sized(&mut self.d_actor_out, hn * 2 * a);
        if paper {
            let target = InputGrad::new(d_later, f, columns.clone(), true);
            let cont_head = &mut self.cont_head;
            nets.cont
                .backward(later, cont_head, n..hn + n, &cont_grad, None, Some(target));
            for r in n..hn {
                for j in 0..a {
                    let q = r * a + j;
                    d_out[r * 2 * a + j] = 0.0;
                    d_out[r * 2 * a + a + j] = d_rho(q, d_entropy(r) / self.std[q]);
                }
            }
            let states = nz.rows(&self.states[n * f..hn * f], n..hn);
            let target = InputGrad::new(d_later, f, columns, true);
            let d_out = &d_out[n * 2 * a..];
            nets.actor
                .backward(states, &mut self.actor, n..hn, d_out, None, Some(target));
        }
        // the critic's own loss, on s_0 … s_{T−1} detached
        let targets = sized(&mut self.targets, hn * k);
        targets.fill(0.0);
        set.twohot.add_encoded(&self.returns, 1.0, targets);
        let reg = cfg.slow_critic_reg as f32;
        set.twohot.add_encoded(&self.slow_value, reg, targets);
        let logits = nets.critic.output(&self.critic, 0..hn);
        let mut ce = vec![0f32; hn];
        soft_cross_entropy(logits, &self.targets, &mut ce);
        let ce_grad: Vec<f32> = self.weights.iter().map(|w| w * per_term).collect();
        soft_cross_entropy_backward(logits, &self.targets, &ce_grad, d_logits);
        let mut critic = nets.critic.zero_grads();
        nets.critic.backward(
            now,
            &mut self.critic,
            0..hn,
            d_logits,
            Some(&mut critic),
            None,
        );
        // through the imagined steps, the last first: the actions' gradients
        let d_actions = sized(&mut self.d_actions, hn * a);
        for t in (0..h).rev() {
            let (before, after) = d_states.split_at_mut((t + 1) * n * f);
            let d_next = &after[..n * f];
            let d_state = (t > 0).then(|| &mut before[t * n * f..]);
            nets.rssm.step_backward(
                &mut self.steps[t],
                d_next,
                &mut d_actions[t * n * a..(t + 1) * n * a],
                d_state,
                &mut self.step_scratch,
            );
        }
        // into the actor's outputs, then its parameters
        for r in 0..hn {
            for j in 0..a {
                let q = r * a + j;
                let d_raw = d_actions[q] * self.shrink[q];
                let m = self.mean[q];
                d_out[r * 2 * a + j] = d_raw * (1.0 - m * m);
                let d_std = d_raw * self.noise[q] + d_entropy(r) / self.std[q];
                d_out[r * 2 * a + a + j] = d_rho(q, d_std);
            }
        }
        let mut actor = nets.actor.zero_grads();
        nets.actor
            .backward(now, &mut self.actor, 0..hn, d_out, Some(&mut actor), None);
        // metrics: the losses' values
        let mut actor_loss = 0f64;
        let mut critic_loss = 0f64;
        for t in 0..h {
            for i in 0..n {
                let j = t * n + i;
                let w = self.weights[j] as f64;
                let adv = (self.returns[j] - self.value[j]) as f64 / scale as f64;
                let bonus = cfg.entropy * self.entropy[j] as f64;
                actor_loss -= w * adv + if paper { bonus } else { w * bonus };
                critic_loss += w * ce[j] as f64;
            }
        }
        ShardGrads {
            actor,
            critic,
            actor_loss: actor_loss / hn as f64,
            critic_loss: critic_loss / hn as f64,
            entropy: mean(&self.entropy),
            reward: mean(&self.reward),
            ret: mean(&self.returns),
        }
    }
}
