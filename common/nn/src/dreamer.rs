//! DreamerV3's acting networks (encoder, RSSM, actor and cMask's mask actor): [`PolicyNets`],
//! which the learner trains in place and the actors run; the heads on the model state
//! ([`state_head`]), the parameter names the learner's policy weights carry, the mask of the mask
//! actor's squashed value ([`mask_value`]), and the noise the learner and the acting policies
//! draw (Gumbel uniforms, standard normals), per stream.

use crate::initial_weights::init_dreamer;
use crate::parameters::{update_each, NamedTensor, Parameters};
use crate::{Activation, Mlp, MlpShape, Rssm, RssmConfig, Weights, WeightsError};
use ctxrace_config::agents::{ContextMode, DreamerConfig, InitialState, MaskSpace, CONTEXT_DIM};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// The networks that act, on plain buffers: encoder, RSSM, actor and (cMask) mask actor, under
/// the names `encoder.`, `rssm.`, `actor.`, `mask.` (the learner's "policy" weights).
#[derive(Clone, Debug)]
pub struct PolicyNets {
    /// Observation encoder (on `symlog o`, or on `symlog [o, a]` with
    /// [`ctxrace_config::agents::StepAlignment::PaperCode`]).
    pub encoder: Mlp,
    /// The recurrent state-space model.
    pub rssm: Rssm,
    /// Actor head on `[h, z, c]`: means and raw standard deviations.
    pub actor: Mlp,
    /// cMask's mask actor on the observation: a ReLU MLP to the means, then the log-σs.
    pub mask: Option<Mlp>,
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
        let encoder = Mlp::from_weights(weights, "encoder.", &encoder)?;
        let rssm = Rssm::from_weights(weights, "rssm.", rssm_config(cfg, obs_dim, act_dim))?;
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
                Some(Mlp::from_weights(weights, "mask.", &shape)?)
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
) -> std::result::Result<Mlp, WeightsError> {
    let (d, z) = (cfg.deter, cfg.stoch * cfg.classes);
    let shape = MlpShape {
        input: d + z + cfg.context.context_dim(),
        units,
        layers,
        out: Some(out),
        act: Activation::SiluNorm,
    };
    Ok(Mlp::from_weights(weights, prefix, &shape)?.sparse_inputs(d..d + z))
}

/// The RSSM's sizes for `cfg`, observations of `obs_dim` and actions of `act_dim`.
pub fn rssm_config(cfg: &DreamerConfig, obs_dim: usize, act_dim: usize) -> RssmConfig {
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

/// The mask of one squashed value `a = tanh u` of the mask actor in `space`: `(a + 1) / 2`
/// (unit), `sigmoid(a)` (the paper's code).
pub fn mask_value(a: f32, space: MaskSpace) -> f32 {
    match space {
        MaskSpace::Unit => a * 0.5 + 0.5,
        MaskSpace::PaperCode => 1.0 / (1.0 + (-a).exp()),
    }
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
