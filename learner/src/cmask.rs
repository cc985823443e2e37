//! cMask's mask SAC (the paper's contribution): a soft actor-critic whose action is the context
//! mask `m_t ∈ [0, 1]²` and whose observation is the LiDAR frame `o_t`, trained on the extrinsic
//! reward, one SAC step per world-model step on the same sequence batch.
//!
//! **Transitions.** Row `t + 1` of a sequence stores the action and the mask chosen at `o_t`, and
//! the reward earned by them: the SAC transitions are `(o_t, m_t, r_{t+1}, o_{t+1},
//! terminal_{t+1})` for `t < T − 1`, with `m_t` the mask that acted (as the paper's code stores
//! it). A mask drawn afresh from `π(· | o_t)` carries no information about `r_{t+1}`: a critic
//! fitted on it is flat in `m`, and the mask actor would learn from its entropy alone.
//! Transitions into a new episode, and those whose action no mask chose (random prefill), are
//! dropped (`valid = 0`).
//!
//! **Losses** (means over the valid transitions), with the twin critics and Polyak targets of
//! [`crate::sac`]: critics `Σ_i (Q_i(o, m) − y)²`, `y = r + γ (1 − d) (min_i Q̄_i(o', m') − α log
//! π(m' | o'))`, `m' ~ π(· | o')`; actor `α log π(m̃ | o) − min_i Q_i(o, m̃)` with a fresh
//! `m̃ ~ π(· | o)`; temperature `−log α · (log π + H̄)`. Each worker's shard of sequences sums its
//! part of a mean (divided by the batch's count of valid transitions) and differentiates it in
//! parallel ([`crate::shards`]).

use crate::adam::Adam;
use crate::algorithm::{scalar, Metrics};
use crate::sac::{polyak, TwinQ};
use crate::sequences::SeqData;
use crate::shards::{on_shards, Shard};
use candle_core::{bail, Result, Tensor};
use candle_nn::Init;
use ctxrace_common::agents::{DreamerConfig, MaskConfig, CONTEXT_DIM};
use ctxrace_common::nn::{ParamStore, TanhGaussianActor};
use ctxrace_common::policy::{mask_sample, normals_per};
use rand_chacha::ChaCha8Rng;

/// The mask SAC's transitions `(o_t, m_t, r_{t+1}, o_{t+1}, terminal_{t+1})` for `t < T − 1`,
/// each `[B·(T−1), …]`, `m_t` the stored mask that acted at `o_t`, with `valid = 0` where
/// `o_{t+1}` starts a new episode or no mask chose the action at `o_t`.
pub(crate) struct Transitions {
    obs: Tensor,
    mask: Tensor,
    reward: Tensor,
    next_obs: Tensor,
    terminal: Tensor,
    valid: Tensor,
}

impl Transitions {
    /// From a batch (row `t + 1` stores the action and mask chosen at `o_t`); `None` for
    /// sequences of one step.
    fn new(d: &SeqData) -> Result<Option<Self>> {
        let (b, t) = (d.batch, d.length);
        if t < 2 {
            return Ok(None);
        }
        let n = b * (t - 1);
        let span = |x: &Tensor, start: usize| x.narrow(1, start, t - 1)?.reshape((n, ()));
        Ok(Some(Self {
            obs: span(&d.obs, 0)?,
            mask: span(&d.mask, 1)?,
            reward: span(&d.reward, 1)?.flatten_all()?,
            next_obs: span(&d.obs, 1)?,
            terminal: span(&d.terminal, 1)?.flatten_all()?,
            valid: Self::valid(d, 0..b)?,
        }))
    }

    /// `[|rows|·(T−1)]`: 1 where row `t + 1` of the sequences `rows` continues the episode and
    /// its action was chosen through a mask.
    fn valid(d: &SeqData, rows: std::ops::Range<usize>) -> Result<Tensor> {
        let next = |x: &Tensor| {
            x.narrow(0, rows.start, rows.len())?
                .narrow(1, 1, d.length - 1)
        };
        (1.0 - next(&d.first)?)?
            .mul(&next(&d.has_mask)?)?
            .flatten_all()
    }
}

