//! DreamerV3's acting networks (encoder, RSSM, actor and cMask's mask actor): [`PolicyNets`] on
//! plain buffers, which the learner trains and the actors run, and [`DreamerNets`], the same as
//! candle modules (the oracle the hand-written passes are tested against); the heads on the
//! model state ([`state_head`]), the parameter names the learner's policy weights carry, and the
//! noise the learner and the acting policies draw (Gumbel uniforms, standard normals), per stream.

#[cfg(any(test, feature = "oracle"))]
use crate::agents::StepAlignment;
use crate::agents::{ContextMode, DreamerConfig, InitialState, MaskSpace, CONTEXT_DIM};
use crate::nn::initial_weights::init_dreamer;
use crate::nn::plain::{update_each, NamedTensor, Parameters, PlainMlp, PlainRssm};
use crate::nn::{Activation, MlpShape, RssmConfig, Weights, WeightsError};
#[cfg(any(test, feature = "oracle"))]
use crate::nn::{Mlp, Rssm, TanhGaussianActor};
#[cfg(any(test, feature = "oracle"))]
use candle_core::{Device, Module, Result, Tensor};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// The networks that act, on plain buffers: encoder, RSSM, actor and (cMask) mask actor, under
/// the names `encoder.`, `rssm.`, `actor.`, `mask.` (the learner's "policy" weights).
#[derive(Clone, Debug)]
pub struct PolicyNets {
    /// Observation encoder (on `symlog o`, or on `symlog [o, a]` with
    /// [`StepAlignment::PaperCode`]).
    pub encoder: PlainMlp,
    /// The recurrent state-space model.
    pub rssm: PlainRssm,
    /// Actor head on `[h, z, c]`: means and raw standard deviations.
    pub actor: PlainMlp,
    /// cMask's mask actor on the observation: a ReLU MLP to the means, then the log-σs.
    pub mask: Option<PlainMlp>,
}

impl PolicyNets {
    /// The networks of `cfg` for observations of `obs_dim` and actions of `act_dim`, read from
    /// `weights` (those of a policy file, or [`Weights::initial`]).
    pub fn from_weights(
        cfg: &DreamerConfig,
        obs_dim: usize,
        act_dim: usize,
        weights: &mut Weights,
    ) -> std::result::Result<Self, WeightsError> {
        let encoder = MlpShape {
            input: cfg.encoder_inputs(obs_dim, act_dim),
            units: cfg.units,
            layers: cfg.layers,
            out: None,
            act: Activation::SiluNorm,
        };
        let encoder = PlainMlp::from_weights(weights, "encoder.", &encoder)?;
        let rssm = PlainRssm::from_weights(weights, "rssm.", rssm_config(cfg, obs_dim, act_dim))?;
        let size = (cfg.head_units, cfg.head_layers);
        let actor = state_head(cfg, weights, "actor.", size, 2 * act_dim)?;
        let mask = match cfg.context {
            ContextMode::Cmask => {
                let shape = MlpShape {
                    input: obs_dim,
                    units: cfg.mask.units,
                    layers: cfg.mask.layers,
                    out: Some(2 * CONTEXT_DIM),
                    act: Activation::Relu,
                };
                Some(PlainMlp::from_weights(weights, "mask.", &shape)?)
            }
            ContextMode::None | ContextMode::Crssm => None,
        };
        Ok(Self {
            encoder,
            rssm,
            actor,
            mask,
        })
    }

    /// Freshly initialised networks of `cfg` (drawn from `cfg.seed` as `cfg.init` says,
    /// [`init_dreamer`]).
    pub fn initial(
        cfg: &DreamerConfig,
        obs_dim: usize,
        act_dim: usize,
    ) -> std::result::Result<Self, WeightsError> {
        let mut nets = Self::from_weights(cfg, obs_dim, act_dim, &mut Weights::initial())?;
        init_dreamer(&mut nets, cfg.seed, cfg, (obs_dim, act_dim));
        Ok(nets)
    }
}

impl Parameters for PolicyNets {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        let mut v = self.encoder.tensors();
        v.extend(self.rssm.tensors());
        v.extend(self.actor.tensors());
        if let Some(mask) = &self.mask {
            v.extend(mask.tensors());
        }
        v
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        let mut nets: Vec<&mut dyn Parameters> =
            vec![&mut self.encoder, &mut self.rssm, &mut self.actor];
        if let Some(mask) = &mut self.mask {
            nets.push(mask);
        }
        update_each(nets, f);
    }
}

