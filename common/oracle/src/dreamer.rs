//! The oracle's DreamerV3 acting networks (candle modules): [`DreamerNets`], the networks of
//! [`ctxrace_nn::dreamer::PolicyNets`] as candle composes them, the mask actor's masks and
//! samples, and the noise of [`ctxrace_nn::dreamer`] as candle tensors.

use super::{Mlp, Rssm, TanhGaussianActor};
use candle_core::{Device, Module, Result, Tensor};
use ctxrace_config::agents::{ContextMode, DreamerConfig, MaskSpace, StepAlignment, CONTEXT_DIM};
use ctxrace_nn::dreamer::{normal_rows, rssm_config, uniform_rows};
use ctxrace_nn::Activation;
use rand_chacha::ChaCha8Rng;

/// The networks that act as candle modules (the oracle of the tests): encoder, RSSM, actor and
/// (cMask) mask actor.
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