/// cMask's mask SAC (the actor lives in the policy store under `mask`).
pub(crate) struct MaskSac {
    pub(crate) critic_store: ParamStore,
    pub(crate) target_store: ParamStore,
    pub(crate) alpha_store: ParamStore,
    pub(crate) q: TwinQ,
    q_target: TwinQ,
    log_alpha: Tensor,
    pub(crate) actor_opt: Adam,
    pub(crate) critic_opt: Adam,
    pub(crate) alpha_opt: Adam,
    cfg: MaskConfig,
}

impl MaskSac {
    pub(crate) fn new(cfg: &DreamerConfig, obs_dim: usize, policy: &ParamStore) -> Result<Self> {
        let m = &cfg.mask;
        let critic_store = ParamStore::new();
        let q = TwinQ::new(
            obs_dim + CONTEXT_DIM,
            m.units,
            m.layers,
            critic_store.builder(),
        )?;
        let target_store = ParamStore::new();
        let q_target = TwinQ::new(
            obs_dim + CONTEXT_DIM,
            m.units,
            m.layers,
            target_store.builder(),
        )?;
        critic_store.init(cfg.seed.wrapping_add(3))?;
        target_store.load_bytes(&critic_store.to_bytes()?)?;
        if m.init_alpha.is_nan() || m.init_alpha <= 0.0 {
            bail!("mask.init_alpha must be positive");
        }
        let alpha_store = ParamStore::new();
        let log_alpha =
            alpha_store
                .builder()
                .get_with_hints(1, "log_alpha", Init::Const(m.init_alpha.ln()))?;
        let no_clip = f64::INFINITY;
        Ok(Self {
            actor_opt: Adam::new(policy.vars_under(&["mask"]), m.lr, 1e-8, no_clip),
            critic_opt: Adam::new(critic_store.vars(), m.lr, 1e-8, no_clip),
            alpha_opt: Adam::new(alpha_store.vars(), m.lr, 1e-8, no_clip),
            critic_store,
            target_store,
            alpha_store,
            q,
            q_target,
            log_alpha,
            cfg: m.clone(),
        })
    }

