//! DreamerV3's world model (Hafner et al. 2023) as the paper's code ran it (REFERENCE §5), with the
//! context of cRSSM and cMask.
//!
//! `e_t = enc(symlog o_t)`; the RSSM runs over each sequence (`h_t = GRU(h_{t−1}, f([z_{t−1},
//! a_{t−1}, c]))`, posterior `z_t ~ q(h_t, e_t)`, prior `p(h_t)`), starting from zeros wherever
//! `is_first` (with a zero previous action). Heads on `x_t = [h_t, z_t, c]`: the decoder regresses
//! `symlog o_t` (squared error summed over the observation), the reward head `r_t` (symlog
//! two-hot), the continue head `1 − terminal_t` (Bernoulli logit). Loss per `(b, t)`:
//! `pred + 0.5 max(1, KL(sg q ‖ p)) + 0.1 max(1, KL(q ‖ sg p))`, averaged. One Adam (after
//! global-norm clipping) steps the encoder, the RSSM and the heads.
//!
//! The step is differentiated by hand on plain buffers (`ctxrace_nn`): the
//! sequence loop of the RSSM over `T` steps of a few rows each was mostly candle's per-operation
//! bookkeeping. Backward: the heads' and the prior's gradients of the posterior states, the KL
//! terms' of the posterior and prior logits (`∂ max(1, KL) = 0` below the free nats), then the
//! loop from the last step back ([`Rssm::observe_backward`]) to the embeddings, and the
//! encoder. Everything runs time-major (row `t B + b`); the starts go out batch-major.
//!
//! `[agent.dreamer] step_alignment = "paper-code"` reads the rows as the paper's code stores
//! them (`(o_t, a_t, r_{t+1})`, [`StepAlignment::PaperCode`]): the loop is the same (each row's
//! action enters the sequence model before that row's posterior), the encoder reads
//! `symlog [o_t, a_t]` and the decoder reconstructs it (its action target zeroed where an
//! episode starts inside a sequence, as the code leaves it). `initial_state = "learned"` starts
//! the sequences from the learned state ([`Rssm::initial_state`]), which the loss trains.
//!
//! The encoder and the RSSM are the acting policy's ([`PolicyNets`]: the actors run them); the
//! model holds the heads and trains all of them in place.

use crate::adam::Adam;
use crate::algorithm::Metrics;
use crate::error::{LearnerError, Result};
use crate::shards::{add_part, on_shards_with, weighted_mean};
use ctxrace_config::agents::{DreamerConfig, StepAlignment};
use ctxrace_config::SequenceBatch;
use ctxrace_nn::dreamer::{state_head, uniform_rows, PolicyNets};
use ctxrace_nn::initial_weights::init_dreamer;
use ctxrace_nn::losses::{
    categorical_kl, categorical_kl_backward, soft_cross_entropy, soft_cross_entropy_backward,
};
use ctxrace_nn::parameters::update_each;
use ctxrace_nn::{sigmoid, sized, symlog_value as symlog, TwoHot, Weights};
use ctxrace_nn::{
    InputGrad, Mlp, MlpGrads, MlpTrace, NamedTensor, NonZeros, ObserveTrace, Parameters, Rssm,
    RssmGrads,
};
use rand_chacha::ChaCha8Rng;

/// Posterior states to imagine from, `N = B·T` of them (batch-major rows: sequence `b`'s steps
/// are rows `b T … (b + 1) T − 1`).
pub(crate) struct Starts {
    /// `N`.
    pub(crate) n: usize,
    /// `h` `[N, D]`.
    pub(crate) deter: Vec<f32>,
    /// `z` `[N, Z]`.
    pub(crate) stoch: Vec<f32>,
    /// `1 − terminal` `[N]`.
    pub(crate) cont: Vec<f32>,
    /// The model context `[N, c]` (empty without one).
    pub(crate) ctx: Vec<f32>,
}

/// Sets the tensor `name` of `net` to zero (an output layer that starts silent).
pub(crate) fn zero_tensor<P: Parameters + ?Sized>(net: &mut P, name: &str) {
    let found = net.tensors().iter().position(|t| t.name == name);
    net.update(&mut |i, values| {
        if Some(i) == found {
            values.fill(0.0);
        }
    });
}

/// The decoder, reward and continue heads on `[h, z, c]` (the "heads" weights).
pub(crate) struct Heads {
    pub(crate) decoder: Mlp,
    pub(crate) reward: Mlp,
    pub(crate) cont: Mlp,
}

impl Heads {
    /// Heads of `cfg` for observations of `obs_dim` and actions of `act_dim`, initialised from
    /// `cfg.seed + 1`, the reward head's output layer at zero; the decoder reconstructs what
    /// the encoder reads.
    fn initial(cfg: &DreamerConfig, obs_dim: usize, act_dim: usize) -> Result<Self> {
        let w = &mut Weights::initial();
        let head = (cfg.head_units, cfg.head_layers);
        let decoded = cfg.encoder_inputs(obs_dim, act_dim);
        let mut heads = Self {
            decoder: state_head(cfg, w, "decoder.", (cfg.units, cfg.layers), decoded)?,
            reward: state_head(cfg, w, "reward.", head, cfg.bins)?,
            cont: state_head(cfg, w, "cont.", head, 1)?,
        };
        init_dreamer(
            &mut heads,
            cfg.seed.wrapping_add(1),
            cfg,
            (obs_dim, act_dim),
        );
        zero_tensor(&mut heads, "reward.out.weight");
        Ok(heads)
    }
}

impl Parameters for Heads {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        let mut v = self.decoder.tensors();
        v.extend(self.reward.tensors());
        v.extend(self.cont.tensors());
        v
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        let nets: [&mut dyn Parameters; 3] = [&mut self.decoder, &mut self.reward, &mut self.cont];
        update_each(nets, f);
    }
}

