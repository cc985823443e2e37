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
//! The encoder and the RSSM live in the acting policy's store (the actors run them); the model
//! holds views of them that share their storage.

use crate::adam::Adam;
use crate::algorithm::{scalar, Metrics};
use crate::sequences::SeqData;
use crate::shards::{on_shards, weighted_mean};
use crate::time_rows::TimeRows;
use candle_core::backprop::GradStore;
use candle_core::{Module, Result, Tensor};
use ctxrace_common::agents::DreamerConfig;
use ctxrace_common::nn::{symlog, Activation, Mlp, ParamStore, Rssm, RssmState, TwoHot};
use ctxrace_common::policy::{uniforms_per, DreamerNets};
use rand_chacha::ChaCha8Rng;

/// DreamerV3's KL balancing with free nats, per batch element, from posterior and prior logits
/// `[N, S, C]`: `(max(free, KL(sg q ‖ p)), max(free, KL(q ‖ sg p)), KL(q ‖ p))`, the last detached.
/// Below the free nats a term is constant and passes no gradient.
pub(crate) fn kl_balance(
    rssm: &Rssm,
    post: &Tensor,
    prior: &Tensor,
    free: f64,
) -> Result<(Tensor, Tensor, Tensor)> {
    let dyn_kl = rssm.kl(&post.detach(), prior)?;
    let rep_kl = rssm.kl(post, &prior.detach())?;
    Ok((
        dyn_kl.maximum(free)?,
        rep_kl.maximum(free)?,
        dyn_kl.detach(),
    ))
}

/// Binary cross-entropy of logits `l` against targets `y`: `max(l, 0) − y l + ln(1 + e^{−|l|})`.
fn bce_with_logits(logits: &Tensor, target: &Tensor) -> Result<Tensor> {
    let softplus_tail = (logits.abs()?.neg()?.exp()? + 1.0)?.log()?;
    (logits.relu()? - logits.mul(target)?)? + softplus_tail
}

/// Posterior states to imagine from, `N = B·T` of them, detached.
pub(crate) struct Starts {
    /// Deterministic and stochastic parts, `[N, …]`.
    pub(crate) state: RssmState,
    /// `[N]` `1 − terminal`.
    pub(crate) cont: Tensor,
    /// `[N, 2]` the model context, if any.
    pub(crate) ctx: Option<Tensor>,
}

/// A shard's world-model loss ([`WorldModel::loss`]) with what its gradients need.
pub(crate) struct ModelLoss {
    loss: Tensor,
    metrics: Metrics,
    starts: Starts,
    /// The observation embeddings as the sequence loop read them.
    embed: TimeRows,
}

impl ModelLoss {
    /// The gradients of `weight` times the loss in every parameter: the backward pass, the
    /// taped weight gradients of `rssm` (the loop's [`Rssm::taped`] model), and the encoder's
    /// from the embeddings' gradients.
    fn gradients(&self, rssm: &Rssm, weight: f64) -> Result<GradStore> {
        let mut grads = (&self.loss * weight)?.backward()?;
        rssm.flush_grads(&mut grads)?;
        self.embed.backprop(&mut grads)?;
        Ok(grads)
    }
}

/// Encoder, RSSM, decoder, reward and continue heads, and the optimiser that trains them.
pub(crate) struct WorldModel {
    /// `enc(symlog o)` (a view of the policy's).
    encoder: Mlp,
    /// The sequence model (a view of the policy's).
    rssm: Rssm,
    decoder: Mlp,
    pub(crate) reward: Mlp,
    pub(crate) cont: Mlp,
    twohot: TwoHot,
    /// The heads' parameters: `decoder`, `reward`, `cont`.
    pub(crate) heads: ParamStore,
    /// Adam over the encoder, the RSSM and the heads.
    pub(crate) opt: Adam,
    cfg: DreamerConfig,
}