    /// One SAC step (critics, actor, temperature, targets) on the transitions of the batch `d`
    /// and the masks stored with them. The critic and actor losses are means over the valid
    /// transitions; each of the `workers` shards of sequences sums its part (divided by the
    /// batch's count) and differentiates it in parallel, and the gradients are summed. A batch
    /// without valid transitions (all random prefill) takes no step.
    pub(crate) fn step(
        &mut self,
        actor: &TanhGaussianActor,
        d: &SeqData,
        workers: usize,
        rngs: &mut [ChaCha8Rng],
        metrics: &mut Metrics,
    ) -> Result<()> {
        if d.length < 2 {
            return Ok(());
        }
        let per_sequence = d.length - 1;
        let valid_count = scalar(&Transitions::valid(d, 0..d.batch)?.sum_all()?)?;
        let alpha = self.log_alpha.exp()?.detach();
        metrics.insert("mask/acted_transitions".into(), valid_count);
        metrics.insert("mask/alpha".into(), scalar(&alpha.sum_all()?)?);
        if valid_count == 0.0 {
            // the losses over no transitions are zero; nothing is stepped
            for key in ["mask/q_loss", "mask/actor_loss", "mask/entropy"] {
                metrics.insert(key.into(), 0.0);
            }
            return Ok(());
        }
        let count = valid_count;
        let shard_transitions = |shard: &Shard| -> Result<Transitions> {
            Transitions::new(&d.sequences(&shard.rows)?)?
                .ok_or_else(|| candle_core::Error::Msg("no transitions".into()))
        };
        // the part of a batch mean that a shard's transitions contribute
        let part = |x: &Tensor, tr: &Transitions| -> Result<Tensor> {
            x.mul(&tr.valid)?.sum_all()? / count
        };

        let this = &*self;
        let critic_parts = on_shards(workers, d.batch, rngs, |shard, rngs| {
            let tr = shard_transitions(&shard)?;
            let noise = normals_per(rngs, per_sequence, CONTEXT_DIM)?;
            let (next_m, next_logp) = mask_sample(actor, &tr.next_obs, &noise)?;
            let soft_next =
                (this.q_target.min(&tr.next_obs, &next_m)? - next_logp.broadcast_mul(&alpha)?)?;
            let keep = ((1.0 - &tr.terminal)? * this.cfg.gamma)?;
            let target = (&tr.reward + keep.mul(&soft_next)?)?.detach();
            let (q1, q2) = this.q.forward(&tr.obs, &tr.mask)?;
            let q_loss = part(&((q1 - &target)?.sqr()? + (q2 - &target)?.sqr()?)?, &tr)?;
            Ok((scalar(&q_loss)?, q_loss.backward()?))
        })?;
        let (q_losses, grads): (Vec<f64>, Vec<_>) = critic_parts.into_iter().unzip();
        self.critic_opt.step_sum(&grads)?;

        let this = &*self;
        let actor_parts = on_shards(workers, d.batch, rngs, |shard, rngs| {
            let tr = shard_transitions(&shard)?;
            let noise = normals_per(rngs, per_sequence, CONTEXT_DIM)?;
            let (m, logp) = mask_sample(actor, &tr.obs, &noise)?;
            let q = this.q.min(&tr.obs, &m)?;
            let actor_loss = part(&(logp.broadcast_mul(&alpha)? - q)?, &tr)?;
            let logp_part = scalar(&part(&logp.detach(), &tr)?)?;
            Ok((scalar(&actor_loss)?, logp_part, actor_loss.backward()?))
        })?;
        let mut grads = Vec::with_capacity(actor_parts.len());
        let (mut actor_loss, mut mean_logp) = (0.0, 0.0);
        for (loss, logp, g) in actor_parts {
            actor_loss += loss;
            mean_logp += logp;
            grads.push(g);
        }
        self.actor_opt.step_sum(&grads)?;

        // temperature: minimise −log α · mean(log π + target entropy) over the valid transitions
        let gap = mean_logp + self.cfg.target_entropy;
        let alpha_loss = (self.log_alpha.sum_all()? * -gap)?;
        self.alpha_opt.minimise(&alpha_loss)?;
        polyak(&self.target_store, &self.critic_store, self.cfg.tau)?;

        metrics.insert("mask/q_loss".into(), q_losses.iter().sum());
        metrics.insert("mask/actor_loss".into(), actor_loss);
        metrics.insert("mask/entropy".into(), -mean_logp);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_common::SequenceBatch;

    #[test]
    fn sac_transitions_take_the_reward_and_mask_of_their_own_step() {
        let seq = SequenceBatch {
            batch: 1,
            length: 4,
            obs_dim: 1,
            act_dim: 1,
            obs: vec![0.0, 1.0, 2.0, 3.0],
            action: vec![0.0; 4],
            reward: vec![0.0, 10.0, 20.0, 30.0],
            is_first: vec![1.0, 0.0, 1.0, 0.0],
            is_terminal: vec![0.0, 1.0, 0.0, 0.0],
            context: vec![0.0; 8],
            // row t + 1 holds the mask that acted at o_t; the action into o_3 had none
            mask: vec![0.0, 0.0, 0.3, 0.4, 0.0, 0.0, 0.7, 0.8],
            has_mask: vec![0.0, 1.0, 0.0, 0.0],
        };
        let d = SeqData::new(&seq, 1, 1).unwrap();
        let tr = Transitions::new(&d).unwrap().unwrap();
        let v = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(v(&tr.obs), [0.0, 1.0, 2.0]);
        assert_eq!(v(&tr.mask), [0.3, 0.4, 0.0, 0.0, 0.7, 0.8]);
        assert_eq!(v(&tr.reward), [10.0, 20.0, 30.0]);
        assert_eq!(v(&tr.next_obs), [1.0, 2.0, 3.0]);
        assert_eq!(v(&tr.terminal), [1.0, 0.0, 0.0]);
        // o_2 starts a new episode; no mask chose the action into o_3
        assert_eq!(v(&tr.valid), [1.0, 0.0, 0.0]);
    }
}