/// The decoder, reward and continue heads and the optimiser that trains them with the
/// policy's encoder and RSSM.
pub(crate) struct WorldModel {
    pub(crate) heads: Heads,
    twohot: TwoHot,
    /// Adam over the encoder, the RSSM and the heads.
    pub(crate) opt: Adam,
    cfg: DreamerConfig,
    /// Each shard's buffers, kept from one step to the next.
    work: Vec<ShardWork>,
}

/// The networks of one step.
struct Nets<'a> {
    encoder: &'a Mlp,
    rssm: &'a Rssm,
    decoder: &'a Mlp,
    reward: &'a Mlp,
    cont: &'a Mlp,
}

/// A shard's gradients of every parameter of the model.
struct ModelGrads {
    encoder: MlpGrads,
    rssm: RssmGrads,
    decoder: MlpGrads,
    reward: MlpGrads,
    cont: MlpGrads,
}

impl ModelGrads {
    /// Every gradient in the order of the optimiser's networks: encoder, RSSM, decoder, reward
    /// and continue heads.
    fn into_tensors(self, nets: &Nets) -> Vec<Vec<f32>> {
        let mut out = self.encoder.into_tensors(nets.encoder);
        out.extend(self.rssm.into_tensors(nets.rssm));
        self.decoder.push_tensors(nets.decoder, &mut out);
        self.reward.push_tensors(nets.reward, &mut out);
        self.cont.push_tensors(nets.cont, &mut out);
        out
    }

    fn zero(nets: &Nets) -> Self {
        Self {
            encoder: nets.encoder.zero_grads(),
            rssm: nets.rssm.zero_grads(),
            decoder: nets.decoder.zero_grads(),
            reward: nets.reward.zero_grads(),
            cont: nets.cont.zero_grads(),
        }
    }

    fn add(&mut self, other: &Self) {
        self.encoder.add(&other.encoder);
        self.rssm.add(&other.rssm);
        self.decoder.add(&other.decoder);
        self.reward.add(&other.reward);
        self.cont.add(&other.cont);
    }
}

/// One shard's inputs (time-major), traces and gradients' buffers.
#[derive(Default)]
struct ShardWork {
    /// The encoder's input `[N, I]` (`symlog o`, or `symlog [o, a]`), the decoder's target
    /// `[N, I]`, the rows' actions `[N, A]`, `1 − first` `[N]`, rewards `[N]`,
    /// `1 − terminal` `[N]`, the contexts `[N, c]`, the Gumbel uniforms `[N, Z]`.
    input: Vec<f32>,
    target: Vec<f32>,
    action: Vec<f32>,
    keep: Vec<f32>,
    reward: Vec<f32>,
    cont: Vec<f32>,
    ctx: Vec<f32>,
    uniform: Vec<f32>,
    encoder: MlpTrace,
    observe: ObserveTrace,
    prior: MlpTrace,
    /// The heads' input `[h, z, c]` `[N, F]` and the non-zeros of its `z`.
    x: Vec<f32>,
    x_non_zeros: NonZeros,
    decoder: MlpTrace,
    reward_head: MlpTrace,
    cont_head: MlpTrace,
    /// Backward buffers.
    d_x: Vec<f32>,
    dh: Vec<f32>,
    dz: Vec<f32>,
    d_post: Vec<f32>,
    d_prior: Vec<f32>,
    d_embed: Vec<f32>,
    d_out: Vec<f32>,
    targets: Vec<f32>,
}

impl WorldModel {
    /// Heads for observations of `obs_dim` and actions of `act_dim` ([`Heads::initial`]), and
    /// the optimiser of the policy's encoder and RSSM and the heads.
    pub(crate) fn new(
        cfg: &DreamerConfig,
        (obs_dim, act_dim): (usize, usize),
        policy: &mut PolicyNets,
    ) -> Result<Self> {
        let mut heads = Heads::initial(cfg, obs_dim, act_dim)?;
        // the moments of the policy's networks, then the heads' (the file's order)
        let policy_tensors = policy.encoder.tensors().len() + policy.rssm.tensors().len();
        let opt = Adam::in_groups(
            &Self::trained(policy, &mut heads)[..],
            &[policy_tensors],
            cfg.model_lr,
            cfg.model_eps,
            cfg.model_clip,
        );
        Ok(Self {
            heads,
            twohot: TwoHot::new(cfg.bins, -20.0, 20.0),
            opt,
            cfg: cfg.clone(),
            work: Vec::new(),
        })
    }