impl WorldModel {
    /// Heads for observations of `obs_dim` on the encoder and RSSM of `nets` (in the store
    /// `policy`), initialised from `cfg.seed + 1`, the reward head's output layer at zero.
    pub(crate) fn new(
        cfg: &DreamerConfig,
        obs_dim: usize,
        nets: &DreamerNets,
        policy: &ParamStore,
    ) -> Result<Self> {
        let silu = Activation::SiluNorm;
        let feat = nets.rssm.feat_dim() + cfg.context.context_dim();
        let heads = ParamStore::new();
        let hb = heads.builder();
        let (hu, hl) = (cfg.head_units, cfg.head_layers);
        let decoder = Mlp::new(
            feat,
            cfg.units,
            cfg.layers,
            Some(obs_dim),
            silu,
            hb.pp("decoder"),
        )?
        .sparse_inputs(nets.rssm.stoch_columns());
        let reward = Mlp::new(feat, hu, hl, Some(cfg.bins), silu, hb.pp("reward"))?
            .sparse_inputs(nets.rssm.stoch_columns());
        let cont = Mlp::new(feat, hu, hl, Some(1), silu, hb.pp("cont"))?
            .sparse_inputs(nets.rssm.stoch_columns());
        heads.init(cfg.seed.wrapping_add(1))?;
        for (n, v) in heads.named() {
            if n == "reward.out.weight" {
                v.set(&v.zeros_like()?)?;
            }
        }
        let mut vars = policy.vars_under(&["encoder", "rssm"]);
        vars.extend(heads.vars());
        Ok(Self {
            encoder: nets.encoder.clone(),
            rssm: nets.rssm.clone(),
            decoder,
            reward,
            cont,
            twohot: TwoHot::new(cfg.bins, -20.0, 20.0)?,
            heads,
            opt: Adam::new(vars, cfg.model_lr, cfg.model_eps, cfg.model_clip),
            cfg: cfg.clone(),
        })
    }

    /// The loss of a shard of sequences `d` (model context `ctx` `[B·T, 2]`, Gumbel noise from the
    /// sequences' streams `rngs`), its metrics and the posterior states to imagine from.
    /// `rssm` is this model's RSSM as [`Rssm::taped`] for the sequence loop; its tapes must be
    /// flushed into the gradients of the loss, and the embeddings' gradients sent on into the
    /// encoder ([`ModelLoss::gradients`]).
    pub(crate) fn loss(
        &self,
        rssm: &Rssm,
        d: &SeqData,
        ctx: Option<&Tensor>,
        rngs: &mut [ChaCha8Rng],
    ) -> Result<ModelLoss> {
        let (b, t_len, n) = (d.batch, d.length, d.batch * d.length);
        let (s, c) = (self.cfg.stoch, self.cfg.classes);
        let target = symlog(&d.flat(&d.obs)?)?;
        // time-major, so that `get(t)` gives contiguous `[B, …]` slices
        let time_major = |x: &Tensor| x.transpose(0, 1)?.contiguous();
        // the loop reads one step at a time: as leaves, not `get(t)` views (see `TimeRows`)
        let embed = TimeRows::new(&time_major(&self.encoder.forward(&target)?.reshape((
            b,
            t_len,
            (),
        ))?)?)?;
        let actions = time_major(&d.action)?;
        let keeps = time_major(&(1.0 - &d.first)?)?;
        let ctx_tm = ctx
            .map(|c| time_major(&c.reshape((b, t_len, ()))?))
            .transpose()?;

        let mut state = rssm.initial(b)?;
        let (mut deters, mut stochs) = (Vec::with_capacity(t_len), Vec::with_capacity(t_len));
        let mut posts = Vec::with_capacity(t_len);
        for t in 0..t_len {
            let keep = keeps.get(t)?.unsqueeze(1)?;
            let prev = RssmState {
                deter: state.deter.broadcast_mul(&keep)?,
                stoch: state.stoch.broadcast_mul(&keep)?,
            };
            let action = actions.get(t)?.broadcast_mul(&keep)?;
            let c_t = ctx_tm.as_ref().map(|c| c.get(t)).transpose()?;
            let (next, post) = rssm.obs_step(
                &prev,
                &action,
                c_t.as_ref(),
                embed.get(t),
                &uniforms_per(rngs, 1, (s, c))?,
            )?;
            deters.push(next.deter.clone());
            stochs.push(next.stoch.clone());
            posts.push(post);
            state = next;
        }
        let batch_major = |xs: &[Tensor]| Tensor::stack(xs, 1)?.reshape((n, ()));
        let deter = batch_major(&deters)?;
        let stoch = batch_major(&stochs)?;
        let prior = rssm.prior_logits(&deter)?;
        let post = batch_major(&posts)?.reshape((n, s, c))?;

        let posterior = RssmState { deter, stoch };
        let x = posterior.head_input(ctx)?;
        let recon = (self.decoder.forward(&x)? - &target)?.sqr()?.sum(1)?;
        let reward = self
            .twohot
            .loss(&self.reward.forward(&x)?, &d.reward.flatten_all()?)?;
        let cont_target = (1.0 - d.terminal.flatten_all()?)?;
        let cont = bce_with_logits(&self.cont.forward(&x)?.squeeze(1)?, &cont_target)?;
        let (dyn_loss, rep_loss, kl) = kl_balance(rssm, &post, &prior, self.cfg.free_nats)?;
        let pred = ((&recon + &reward)? + &cont)?;
        let loss = (((pred * self.cfg.pred_scale)? + (&dyn_loss * self.cfg.kl_dyn)?)?
            + (&rep_loss * self.cfg.kl_rep)?)?
            .mean_all()?;

        let mut metrics = Metrics::new();
        for (name, v) in [
            ("model/loss", &loss),
            ("model/recon", &recon.mean_all()?),
            ("model/reward", &reward.mean_all()?),
            ("model/cont", &cont.mean_all()?),
            ("model/kl", &kl.mean_all()?),
        ] {
            metrics.insert(name.into(), scalar(v)?);
        }
        let starts = Starts {
            state: posterior.detach(),
            cont: cont_target,
            ctx: ctx.map(|c| c.detach()),
        };
        Ok(ModelLoss {
            loss,
            metrics,
            starts,
            embed,
        })
    }