/// A SiLU-LayerNorm MLP of `layers` layers of `units` on the model state `[h, z, c]` of `cfg`
/// to `out` outputs (actor, critics, decoder, reward and continue heads), read from `weights`
/// under `prefix`, told that the one-hot `z` columns are mostly zero.
pub fn state_head(
    cfg: &DreamerConfig,
    weights: &mut Weights,
    prefix: &str,
    (units, layers): (usize, usize),
    out: usize,
) -> std::result::Result<PlainMlp, WeightsError> {
    let (d, z) = (cfg.deter, cfg.stoch * cfg.classes);
    let shape = MlpShape {
        input: d + z + cfg.context.context_dim(),
        units,
        layers,
        out: Some(out),
        act: Activation::SiluNorm,
    };
    Ok(PlainMlp::from_weights(weights, prefix, &shape)?.sparse_inputs(d..d + z))
}

/// The networks that act as candle modules (the oracle of the tests): encoder, RSSM, actor and
/// (cMask) mask actor.
#[cfg(any(test, feature = "oracle"))]
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

#[cfg(any(test, feature = "oracle"))]
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
        let rssm = Rssm::new(rssm_config(cfg, obs_dim, act_dim), vb.pp("rssm"))?;
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
        let out = self.actor.forward(x)?;
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
}

/// The RSSM's sizes for `cfg`, observations of `obs_dim` and actions of `act_dim`.
pub(crate) fn rssm_config(cfg: &DreamerConfig, obs_dim: usize, act_dim: usize) -> RssmConfig {
    let enc_in = cfg.encoder_inputs(obs_dim, act_dim);
    RssmConfig {
        deter: cfg.deter,
        hidden: cfg.hidden,
        stoch: cfg.stoch,
        classes: cfg.classes,
        unimix: cfg.unimix,
        act_dim,
        embed_dim: if cfg.layers == 0 { enc_in } else { cfg.units },
        context_dim: cfg.context.context_dim(),
        learned_initial: cfg.initial_state == InitialState::Learned,
    }
}

/// The mask of the mask actor's squashed value `a = tanh u` in `space`: `(a + 1) / 2` (unit),
/// `sigmoid(a)` (the paper's code).
#[cfg(any(test, feature = "oracle"))]
pub fn mask_of(a: &Tensor, space: MaskSpace) -> Result<Tensor> {
    match space {
        MaskSpace::Unit => a.affine(0.5, 0.5),
        MaskSpace::PaperCode => candle_nn::ops::sigmoid(a),
    }
}

/// A mask sample from the tanh-Gaussian mask actor and `log π` in `space`: unit,
/// `m = (a + 1) / 2` and its density `log π(m) = log π(a) + |m| ln 2`; the paper's code,
/// `m = sigmoid(a)` and the density of `a` itself (where the code takes its entropy).
#[cfg(any(test, feature = "oracle"))]
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

/// The mask of one squashed value `a = tanh u` of the mask actor in `space` ([`mask_of`]).
pub fn mask_value(a: f32, space: MaskSpace) -> f32 {
    match space {
        MaskSpace::Unit => a * 0.5 + 0.5,
        MaskSpace::PaperCode => 1.0 / (1.0 + (-a).exp()),
    }
}

/// Gumbel-max uniforms in `(0, 1)`.
#[cfg(any(test, feature = "oracle"))]
pub fn uniforms(rng: &mut ChaCha8Rng, shape: (usize, usize, usize)) -> Result<Tensor> {
    uniforms_per(std::slice::from_mut(rng), shape.0, (shape.1, shape.2))
}

/// Standard-normal noise.
#[cfg(any(test, feature = "oracle"))]
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
#[cfg(any(test, feature = "oracle"))]
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
#[cfg(any(test, feature = "oracle"))]
pub fn normals_per(rngs: &mut [ChaCha8Rng], rows: usize, width: usize) -> Result<Tensor> {
    let n = rngs.len() * rows;
    Tensor::from_vec(normal_rows(rngs, rows, width), (n, width), &Device::Cpu)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

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
}