    /// The networks the optimiser steps, in its order: encoder, RSSM, decoder, reward, cont.
    fn trained<'a>(
        policy: &'a mut PolicyNets,
        heads: &'a mut Heads,
    ) -> [&'a mut dyn Parameters; 5] {
        [
            &mut policy.encoder,
            &mut policy.rssm,
            &mut heads.decoder,
            &mut heads.reward,
            &mut heads.cont,
        ]
    }

    /// One step of the world model (with the policy's encoder and RSSM) on the batch `seq`
    /// (model context `ctx` `[B·T, c]`, empty without one; Gumbel noise from the sequences'
    /// streams `rngs`), its shards' losses and gradients computed by `workers` threads in
    /// parallel; returns each shard's posterior states to imagine from.
    pub(crate) fn step(
        &mut self,
        policy: &mut PolicyNets,
        seq: &SequenceBatch,
        (ctx, workers): (&[f32], usize),
        rngs: &mut [ChaCha8Rng],
        metrics: &mut Metrics,
    ) -> Result<Vec<Starts>> {
        let (grads, starts) = self.gradients(policy, seq, (ctx, workers), rngs, metrics)?;
        let nets = &mut Self::trained(policy, &mut self.heads)[..];
        let norm = self.opt.step(nets, &grads)?;
        metrics.insert("model/grad_norm".into(), norm);
        Ok(starts)
    }

    /// The gradients of [`WorldModel::step`]'s loss in every parameter (in the optimiser's
    /// order), its metrics added to `metrics`, and the starts.
    pub(crate) fn gradients(
        &mut self,
        policy: &PolicyNets,
        seq: &SequenceBatch,
        (ctx, workers): (&[f32], usize),
        rngs: &mut [ChaCha8Rng],
        metrics: &mut Metrics,
    ) -> Result<(Vec<Vec<f32>>, Vec<Starts>)> {
        let mut work = std::mem::take(&mut self.work);
        work.resize_with(workers.clamp(1, seq.batch.max(1)), ShardWork::default);
        let this = &*self;
        let nets = Nets {
            encoder: &policy.encoder,
            rssm: &policy.rssm,
            decoder: &this.heads.decoder,
            reward: &this.heads.reward,
            cont: &this.heads.cont,
        };
        let parts = on_shards_with(workers, seq.batch, rngs, &mut work, |shard, rngs, w| {
            let z = this.cfg.stoch * this.cfg.classes;
            w.load(seq, ctx, &shard.rows, rngs, (z, this.cfg.step_alignment));
            let (m, grads, starts) = this.shard_step(&nets, w, shard.rows.len(), shard.weight);
            Ok((shard.weight, m, grads, starts))
        })?;
        let mut total = None;
        let mut shard_metrics = Vec::with_capacity(parts.len());
        let mut starts = Vec::with_capacity(parts.len());
        for (w, m, g, s) in parts {
            add_part(&mut total, g, ModelGrads::add);
            shard_metrics.push((w, m));
            starts.push(s);
        }
        let Some(total) = total else {
            return Err(LearnerError::NoSequences);
        };
        let grads = total.into_tensors(&nets);
        self.work = work;
        metrics.extend(weighted_mean(&shard_metrics));
        Ok((grads, starts))
    }

    /// The forward and backward passes of one shard of `batch` sequences (loaded into `w`), its
    /// loss times `share`: the metrics, the gradients and the starts.
    fn shard_step(
        &self,
        nets: &Nets,
        w: &mut ShardWork,
        batch: usize,
        share: f64,
    ) -> (Metrics, ModelGrads, Starts) {
        let cfg = &self.cfg;
        let n = w.keep.len();
        let (o, bins) = (w.target.len() / n, self.twohot.count());
        let rc = nets.rssm.config();
        let (d, z, c) = (rc.deter, rc.stoch * rc.classes, rc.context_dim);
        let f = d + z + c;
        // forward: the embeddings, the loop, the prior, the heads
        nets.encoder.fit(&mut w.encoder, n);
        nets.encoder.forward(&w.input, &mut w.encoder, 0..n);
        let embed = if nets.encoder.outputs() == 0 {
            &w.input[..]
        } else {
            nets.encoder.output(&w.encoder, 0..n)
        };
        let inputs = (embed, &w.action[..], &w.ctx[..], &w.keep[..]);
        nets.rssm.observe(batch, inputs, &w.uniform, &mut w.observe);
        let (h, zs, post) = w.observe.states();
        let prior_net = nets.rssm.prior();
        prior_net.fit(&mut w.prior, n);
        prior_net.forward(h, &mut w.prior, 0..n);
        let prior = prior_net.output(&w.prior, 0..n);
        let x = sized(&mut w.x, n * f);
        for (i, row) in x.chunks_exact_mut(f).enumerate() {
            row[..d].copy_from_slice(&h[i * d..(i + 1) * d]);
            row[d..d + z].copy_from_slice(&zs[i * z..(i + 1) * z]);
            row[d + z..].copy_from_slice(&w.ctx[i * c..(i + 1) * c]);
        }
        w.x_non_zeros.reset(d..d + z);
        w.x_non_zeros.push(&w.x, f);
        for (net, trace) in [
            (&nets.decoder, &mut w.decoder),
            (&nets.reward, &mut w.reward_head),
            (&nets.cont, &mut w.cont_head),
        ] {
            net.fit(trace, n);
            net.forward(w.x_non_zeros.rows(&w.x, 0..n), trace, 0..n);
        }
        // the losses per row, and each one's gradient: share / N each
        let g = (share / n as f64) as f32;
        let pred_g = g * cfg.pred_scale as f32;
        let mut grads = ModelGrads::zero(nets);
        let d_x = sized(&mut w.d_x, n * f);
        let columns = 0..d + z;
        // decoder: Σ (dec − target)²
        let dec = nets.decoder.output(&w.decoder, 0..n);
        let d_out = sized(&mut w.d_out, n * o);
        let mut recon = 0f64;
        for ((dd, &y), &t) in d_out.iter_mut().zip(dec).zip(&w.target) {
            recon += ((y - t) * (y - t)) as f64;
            *dd = 2.0 * pred_g * (y - t);
        }
        let dec_grads = Some(&mut grads.decoder);
        nets.decoder.backward(
            w.x_non_zeros.rows(&w.x, 0..n),
            &mut w.decoder,
            0..n,
            d_out,
            dec_grads,
            Some(InputGrad::new(d_x, f, columns.clone(), false)),
        );
        // reward: two-hot cross-entropy
        let targets = sized(&mut w.targets, n * bins);
        targets.fill(0.0);
        self.twohot.add_encoded(&w.reward, 1.0, targets);
        let logits = nets.reward.output(&w.reward_head, 0..n);
        let mut ce = vec![0f32; n];
        soft_cross_entropy(logits, &w.targets, &mut ce);
        let d_out = sized(&mut w.d_out, n * bins);
        soft_cross_entropy_backward(logits, &w.targets, &vec![pred_g; n], d_out);
        let rew_grads = Some(&mut grads.reward);
        nets.reward.backward(
            w.x_non_zeros.rows(&w.x, 0..n),
            &mut w.reward_head,
            0..n,
            d_out,
            rew_grads,
            Some(InputGrad::new(d_x, f, columns.clone(), true)),
        );
        // continue: binary cross-entropy of the logit
        let logits = nets.cont.output(&w.cont_head, 0..n);
        let d_out = sized(&mut w.d_out, n);
        let mut bce = 0f64;
        for ((dd, &l), &y) in d_out.iter_mut().zip(logits).zip(&w.cont) {
            bce += (l.max(0.0) - y * l + (-l.abs()).exp().ln_1p()) as f64;
            *dd = pred_g * (sigmoid(l) - y);
        }
        let cont_grads = Some(&mut grads.cont);
        nets.cont.backward(
            w.x_non_zeros.rows(&w.x, 0..n),
            &mut w.cont_head,
            0..n,
            d_out,
            cont_grads,
            Some(InputGrad::new(d_x, f, columns.clone(), true)),
        );
        // KL balance: max(free, KL(sg q ‖ p)) trains the prior, max(free, KL(q ‖ sg p)) the
        // posterior; below the free nats neither
        let unimix = cfg.unimix as f32;
        let mut kl = vec![0f32; n];
        categorical_kl(post, prior, rc.classes, unimix, &mut kl);
        let free = cfg.free_nats as f32;
        let above: Vec<f32> = kl.iter().map(|&k| f32::from(k > free)).collect();
        let dyn_g: Vec<f32> = above.iter().map(|a| a * g * cfg.kl_dyn as f32).collect();
        let rep_g: Vec<f32> = above.iter().map(|a| a * g * cfg.kl_rep as f32).collect();
        let d_prior = sized(&mut w.d_prior, n * z);
        categorical_kl_backward(
            post,
            prior,
            &dyn_g,
            (rc.classes, unimix),
            (&mut [], d_prior),
        );
        let d_post = sized(&mut w.d_post, n * z);
        categorical_kl_backward(post, prior, &rep_g, (rc.classes, unimix), (d_post, &mut []));
        // the states' gradients: the heads', then the prior's
        let dh = sized(&mut w.dh, n * d);
        let dz = sized(&mut w.dz, n * z);
        for ((row, dhr), dzr) in w
            .d_x
            .chunks_exact(f)
            .zip(dh.chunks_exact_mut(d))
            .zip(dz.chunks_exact_mut(z))
        {
            dhr.copy_from_slice(&row[..d]);
            dzr.copy_from_slice(&row[d..d + z]);
        }
        let target = InputGrad::new(dh, d, 0..d, true);
        let prior_grads = Some(&mut grads.rssm.prior);
        prior_net.backward(h, &mut w.prior, 0..n, &w.d_prior, prior_grads, Some(target));
        // the loop, then the encoder
        let e = embed.len() / n;
        let d_embed = sized(&mut w.d_embed, n * e);
        nets.rssm.observe_backward(
            batch,
            &w.keep,
            &mut w.observe,
            (&mut w.dh, &mut w.dz),
            &w.d_post,
            d_embed,
            &mut grads.rssm,
        );
        let enc_grads = Some(&mut grads.encoder);
        nets.encoder
            .backward(&w.input, &mut w.encoder, 0..n, &w.d_embed, enc_grads, None);
        // metrics and the starts, batch-major
        let per_row = |sum: f64| sum / n as f64;
        let kl_sum: f64 = kl.iter().map(|&k| k as f64).sum();
        let reward_sum: f64 = ce.iter().map(|&v| v as f64).sum();
        let kl_terms: f64 = kl
            .iter()
            .map(|&k| (k.max(free) as f64) * (cfg.kl_dyn + cfg.kl_rep))
            .sum();
        let pred = (recon + reward_sum + bce) * cfg.pred_scale;
        let mut metrics = Metrics::new();
        metrics.insert("model/loss".into(), per_row(pred + kl_terms));
        metrics.insert("model/recon".into(), per_row(recon));
        metrics.insert("model/reward".into(), per_row(reward_sum));
        metrics.insert("model/cont".into(), per_row(bce));
        metrics.insert("model/kl".into(), per_row(kl_sum));
        let (h, zs, _) = w.observe.states();
        let length = n / batch.max(1);
        let batch_major = |x: &[f32], width: usize| -> Vec<f32> {
            let mut out = vec![0f32; x.len()];
            for b in 0..batch {
                for t in 0..length {
                    let (from, to) = ((t * batch + b) * width, (b * length + t) * width);
                    out[to..to + width].copy_from_slice(&x[from..from + width]);
                }
            }
            out
        };
        let starts = Starts {
            n,
            deter: batch_major(h, d),
            stoch: batch_major(zs, z),
            cont: batch_major(&w.cont, 1),
            ctx: batch_major(&w.ctx, c),
        };
        (metrics, grads, starts)
    }
}

