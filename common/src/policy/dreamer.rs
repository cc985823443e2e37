//! DreamerV3's acting networks (encoder, RSSM, actor and cMask's mask actor) and the batch-1
//! policy that runs them in the actors: at each step the observation updates the posterior
//! state, the actor reads `[h, z, c]` and (cMask) the mask actor masks the context first.
//! The learner trains the same [`DreamerNets`] and ships their "policy" parameter store.

use super::ACT_DIM;
use crate::agents::{
    ContextMode, DreamerConfig, InitialState, MaskSpace, StepAlignment, CONTEXT_DIM,
};
use crate::nn::{
    symlog, Activation, Mlp, ParamStore, Rssm, RssmConfig, RssmState, TanhGaussianActor,
};
use candle_core::{bail, DType, Device, Module, Result, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// The networks that act: encoder, RSSM, actor and (cMask) mask actor.
#[derive(Clone, Debug)]
pub struct DreamerNets {
    /// Observation encoder (on `symlog o`, or on `symlog [o, a]` with
    /// [`StepAlignment::PaperCode`]).
    pub encoder: Mlp,
    /// The encoder reads the action beside the observation ([`StepAlignment::PaperCode`]).
    pub action_in_encoder: bool,
    /// The recurrent state-space model.
    pub rssm: Rssm,
    /// Actor head on `[h, z, c]`: means and raw standard deviations.
    pub actor: Mlp,
    /// cMask's mask actor on the observation.
    pub mask: Option<TanhGaussianActor>,
    /// How the mask actor's samples become masks ([`MaskSpace`]).
    pub mask_space: MaskSpace,
    /// Action size.
    pub act_dim: usize,
    /// Smallest actor standard deviation.
    pub min_std: f64,
    /// Largest actor standard deviation.
    pub max_std: f64,
    /// Raw contexts are divided by it ([`DreamerConfig::context_divisor`]): the training
    /// context range, or 1 for the raw context.
    pub context_divisor: f64,
}

impl DreamerNets {
    /// The networks of `cfg` for observations of `obs_dim` and actions of `act_dim`, built under `vb`.
    pub fn new(
        cfg: &DreamerConfig,
        obs_dim: usize,
        act_dim: usize,
        vb: candle_nn::VarBuilder,
    ) -> Result<Self> {
        let silu = Activation::SiluNorm;
        let context_dim = cfg.context.context_dim();
        let enc_in = cfg.encoder_inputs(obs_dim, act_dim);
        let encoder = Mlp::new(enc_in, cfg.units, cfg.layers, None, silu, vb.pp("encoder"))?;
        let rssm_cfg = RssmConfig {
            deter: cfg.deter,
            hidden: cfg.hidden,
            stoch: cfg.stoch,
            classes: cfg.classes,
            unimix: cfg.unimix,
            act_dim,
            embed_dim: if cfg.layers == 0 { enc_in } else { cfg.units },
            context_dim,
            learned_initial: cfg.initial_state == InitialState::Learned,
        };
        let rssm = Rssm::new(rssm_cfg, vb.pp("rssm"))?;
        let actor = Mlp::new(
            rssm.feat_dim() + context_dim,
            cfg.head_units,
            cfg.head_layers,
            Some(2 * act_dim),
            silu,
            vb.pp("actor"),
        )?
        .sparse_inputs(rssm.stoch_columns());
        let mask = match cfg.context {
            ContextMode::Cmask => Some(
                TanhGaussianActor::new(
                    obs_dim,
                    CONTEXT_DIM,
                    cfg.mask.units,
                    cfg.mask.layers,
                    vb.pp("mask"),
                )?
                .with_log_std_clamp(cfg.mask.log_std_clamp),
            ),
            ContextMode::None | ContextMode::Crssm => None,
        };
        Ok(Self {
            encoder,
            action_in_encoder: cfg.step_alignment == StepAlignment::PaperCode,
            rssm,
            actor,
            mask,
            mask_space: cfg.mask.mask_space,
            act_dim,
            min_std: cfg.min_std,
            max_std: cfg.max_std,
            context_divisor: cfg.context_divisor(),
        })
    }

    /// The same networks on detached (shared) parameters: what they compute tracks no graph.
    pub fn frozen(&self) -> Self {
        Self {
            encoder: self.encoder.frozen(),
            rssm: self.rssm.frozen(),
            actor: self.actor.frozen(),
            mask: self.mask.as_ref().map(TanhGaussianActor::frozen),
            ..self.clone()
        }
    }

    /// The same networks for loops that apply them many times (acting step after step, the
    /// imagination's horizon): every weight transposed once ([`crate::nn::Dense::looped`]).
    pub fn looped(&self) -> Result<Self> {
        Ok(Self {
            encoder: self.encoder.looped()?,
            rssm: self.rssm.looped()?,
            actor: self.actor.looped()?,
            mask: self
                .mask
                .as_ref()
                .map(TanhGaussianActor::looped)
                .transpose()?,
            ..self.clone()
        })
    }

    /// The model's context input `[N, 2]` for raw contexts and (cMask) masks, or `None`.
    pub fn context(&self, raw: &Tensor, mask: Option<&Tensor>) -> Result<Option<Tensor>> {
        if self.rssm.config().context_dim == 0 {
            return Ok(None);
        }
        let c = (raw / self.context_divisor)?;
        Ok(Some(match mask {
            Some(m) => c.mul(m)?,
            None => c,
        }))
    }

    /// The actor's mean `tanh μ` and standard deviation, each `[N, A]`.
    pub fn actor_dist(&self, x: &Tensor) -> Result<(Tensor, Tensor)> {
        self.actor_dist_of(&self.actor, x)
    }

    /// [`DreamerNets::actor_dist`] through `actor`, a view of this actor (e.g. [`Mlp::looped`]).
    pub fn actor_dist_of(&self, actor: &Mlp, x: &Tensor) -> Result<(Tensor, Tensor)> {
        let out = actor.forward(x)?;
        let mean = out.narrow(1, 0, self.act_dim)?.tanh()?;
        let raw = (out.narrow(1, self.act_dim, self.act_dim)? + 2.0)?;
        let std =
            candle_nn::ops::sigmoid(&raw)?.affine(self.max_std - self.min_std, self.min_std)?;
        Ok((mean, std))
    }

    /// A reparameterised action `[N, A]` from the distribution and standard-normal noise, scaled
    /// into `[−1, 1]` with a stop-gradient factor.
    pub fn sample_action(mean: &Tensor, std: &Tensor, noise: &Tensor) -> Result<Tensor> {
        let a = (mean + std.mul(noise)?)?;
        let shrink = a.abs()?.maximum(1.0)?.recip()?.detach();
        a.mul(&shrink)
    }

    /// One observation step at batch `N` (acting): the sequence model reads the previous action,
    /// the encoder `symlog o` (`symlog [o, a_{t−1}]` with [`StepAlignment::PaperCode`], as the
    /// paper's code acts); the next state and the action (sampled with `noise`, else the mean).
    pub fn observe(
        &self,
        state: &RssmState,
        prev_action: &Tensor,
        obs: &Tensor,
        ctx: Option<&Tensor>,
        uniform: &Tensor,
        noise: Option<&Tensor>,
    ) -> Result<(RssmState, Tensor)> {
        let input = match self.action_in_encoder {
            true => Tensor::cat(&[obs, prev_action], 1)?,
            false => obs.clone(),
        };
        let embed = self.encoder.forward(&symlog(&input)?)?;
        let (next, _) = self
            .rssm
            .obs_step(state, prev_action, ctx, &embed, uniform)?;
        let (mean, std) = self.actor_dist(&next.head_input(ctx)?)?;
        let action = match noise {
            Some(n) => Self::sample_action(&mean, &std, n)?,
            None => mean,
        };
        Ok((next, action))
    }
}

/// The mask of the mask actor's squashed value `a = tanh u` in `space`: `(a + 1) / 2` (unit),
/// `sigmoid(a)` (the paper's code).
pub fn mask_of(a: &Tensor, space: MaskSpace) -> Result<Tensor> {
    match space {
        MaskSpace::Unit => a.affine(0.5, 0.5),
        MaskSpace::PaperCode => candle_nn::ops::sigmoid(a),
    }
}

/// A mask sample from the tanh-Gaussian mask actor and `log π` in `space`: unit,
/// `m = (a + 1) / 2` and its density `log π(m) = log π(a) + |m| ln 2`; the paper's code,
/// `m = sigmoid(a)` and the density of `a` itself (where the code takes its entropy).
pub fn mask_sample(
    actor: &TanhGaussianActor,
    obs: &Tensor,
    noise: &Tensor,
    space: MaskSpace,
) -> Result<(Tensor, Tensor)> {
    let (a, log_prob) = actor.sample(obs, noise)?;
    let log_prob = match space {
        MaskSpace::Unit => (log_prob + CONTEXT_DIM as f64 * std::f64::consts::LN_2)?,
        MaskSpace::PaperCode => log_prob,
    };
    Ok((mask_of(&a, space)?, log_prob))
}

/// Gumbel-max uniforms in `(0, 1)`.
pub fn uniforms(rng: &mut ChaCha8Rng, shape: (usize, usize, usize)) -> Result<Tensor> {
    uniforms_per(std::slice::from_mut(rng), shape.0, (shape.1, shape.2))
}

/// Standard-normal noise.
pub fn normals(rng: &mut ChaCha8Rng, shape: (usize, usize)) -> Result<Tensor> {
    normals_per(std::slice::from_mut(rng), shape.0, shape.1)
}

/// `[R·rows, width]` values where rows `r·rows … (r+1)·rows − 1` come from stream `r` of `rngs`
/// (so that, say, each sequence of a batch draws its own noise however the batch is split).
fn rows_per_stream(
    rngs: &mut [ChaCha8Rng],
    rows: usize,
    width: usize,
    draw: impl Fn(&mut ChaCha8Rng) -> f32,
) -> Vec<f32> {
    let mut v = Vec::with_capacity(rngs.len() * rows * width);
    for rng in rngs {
        v.extend((0..rows * width).map(|_| draw(rng)));
    }
    v
}

/// Gumbel-max uniforms in `(0, 1)`, `[R·rows, width]` values, `rows` of them from each stream
/// of `rngs`.
///
/// The values of `random_range(1e-6..1 − 1e-6)` one after another, made from a block of each
/// stream's words at once (the same words, in the same order): rand's uniform `f32` in
/// `[low, high)` is a word's top 23 bits as the mantissa of a float in `[1, 2)`, less 1, times
/// `high − low`, plus `low`; a loop over a block of words vectorises, one call a value did not.
pub fn uniform_rows(rngs: &mut [ChaCha8Rng], rows: usize, width: usize) -> Vec<f32> {
    const LOW: f32 = 1e-6;
    const HIGH: f32 = 1.0 - 1e-6;
    let n = rows * width;
    if n == 0 {
        return Vec::new();
    }
    let mut words = vec![0u32; rngs.len() * n];
    for (rng, block) in rngs.iter_mut().zip(words.chunks_mut(n)) {
        rng.fill(block);
    }
    let scale = HIGH - LOW;
    let unit = |w: u32| f32::from_bits(w >> 9 | 0x3f80_0000) - 1.0;
    words.iter().map(|&w| unit(w) * scale + LOW).collect()
}

/// Standard-normal noise, `[R·rows, width]` values, `rows` of them from each stream of `rngs`.
pub fn normal_rows(rngs: &mut [ChaCha8Rng], rows: usize, width: usize) -> Vec<f32> {
    rows_per_stream(rngs, rows, width, |r| r.sample(StandardNormal))
}

/// Gumbel-max uniforms `[R·rows, S, C]`, `rows` of them from each stream of `rngs`.
pub fn uniforms_per(
    rngs: &mut [ChaCha8Rng],
    rows: usize,
    (stoch, classes): (usize, usize),
) -> Result<Tensor> {
    let n = rngs.len() * rows;
    let v = uniform_rows(rngs, rows, stoch * classes);
    Tensor::from_vec(v, (n, stoch, classes), &Device::Cpu)
}

/// Standard-normal noise `[R·rows, width]`, `rows` of them from each stream of `rngs`.
pub fn normals_per(rngs: &mut [ChaCha8Rng], rows: usize, width: usize) -> Result<Tensor> {
    let n = rngs.len() * rows;
    Tensor::from_vec(normal_rows(rngs, rows, width), (n, width), &Device::Cpu)
}
/// The acting side of DreamerV3 at batch 1: keeps the recurrent state and the previous action.
pub struct DreamerPolicy {
    store: ParamStore,
    /// The networks on `store`'s weights.
    stored: DreamerNets,
    /// `stored` [`DreamerNets::frozen`] (acting records no graph, so an episode's earlier steps
    /// are not kept alive) and [`DreamerNets::looped`] for acting step after step (re-made on
    /// every load).
    nets: DreamerNets,
    obs_dim: usize,
    /// The state episodes start from ([`Rssm::initial`] of the loaded weights).
    zero: RssmState,
    state: RssmState,
    zero_action: Tensor,
    prev_action: Tensor,
    uniform_mode: Tensor,
    stoch: (usize, usize),
    rng: ChaCha8Rng,
}

impl DreamerPolicy {
    /// A policy of the architecture `cfg` for observations of `obs_dim`, with the bytes of
    /// the learner's policy weights; `seed` seeds its sampling noise.
    pub fn new(cfg: &DreamerConfig, obs_dim: usize, weights: &[u8], seed: u64) -> Result<Self> {
        cfg.validate().map_err(candle_core::Error::wrap)?;
        let store = ParamStore::new();
        let stored = DreamerNets::new(cfg, obs_dim, ACT_DIM, store.builder())?;
        store.load_bytes(weights)?;
        let nets = stored.frozen().looped()?;
        let zero = nets.rssm.initial(1)?;
        let zero_action = Tensor::zeros((1, ACT_DIM), DType::F32, &Device::Cpu)?;
        Ok(Self {
            store,
            obs_dim,
            state: zero.clone(),
            zero,
            prev_action: zero_action.clone(),
            zero_action,
            // equal Gumbel noise: the sample is the most likely class
            uniform_mode: Tensor::full(0.5f32, (1, cfg.stoch, cfg.classes), &Device::Cpu)?,
            stoch: (cfg.stoch, cfg.classes),
            stored,
            nets,
            rng: ChaCha8Rng::seed_from_u64(seed),
        })
    }

    /// Replaces the weights (same architecture) without resetting the state (the next
    /// episode starts from the new weights' initial state).
    pub fn load(&mut self, weights: &[u8]) -> Result<()> {
        self.store.load_bytes(weights)?;
        self.nets = self.stored.frozen().looped()?;
        self.zero = self.nets.rssm.initial(1)?;
        Ok(())
    }

    /// Restarts the sampling noise from `seed`.
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// Starts a new episode: the initial state and a zero previous action.
    pub fn reset(&mut self) {
        self.state = self.zero.clone();
        self.prev_action = self.zero_action.clone();
    }

    /// The action in `[−1, 1]²` for observation `obs` and raw context `[c_v, c_θ]`, and (cMask) the
    /// mask used. Deterministic: the mean action, the most likely latent and the mask of
    /// `tanh μ` ([`mask_of`]); otherwise samples.
    pub fn act(
        &mut self,
        obs: &[f32],
        context: [f32; 2],
        deterministic: bool,
    ) -> Result<([f32; 2], Option<[f32; 2]>)> {
        if obs.len() != self.obs_dim {
            bail!(
                "observation has {} values, the policy expects {}",
                obs.len(),
                self.obs_dim
            );
        }
        let dev = &Device::Cpu;
        let o = Tensor::from_slice(obs, (1, self.obs_dim), dev)?;
        let space = self.nets.mask_space;
        let mask = match &self.nets.mask {
            Some(actor) if deterministic => Some(mask_of(&actor.mean_action(&o)?, space)?),
            Some(actor) => {
                let noise = normals(&mut self.rng, (1, CONTEXT_DIM))?;
                Some(mask_sample(actor, &o, &noise, space)?.0)
            }
            None => None,
        };
        let ctx = self.nets.context(
            &Tensor::from_slice(&context, (1, CONTEXT_DIM), dev)?,
            mask.as_ref(),
        )?;
        let (uniform, noise) = if deterministic {
            (self.uniform_mode.clone(), None)
        } else {
            let (s, c) = self.stoch;
            let u = uniforms(&mut self.rng, (1, s, c))?;
            (u, Some(normals(&mut self.rng, (1, ACT_DIM))?))
        };
        let (state, action) = self.nets.observe(
            &self.state,
            &self.prev_action,
            &o,
            ctx.as_ref(),
            &uniform,
            noise.as_ref(),
        )?;
        self.state = state;
        self.prev_action = action.clone();
        let pair = |t: &Tensor| -> Result<[f32; 2]> {
            let v = t.flatten_all()?.to_vec1::<f32>()?;
            Ok([v[0], v[1]])
        };
        Ok((pair(&action)?, mask.as_ref().map(pair).transpose()?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::agents::{ContextMode, ContextScale, MaskConfig};

    /// A DreamerV3 configuration small enough for a test, with the context mode `context`.
    fn tiny(context: ContextMode) -> DreamerConfig {
        DreamerConfig {
            context,
            units: 16,
            layers: 1,
            deter: 16,
            hidden: 16,
            stoch: 4,
            classes: 4,
            head_units: 16,
            head_layers: 1,
            mask: MaskConfig {
                units: 16,
                ..MaskConfig::default()
            },
            ..DreamerConfig::default()
        }
    }
    #[test]
    fn uniform_rows_are_rands_random_range_value_by_value() {
        let seeded = |s: u64| {
            (0..3)
                .map(|i| ChaCha8Rng::seed_from_u64(s + i))
                .collect::<Vec<_>>()
        };
        for (rows, width) in [(2, 37), (1, 256), (5, 1)] {
            let (mut fast, mut one_by_one) = (seeded(7), seeded(7));
            let v = uniform_rows(&mut fast, rows, width);
            let want = rows_per_stream(&mut one_by_one, rows, width, |r| {
                r.random_range(1e-6f32..1.0 - 1e-6)
            });
            assert_eq!(v.len(), want.len());
            for (a, b) in v.iter().zip(&want) {
                assert_eq!(a.to_bits(), b.to_bits(), "{a} vs {b}");
            }
            // and the streams went on from the same place
            for (a, b) in fast.iter_mut().zip(&mut one_by_one) {
                assert_eq!(a.random::<u32>(), b.random::<u32>());
            }
        }
        assert!(uniform_rows(&mut seeded(1), 0, 5).is_empty());
    }

    /// The acting policy feeds the context as `context_scale` says: raw, the network sees `c`
    /// where, normalised, it sees `c / 0.15` (so a raw policy at `c` acts as a normalised one
    /// at `0.15 c`), the mask of cMask multiplying the scaled context.
    #[test]
    fn acting_feeds_the_context_at_its_scale() {
        for context in [ContextMode::Crssm, ContextMode::Cmask] {
            let cfg = |scale| DreamerConfig {
                context_scale: scale,
                ..tiny(context)
            };
            let (raw, normalised) = (cfg(ContextScale::Raw), cfg(ContextScale::Normalised));
            let store = ParamStore::new();
            let nets = DreamerNets::new(&raw, 3, ACT_DIM, store.builder()).unwrap();
            let c = Tensor::new(&[[0.1f32, -0.3]], &Device::Cpu).unwrap();
            let fed: Vec<Vec<f32>> = nets.context(&c, None).unwrap().unwrap().to_vec2().unwrap();
            assert_eq!(fed, [[0.1, -0.3]]);
            let weights = store.to_bytes().unwrap();
            let act = |cfg: &DreamerConfig, c: [f32; 2]| {
                let mut policy = DreamerPolicy::new(cfg, 3, &weights, 1).unwrap();
                (0..3)
                    .map(|_| policy.act(&[0.5, 0.2, 0.1], c, true).unwrap().0)
                    .collect::<Vec<_>>()
            };
            let (a, b) = (act(&raw, [0.06, -0.09]), act(&normalised, [0.009, -0.0135]));
            for (x, y) in a.iter().flatten().zip(b.iter().flatten()) {
                assert!((x - y).abs() < 1e-5, "{a:?} vs {b:?}");
            }
            let other = act(&normalised, [0.06, -0.09]);
            assert!(
                a.iter()
                    .flatten()
                    .zip(other.iter().flatten())
                    .any(|(x, y)| (x - y).abs() > 1e-4),
                "the context scale changes nothing: {a:?} vs {other:?}"
            );
        }
    }

    /// The acting masks of each [`MaskSpace`]: `(1 + tanh u)/2` over `(0, 1)`, the paper's code's
    /// `sigmoid(tanh u)` inside `(σ(−1), σ(1)) ≈ (0.269, 0.731)`; the deterministic mask is the
    /// space's map of `tanh μ`.
    #[test]
    fn the_policy_acts_with_the_mask_of_its_space() {
        let unit = MaskConfig {
            units: 16,
            ..MaskConfig::default()
        };
        for mask in [unit.clone(), unit.with_paper_code_mask()] {
            let cfg = DreamerConfig {
                mask,
                ..tiny(ContextMode::Cmask)
            };
            let store = ParamStore::new();
            let nets = DreamerNets::new(&cfg, 3, ACT_DIM, store.builder()).unwrap();
            let mut policy = DreamerPolicy::new(&cfg, 3, &store.to_bytes().unwrap(), 1).unwrap();
            let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
            let (lo, hi) = match cfg.mask.mask_space {
                MaskSpace::Unit => (0.0, 1.0),
                MaskSpace::PaperCode => (sigmoid(-1.0), sigmoid(1.0)),
            };
            let (mut least, mut most) = (1f32, 0f32);
            for k in 0..200 {
                let obs = [0.5, 0.2, (k as f32 * 0.37).sin() * 3.0];
                let (_, m) = policy.act(&obs, [0.1, -0.1], false).unwrap();
                for v in m.unwrap() {
                    assert!(lo <= v && v <= hi, "{:?}: {v}", cfg.mask.mask_space);
                    (least, most) = (least.min(v), most.max(v));
                }
            }
            // the samples spread over the range (an untrained actor's σ is about 1)
            assert!(most - least > 0.5 * (hi - lo), "{least}..{most}");
            let obs = [0.5, 0.2, 0.1];
            let (_, m) = policy.act(&obs, [0.1, -0.1], true).unwrap();
            let o = Tensor::from_slice(&obs, (1, 3), &Device::Cpu).unwrap();
            let mode = nets.mask.as_ref().unwrap().mean_action(&o).unwrap();
            let want: Vec<f32> = mask_of(&mode, cfg.mask.mask_space)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            // the acting pass and the candle composition may round differently (one ulp)
            let got = m.unwrap();
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-6, "{got:?} vs {want:?}");
            }
        }
    }

    #[test]
    fn the_kept_state_holds_no_graph_of_earlier_steps() {
        let cfg = tiny(ContextMode::Cmask);
        let store = ParamStore::new();
        DreamerNets::new(&cfg, 3, ACT_DIM, store.builder()).unwrap();
        let mut policy = DreamerPolicy::new(&cfg, 3, &store.to_bytes().unwrap(), 1).unwrap();
        for deterministic in [true, false] {
            let (action, mask) = policy
                .act(&[0.5, 0.2, 0.1], [0.1, -0.1], deterministic)
                .unwrap();
            assert!(action
                .iter()
                .chain(mask.iter().flatten())
                .all(|v| v.is_finite()));
            // the stored weights are variables, the acting copies are not: what the policy
            // keeps holds no graph of the episode's earlier steps (memory grew ~80 KB a step)
            for t in [
                &policy.state.deter,
                &policy.state.stoch,
                &policy.prev_action,
            ] {
                assert!(!t.track_op());
            }
        }
    }

    /// With the paper code's world model the policy acts as the code does: the sequence model
    /// reads the previous action (zero at the first step), the encoder `symlog [o_t, a_{t−1}]`,
    /// from the learned initial state; its state after two steps is the candle composition's.
    #[test]
    fn the_paper_code_policy_feeds_the_previous_action_to_the_encoder() {
        let cfg = tiny(ContextMode::None).with_paper_code_world_model();
        let store = ParamStore::new();
        let nets = DreamerNets::new(&cfg, 3, ACT_DIM, store.builder()).unwrap();
        store.init(2).unwrap();
        for (name, v) in store.named() {
            if name == "rssm.initial_state.w" {
                v.set(&Tensor::randn(0f32, 1.0, v.shape(), &Device::Cpu).unwrap())
                    .unwrap();
            }
        }
        let mut policy = DreamerPolicy::new(&cfg, 3, &store.to_bytes().unwrap(), 1).unwrap();
        let dev = &Device::Cpu;
        let mut state = nets.rssm.initial(1).unwrap();
        let mut prev = Tensor::zeros((1, ACT_DIM), DType::F32, dev).unwrap();
        let u = Tensor::full(0.5f32, (1, 4, 4), dev).unwrap();
        for obs in [[0.5f32, 0.2, 0.1], [0.3, -0.4, 0.9]] {
            let (action, _) = policy.act(&obs, [0.0; 2], true).unwrap();
            let o = Tensor::from_slice(&obs, (1, 3), dev).unwrap();
            let input = symlog(&Tensor::cat(&[&o, &prev], 1).unwrap()).unwrap();
            let embed = nets.encoder.forward(&input).unwrap();
            let (next, _) = nets.rssm.obs_step(&state, &prev, None, &embed, &u).unwrap();
            let (mean, _) = nets.actor_dist(&next.feat().unwrap()).unwrap();
            let want: Vec<f32> = mean.flatten_all().unwrap().to_vec1().unwrap();
            let got: Vec<f32> = policy.state.deter.flatten_all().unwrap().to_vec1().unwrap();
            let deter: Vec<f32> = next.deter.flatten_all().unwrap().to_vec1().unwrap();
            for (a, b) in got.iter().zip(&deter).chain(action.iter().zip(&want)) {
                assert!((a - b).abs() < 1e-5, "{a} vs {b}");
            }
            (state, prev) = (next, mean);
        }
    }
}