    /// One step of the world model on the batch `d`, its shards' losses and gradients computed by
    /// `workers` threads in parallel; returns each shard's posterior states to imagine from.
    pub(crate) fn step(
        &mut self,
        d: &SeqData,
        ctx: Option<&Tensor>,
        workers: usize,
        rngs: &mut [ChaCha8Rng],
        metrics: &mut Metrics,
    ) -> Result<Vec<Starts>> {
        let parts = on_shards(workers, d.batch, rngs, |shard, rngs| {
            let ds = d.sequences(&shard.rows)?;
            let cs = ctx.map(|c| d.rows_of(c, &shard.rows)).transpose()?;
            // the weights transposed once for the 64 steps, their gradients one product each
            let rssm = self.rssm.taped()?;
            let shard_loss = self.loss(&rssm, &ds, cs.as_ref(), rngs)?;
            let grads = shard_loss.gradients(&rssm, shard.weight)?;
            Ok((shard.weight, shard_loss.metrics, grads, shard_loss.starts))
        })?;
        let mut grads = Vec::with_capacity(parts.len());
        let mut starts = Vec::with_capacity(parts.len());
        let mut shard_metrics = Vec::with_capacity(parts.len());
        for (w, m, g, s) in parts {
            shard_metrics.push((w, m));
            grads.push(g);
            starts.push(s);
        }
        metrics.extend(weighted_mean(&shard_metrics));
        metrics.insert("model/grad_norm".into(), self.opt.step_sum(&grads)?);
        Ok(starts)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};
    use ctxrace_common::nn::RssmConfig;

    fn grad_norm(grads: &candle_core::backprop::GradStore, v: &Var) -> f64 {
        grads
            .get(v.as_tensor())
            .map(|g| scalar(&g.sqr().unwrap().sum_all().unwrap()).unwrap().sqrt())
            .unwrap_or(0.0)
    }

    #[test]
    fn kl_free_nats_below_and_above_the_threshold() {
        let cfg = RssmConfig {
            deter: 4,
            hidden: 4,
            stoch: 1,
            classes: 2,
            unimix: 0.0,
            act_dim: 1,
            embed_dim: 1,
            context_dim: 0,
        };
        let (_, rssm) = ctxrace_common::nn::rssm::standalone(cfg, 0).unwrap();
        // q = (1/2, 1/2), p = (3/4, 1/4): KL(q ‖ p) = ½ ln(2/3) + ½ ln 2 = ½ ln(4/3)
        let want = 0.5 * (4f64 / 3.0).ln();
        let post = Var::new(&[[[0f32, 0.0]]], &Device::Cpu).unwrap();
        let prior = Var::new(&[[[3f32.ln(), 0.0]]], &Device::Cpu).unwrap();
        for (free, expect_grad) in [(1.0, false), (0.1, true)] {
            let (dyn_kl, rep_kl, kl) =
                kl_balance(&rssm, post.as_tensor(), prior.as_tensor(), free).unwrap();
            assert!((scalar(&kl.sum_all().unwrap()).unwrap() - want).abs() < 1e-6);
            let v = scalar(&dyn_kl.sum_all().unwrap()).unwrap();
            assert!((v - want.max(free)).abs() < 1e-6, "free {free}: {v}");
            assert!((scalar(&rep_kl.sum_all().unwrap()).unwrap() - v).abs() < 1e-6);
            // dyn trains only the prior, rep only the posterior; below the free nats neither
            let g = dyn_kl.sum_all().unwrap().backward().unwrap();
            assert_eq!(grad_norm(&g, &prior) > 1e-4, expect_grad, "free {free}");
            assert_eq!(grad_norm(&g, &post), 0.0);
            let g = rep_kl.sum_all().unwrap().backward().unwrap();
            assert_eq!(grad_norm(&g, &post) > 1e-4, expect_grad, "free {free}");
            assert_eq!(grad_norm(&g, &prior), 0.0);
        }
    }
}