impl ShardWork {
    /// The shard's sequences `rows` of `seq` (and of the context `ctx`, batch-major rows of
    /// `c` values), time-major, read as `alignment` says, with the loop's Gumbel uniforms (`z`
    /// per step and sequence) from the sequences' streams `rngs`.
    fn load(
        &mut self,
        seq: &SequenceBatch,
        ctx: &[f32],
        rows: &std::ops::Range<usize>,
        rngs: &mut [ChaCha8Rng],
        (z, alignment): (usize, StepAlignment),
    ) {
        let (b, t_len) = (rows.len(), seq.length);
        let (o, a) = (seq.obs_dim, seq.act_dim);
        let c = ctx.len() / (seq.batch * t_len).max(1);
        let n = b * t_len;
        let with_action = alignment == StepAlignment::PaperCode;
        let i_w = if with_action { o + a } else { o };
        for (v, width) in [
            (&mut self.input, i_w),
            (&mut self.target, i_w),
            (&mut self.action, a),
            (&mut self.keep, 1),
            (&mut self.reward, 1),
            (&mut self.cont, 1),
            (&mut self.ctx, c),
        ] {
            sized(v, n * width);
        }
        for (i, seq_row) in rows.clone().enumerate() {
            for t in 0..t_len {
                let (from, to) = (seq_row * t_len + t, t * b + i);
                let action = &seq.action[from * a..(from + 1) * a];
                let input = &mut self.input[to * i_w..(to + 1) * i_w];
                for (dst, src) in input.iter_mut().zip(&seq.obs[from * o..(from + 1) * o]) {
                    *dst = symlog(*src);
                }
                if with_action {
                    for (dst, src) in input[o..].iter_mut().zip(action) {
                        *dst = symlog(*src);
                    }
                }
                let target = &mut self.target[to * i_w..(to + 1) * i_w];
                target.copy_from_slice(input);
                if with_action && t > 0 && seq.is_first[from] == 1.0 {
                    // the code zeroes the row's action in place (`prev_action *= 1 − is_first`)
                    // after the encoder read it and before the decoder's loss does
                    target[o..].fill(0.0);
                }
                self.action[to * a..(to + 1) * a].copy_from_slice(action);
                self.ctx[to * c..(to + 1) * c].copy_from_slice(&ctx[from * c..(from + 1) * c]);
                self.keep[to] = 1.0 - seq.is_first[from];
                self.reward[to] = seq.reward[from];
                self.cont[to] = 1.0 - seq.is_terminal[from];
            }
        }
        self.uniform.clear();
        for _ in 0..t_len {
            self.uniform.extend(uniform_rows(rngs, 1, z));
        }
    }
}

#[cfg(test)]
pub(crate) mod oracle {
    //! The networks as candle modules holding the plain networks' weights: the tests' oracle.
    use super::*;
    use candle_core::backprop::GradStore;
    use ctxrace_nn::parameters::to_safetensors;
    use ctxrace_nn::Activation;
    use ctxrace_oracle::{DreamerNets, Mlp as CandleMlp, ParamStore};

    /// A candle head on `[h, z, c]` of `cfg` under `vb` ([`state_head`]'s).
    pub(crate) fn head(
        cfg: &DreamerConfig,
        vb: candle_nn::VarBuilder,
        (units, layers): (usize, usize),
        out: usize,
    ) -> CandleMlp {
        let (d, z) = (cfg.deter, cfg.stoch * cfg.classes);
        let input = d + z + cfg.context.context_dim();
        CandleMlp::new(input, units, layers, Some(out), Activation::SiluNorm, vb)
            .unwrap()
            .sparse_inputs(d..d + z)
    }

    /// The candle modules `build` makes in a store that then holds the weights of `nets`.
    pub(crate) fn store_of<N: Parameters + ?Sized, T>(
        nets: &N,
        build: impl FnOnce(candle_nn::VarBuilder) -> T,
    ) -> (ParamStore, T) {
        let store = ParamStore::new();
        let built = build(store.builder());
        store.load_bytes(&to_safetensors(nets).unwrap()).unwrap();
        (store, built)
    }

    /// The policy's networks as candle modules.
    pub(crate) fn policy(
        cfg: &DreamerConfig,
        (obs_dim, act_dim): (usize, usize),
        nets: &PolicyNets,
    ) -> (ParamStore, DreamerNets) {
        store_of(nets, |vb| {
            DreamerNets::new(cfg, obs_dim, act_dim, vb).unwrap()
        })
    }

    /// The heads as candle modules: decoder, reward, continue.
    pub(crate) fn heads(
        cfg: &DreamerConfig,
        (obs_dim, act_dim): (usize, usize),
        heads: &Heads,
    ) -> (ParamStore, [CandleMlp; 3]) {
        store_of(heads, |vb| {
            let size = (cfg.head_units, cfg.head_layers);
            let decoded = cfg.encoder_inputs(obs_dim, act_dim);
            [
                head(cfg, vb.pp("decoder"), (cfg.units, cfg.layers), decoded),
                head(cfg, vb.pp("reward"), size, cfg.bins),
                head(cfg, vb.pp("cont"), size, 1),
            ]
        })
    }

    /// The values of the gradient `grads` holds for the tensor `name` of `store`.
    pub(crate) fn grad(grads: &GradStore, store: &ParamStore, name: &str) -> Option<Vec<f32>> {
        let (_, var) = store.named().into_iter().find(|(n, _)| n == name)?;
        grads
            .get(var.as_tensor())?
            .flatten_all()
            .ok()?
            .to_vec1()
            .ok()
    }

    /// Sets every tensor of `net` named `*out.weight` to normal values of deviation `std` (an
    /// output layer that is not zero, so that its path weighs).
    pub(crate) fn randomise_outputs<P: Parameters + ?Sized>(net: &mut P, std: f32, seed: u64) {
        randomise(net, |name| name.ends_with("out.weight"), std, seed);
    }

    /// Sets the tensors of `net` whose names `pick` picks to normal values of deviation `std`.
    pub(crate) fn randomise<P: Parameters + ?Sized>(
        net: &mut P,
        pick: impl Fn(&str) -> bool,
        std: f32,
        seed: u64,
    ) {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let picked: Vec<bool> = net.tensors().iter().map(|t| pick(t.name)).collect();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let normal = Normal::new(0.0, std).unwrap();
        net.update(&mut |i, values| {
            if picked[i] {
                values.iter_mut().for_each(|v| *v = normal.sample(&mut rng));
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::oracle::{grad, randomise};
    use super::*;
    use crate::sequences::SeqData;
    use candle_core::{Device, Module, Tensor};
    use ctxrace_config::agents::{ContextMode, InitialState};
    use ctxrace_oracle::dreamer::uniforms_per;
    use ctxrace_oracle::{
        symlog as symlog_tensor, DreamerNets, FromOracle, Mlp as CandleMlp, ParamStore, RssmState,
        TwoHotTensors,
    };
    use rand::{Rng, SeedableRng};

    /// The world model's loss on `d` (its actions `[B, T, A]`) composed of candle operations on
    /// the candle copies `nets` and `[decoder, reward, cont]` of its networks, autograd's
    /// statement of what [`WorldModel::gradients`] differentiates by hand, with the loop's
    /// noise from `rngs`.
    fn candle_loss(
        m: &WorldModel,
        (nets, [decoder, reward, cont]): (&DreamerNets, &[CandleMlp; 3]),
        (d, actions): (&SeqData, &Tensor),
        ctx: Option<&Tensor>,
        rngs: &mut [ChaCha8Rng],
    ) -> Tensor {
        let cfg = &m.cfg;
        let (b, t_len, n) = (d.batch, d.length, d.batch * d.length);
        let (s, c) = (cfg.stoch, cfg.classes);
        let obs = symlog_tensor(&d.flat(&d.obs).unwrap()).unwrap();
        let (input, target) = match cfg.step_alignment {
            StepAlignment::Ctxrace => (obs.clone(), obs),
            StepAlignment::PaperCode => {
                let a = symlog_tensor(&actions.reshape((n, ())).unwrap()).unwrap();
                // the decoder's action target is zero where an episode starts at t > 0
                let first: Vec<f32> = d.first.flatten_all().unwrap().to_vec1().unwrap();
                let kept: Vec<f32> = (0..n)
                    .map(|i| 1.0 - f32::from(i % t_len > 0) * first[i])
                    .collect();
                let kept = Tensor::from_vec(kept, (n, 1), &Device::Cpu).unwrap();
                let a_target = a.broadcast_mul(&kept).unwrap();
                (
                    Tensor::cat(&[&obs, &a], 1).unwrap(),
                    Tensor::cat(&[&obs, &a_target], 1).unwrap(),
                )
            }
        };
        let time_major = |x: &Tensor| x.transpose(0, 1).unwrap().contiguous().unwrap();
        let embed = nets
            .encoder
            .forward(&input)
            .unwrap()
            .reshape((b, t_len, ()))
            .unwrap();
        let embed = time_major(&embed);
        let actions = time_major(actions);
        let keeps = time_major(&(1.0 - &d.first).unwrap());
        let ctx_tm = ctx.map(|c| time_major(&c.reshape((b, t_len, ())).unwrap()));
        let init = nets.rssm.initial(b).unwrap();
        let mut state = init.clone();
        let (mut deters, mut stochs, mut posts) = (Vec::new(), Vec::new(), Vec::new());
        for t in 0..t_len {
            let keep = keeps.get(t).unwrap().unsqueeze(1).unwrap();
            let blend = |x: &Tensor, x0: &Tensor| {
                let start = x0.broadcast_mul(&(1.0 - &keep).unwrap()).unwrap();
                (x.broadcast_mul(&keep).unwrap() + start).unwrap()
            };
            let prev = RssmState {
                deter: blend(&state.deter, &init.deter),
                stoch: blend(&state.stoch, &init.stoch),
            };
            let action = actions.get(t).unwrap().broadcast_mul(&keep).unwrap();
            let c_t = ctx_tm.as_ref().map(|c| c.get(t).unwrap());
            let uniform = uniforms_per(rngs, 1, (s, c)).unwrap();
            let (next, post) = nets
                .rssm
                .obs_step(
                    &prev,
                    &action,
                    c_t.as_ref(),
                    &embed.get(t).unwrap(),
                    &uniform,
                )
                .unwrap();
            deters.push(next.deter.clone());
            stochs.push(next.stoch.clone());
            posts.push(post);
            state = next;
        }
        let batch_major = |xs: &[Tensor]| Tensor::stack(xs, 1).unwrap().reshape((n, ())).unwrap();
        let deter = batch_major(&deters);
        let prior = nets.rssm.prior_logits(&deter).unwrap();
        let post = batch_major(&posts).reshape((n, s, c)).unwrap();
        let posterior = RssmState {
            deter,
            stoch: batch_major(&stochs),
        };
        let x = posterior.head_input(ctx).unwrap();
        let recon = (decoder.forward(&x).unwrap() - &target)
            .unwrap()
            .sqr()
            .unwrap()
            .sum(1)
            .unwrap();
        let reward = m
            .twohot
            .loss(
                &reward.forward(&x).unwrap(),
                &d.reward.flatten_all().unwrap(),
            )
            .unwrap();
        let y = (1.0 - d.terminal.flatten_all().unwrap()).unwrap();
        let l = cont.forward(&x).unwrap().squeeze(1).unwrap();
        let softplus_tail = (l.abs().unwrap().neg().unwrap().exp().unwrap() + 1.0)
            .unwrap()
            .log()
            .unwrap();
        let cont = ((l.relu().unwrap() - l.mul(&y).unwrap()).unwrap() + softplus_tail).unwrap();
        let dyn_kl = nets
            .rssm
            .kl(&post.detach(), &prior)
            .unwrap()
            .maximum(cfg.free_nats)
            .unwrap();
        let rep_kl = nets
            .rssm
            .kl(&post, &prior.detach())
            .unwrap()
            .maximum(cfg.free_nats)
            .unwrap();
        let pred = ((recon + reward).unwrap() + cont).unwrap();
        let kl = ((dyn_kl * cfg.kl_dyn).unwrap() + (rep_kl * cfg.kl_rep).unwrap()).unwrap();
        ((pred * cfg.pred_scale).unwrap() + kl)
            .unwrap()
            .mean_all()
            .unwrap()
    }

    /// A batch of random sequences with episodes starting within them.
    fn random_batch(b: usize, t: usize, rng: &mut ChaCha8Rng) -> SequenceBatch {
        let n = b * t;
        let mut v = |k: usize, lo: f32, hi: f32| -> Vec<f32> {
            (0..k).map(|_| rng.random_range(lo..hi)).collect()
        };
        SequenceBatch {
            batch: b,
            length: t,
            obs_dim: 3,
            act_dim: 2,
            obs: v(n * 3, -2.0, 2.0),
            action: v(n * 2, -1.0, 1.0),
            reward: v(n, -3.0, 3.0),
            is_first: (0..n)
                .map(|i| f32::from(i % t == 0 || i % 7 == 3))
                .collect(),
            is_terminal: (0..n).map(|i| f32::from(i % 11 == 5)).collect(),
            context: v(n * 2, -0.15, 0.15),
            mask: vec![1.0; n * 2],
            has_mask: vec![1.0; n],
        }
    }

    /// The hand-differentiated world model computes the loss and every parameter's gradient of
    /// the candle composition, with and without a context, over sequences that start anew
    /// inside the batch, on one shard and on two, as ctxrace reads its rows from zeros and as the
    /// paper's code does from its learned initial state.
    #[test]
    fn the_model_step_differentiates_the_candle_composition() {
        let ctxrace = DreamerConfig::default();
        let code = DreamerConfig::default().with_paper_code_world_model();
        for (mode, workers, form) in [
            (ContextMode::None, 1, &ctxrace),
            (ContextMode::Crssm, 2, &ctxrace),
            (ContextMode::None, 1, &code),
            (ContextMode::Crssm, 2, &code),
        ] {
            let cfg = DreamerConfig {
                context: mode,
                units: 16,
                layers: 2,
                deter: 16,
                hidden: 12,
                stoch: 3,
                classes: 4,
                head_units: 16,
                head_layers: 2,
                free_nats: 0.01,
                ..form.clone()
            };
            let mut policy = PolicyNets::from_weights(&cfg, 3, 2, &mut Weights::initial()).unwrap();
            ctxrace_nn::parameters::init(&mut policy, 4);
            // a learned initial state away from zero, where its prior's classes do not tie
            randomise(&mut policy, |n| n == "rssm.initial_state.w", 1.0, 1);
            let mut model = WorldModel::new(&cfg, (3, 2), &mut policy).unwrap();
            // a reward head that is not zero, so that its path weighs
            randomise(&mut model.heads, |n| n == "reward.out.weight", 0.3, 2);
            let (policy_store, nets) = oracle::policy(&cfg, (3, 2), &policy);
            let (heads_store, heads) = oracle::heads(&cfg, (3, 2), &model.heads);
            let mut rng = ChaCha8Rng::seed_from_u64(9);
            let seq = random_batch(4, 10, &mut rng);
            let d = SeqData::new(&seq, 3, 2).unwrap();
            let ctx = nets.context(&d.flat(&d.context).unwrap(), None).unwrap();
            let ctx_rows = match &ctx {
                Some(c) => c.flatten_all().unwrap().to_vec1().unwrap(),
                None => Vec::new(),
            };
            let streams = || -> Vec<ChaCha8Rng> {
                (0..4).map(|b| ChaCha8Rng::seed_from_u64(100 + b)).collect()
            };
            let actions = Tensor::from_slice(&seq.action, (4, 10, 2), &Device::Cpu).unwrap();
            let loss = candle_loss(
                &model,
                (&nets, &heads),
                (&d, &actions),
                ctx.as_ref(),
                &mut streams(),
            );
            let want = loss.backward().unwrap();
            let mut metrics = Metrics::new();
            let (got, starts) = model
                .gradients(
                    &policy,
                    &seq,
                    (&ctx_rows, workers),
                    &mut streams(),
                    &mut metrics,
                )
                .unwrap();
            assert_eq!(starts.iter().map(|s| s.n).sum::<usize>(), 40);
            let l = loss.to_scalar::<f32>().unwrap() as f64;
            assert!(
                (metrics["model/loss"] - l).abs() < 1e-4 * (1.0 + l.abs()),
                "{mode:?}: loss {} vs {l}",
                metrics["model/loss"]
            );
            let learned = cfg.initial_state == InitialState::Learned;
            let names: Vec<String> = policy_store.named().into_iter().map(|(n, _)| n).collect();
            assert_eq!(names.contains(&"rssm.initial_state.w".into()), learned);
            let trained = &WorldModel::trained(&mut policy, &mut model.heads)[..];
            let tensors = trained.tensors();
            assert_eq!(got.len(), tensors.len());
            for (t, g) in tensors.iter().zip(&got) {
                let name = t.name;
                let store = match name.starts_with("encoder.") || name.starts_with("rssm.") {
                    true => &policy_store,
                    false => &heads_store,
                };
                let w = grad(&want, store, name).unwrap_or_else(|| panic!("{name}: no gradient"));
                assert_eq!(g.len(), w.len(), "{name}");
                let scale = w.iter().fold(0f32, |m, x| m.max(x.abs())).max(1e-6);
                for (i, (a, b)) in g.iter().zip(&w).enumerate() {
                    assert!(
                        (a - b).abs() <= 2e-3 * scale,
                        "{mode:?} {:?} {name}[{i}]: {a} vs {b}",
                        cfg.step_alignment
                    );
                }
            }
        }
    }

    /// The episode `o_0 −a_0→ o_1 (r_1) −a_1→ o_2 (r_2) −a_2→ o_3 (r_3, terminated)` as each form
    /// stores it (the actors' rows, [`ctxrace_config::agents::StepAlignment`]) and what the
    /// world model reads of it: ctxrace's four rows feed `0, a_0, a_1, a_2` to the sequence
    /// model and `symlog o_t` to the encoder, with the terminal flag on `o_3`; the paper code's
    /// three rows (`o_3` never stored) feed `0, a_1, a_2` (the row's own action, zeroed where
    /// the episode starts), `symlog [o_t, a_t]` to the encoder, `r_{t+1}` to the reward head and
    /// the terminal flag on `o_2`. Which action reached the sequence model is read from the
    /// loop's states: each equals a candle observation step fed the expected action.
    #[test]
    fn a_three_step_episode_reaches_the_world_model_as_each_form_stores_it() {
        let o = |k: usize| [k as f32 + 1.0, -(k as f32) - 1.0, 0.5 * k as f32];
        let a = |k: usize| [0.1 * (k as f32 + 1.0), -0.2 * (k as f32 + 1.0)];
        let r = |k: usize| 10.0 * k as f32;
        // rows (obs, action, reward, first, terminal)
        let ctxrace_rows = vec![
            (o(0), [0.0; 2], 0.0, 1.0, 0.0),
            (o(1), a(0), r(1), 0.0, 0.0),
            (o(2), a(1), r(2), 0.0, 0.0),
            (o(3), a(2), r(3), 0.0, 1.0),
        ];
        let code_rows = vec![
            (o(0), a(0), r(1), 1.0, 0.0),
            (o(1), a(1), r(2), 0.0, 0.0),
            (o(2), a(2), r(3), 0.0, 1.0),
        ];
        let base = DreamerConfig {
            units: 8,
            layers: 1,
            deter: 8,
            hidden: 8,
            stoch: 2,
            classes: 3,
            head_units: 8,
            head_layers: 1,
            ..DreamerConfig::default()
        };
        let cases = [
            (base.clone(), ctxrace_rows, vec![[0.0; 2], a(0), a(1), a(2)]),
            (
                base.with_paper_code_world_model(),
                code_rows,
                vec![[0.0; 2], a(1), a(2)],
            ),
        ];
        for (cfg, rows, into_gru) in cases {
            let t_len = rows.len();
            let seq = SequenceBatch {
                batch: 1,
                length: t_len,
                obs_dim: 3,
                act_dim: 2,
                obs: rows.iter().flat_map(|row| row.0).collect(),
                action: rows.iter().flat_map(|row| row.1).collect(),
                reward: rows.iter().map(|row| row.2).collect(),
                is_first: rows.iter().map(|row| row.3).collect(),
                is_terminal: rows.iter().map(|row| row.4).collect(),
                context: vec![0.0; t_len * 2],
                mask: vec![0.0; t_len * 2],
                has_mask: vec![0.0; t_len],
            };
            let alignment = cfg.step_alignment;
            let mut w = ShardWork::default();
            let mut rngs = vec![ChaCha8Rng::seed_from_u64(5)];
            let z = cfg.stoch * cfg.classes;
            w.load(&seq, &[], &(0..1), &mut rngs, (z, alignment));
            // the encoder's input and the heads' targets
            let symlogged = |v: &[f32]| v.iter().map(|&x| symlog(x)).collect::<Vec<f32>>();
            let want_input: Vec<f32> = rows
                .iter()
                .flat_map(|row| match alignment {
                    StepAlignment::Ctxrace => symlogged(&row.0),
                    StepAlignment::PaperCode => symlogged(&[&row.0[..], &row.1[..]].concat()),
                })
                .collect();
            assert_eq!(w.input, want_input, "{alignment:?}");
            assert_eq!(
                w.target, want_input,
                "{alignment:?}: one episode, nothing zeroed"
            );
            let rewards: Vec<f32> = rows.iter().map(|row| row.2).collect();
            assert_eq!(w.reward, rewards, "{alignment:?}");
            let mut cont = vec![1.0; t_len];
            cont[t_len - 1] = 0.0;
            assert_eq!(
                w.cont, cont,
                "{alignment:?}: the terminal flag on the last row"
            );
            // the loop: its states are candle steps fed the expected actions from zeros
            let policy = ParamStore::new();
            let nets = DreamerNets::new(&cfg, 3, 2, policy.builder()).unwrap();
            policy.init(6).unwrap();
            let dev = &Device::Cpu;
            let input = Tensor::from_slice(&w.input, (t_len, w.input.len() / t_len), dev).unwrap();
            let embed = nets.encoder.forward(&input).unwrap();
            let embed_rows: Vec<f32> = embed.flatten_all().unwrap().to_vec1().unwrap();
            let plain = Rssm::from_oracle(&nets.rssm).unwrap();
            let mut trace = ObserveTrace::default();
            let inputs = (&embed_rows[..], &w.action[..], &w.ctx[..], &w.keep[..]);
            plain.observe(1, inputs, &w.uniform, &mut trace);
            let (h, _, _) = trace.states();
            let mut state = nets.rssm.initial(1).unwrap();
            for (t, action) in into_gru.iter().enumerate() {
                let u = &w.uniform[t * z..(t + 1) * z];
                let u = Tensor::from_slice(u, (1, cfg.stoch, cfg.classes), dev).unwrap();
                let action = Tensor::from_slice(action, (1, 2), dev).unwrap();
                let e = embed.narrow(0, t, 1).unwrap();
                let (next, _) = nets.rssm.obs_step(&state, &action, None, &e, &u).unwrap();
                let want: Vec<f32> = next.deter.flatten_all().unwrap().to_vec1().unwrap();
                for (got, want) in h[t * cfg.deter..(t + 1) * cfg.deter].iter().zip(&want) {
                    assert!((got - want).abs() < 1e-5, "{alignment:?} step {t}");
                }
                state = next;
            }
        }
    }
}
