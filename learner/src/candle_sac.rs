//! The candle-held forms of SAC's critics and Polyak averaging, kept for cMask's mask SAC
//! ([`crate::cmask`]) and DreamerV3's slow critic ([`crate::dreamer`]) until they train in
//! place on [`crate::sac_core`] and `ctxrace_common::nn::plain::polyak`; the tests' candle
//! oracle for SAC's critics ([`TwinQ::forward`]).

use crate::sac_core::PlainActor;
use candle_core::backprop::GradStore;
use candle_core::Result;
#[cfg(test)]
use candle_core::{Module, Tensor, D};
use candle_nn::VarBuilder;
use ctxrace_common::nn::plain::{MlpGrads, PlainMlp};
use ctxrace_common::nn::{Activation, Mlp, ParamStore, TanhGaussianActor};

/// Twin critics `Q_1, Q_2 (o, a)`: two ReLU MLPs `q1`, `q2` on `[o, a]`, held by candle.
pub(crate) struct TwinQ {
    q1: Mlp,
    q2: Mlp,
}

impl TwinQ {
    /// Critics on inputs `[o, a]` of `input` values, `layers` hidden layers of `hidden` units.
    pub(crate) fn new(input: usize, hidden: usize, layers: usize, vb: VarBuilder) -> Result<Self> {
        let q = |name: &str| {
            Mlp::new(
                input,
                hidden,
                layers,
                Some(1),
                Activation::Relu,
                vb.pp(name),
            )
        };
        Ok(Self {
            q1: q("q1")?,
            q2: q("q2")?,
        })
    }

    /// `(Q_1, Q_2)`, each `[B]`, for observations `[B, O]` and actions `[B, A]` (the candle
    /// composition that the tests hold the plain passes to).
    #[cfg(test)]
    pub(crate) fn forward(&self, obs: &Tensor, action: &Tensor) -> Result<(Tensor, Tensor)> {
        let x = Tensor::cat(&[obs, action], D::Minus1)?;
        Ok((
            self.q1.forward(&x)?.squeeze(D::Minus1)?,
            self.q2.forward(&x)?.squeeze(D::Minus1)?,
        ))
    }

    /// `min(Q_1, Q_2)` `[B]`.
    #[cfg(test)]
    pub(crate) fn min(&self, obs: &Tensor, action: &Tensor) -> Result<Tensor> {
        let (q1, q2) = self.forward(obs, action)?;
        q1.minimum(&q2)
    }

    /// Both critics on plain buffers (copies of the current weights).
    pub(crate) fn plain(&self) -> Result<[PlainMlp; 2]> {
        Ok([PlainMlp::new(&self.q1)?, PlainMlp::new(&self.q2)?])
    }

    /// Adds the gradients `grads` of the plain copies `plain` ([`TwinQ::plain`]) into `store`.
    pub(crate) fn add_grads_to(
        &self,
        plain: &[PlainMlp; 2],
        grads: [MlpGrads; 2],
        store: &mut GradStore,
    ) -> Result<()> {
        let [q1, q2] = grads;
        plain[0].add_grads_to(q1, &self.q1, store)?;
        plain[1].add_grads_to(q2, &self.q2, store)
    }
}

/// Polyak averaging `target ← (1 − τ) target + τ source`, parameter by parameter (the two stores
/// hold the same names).
pub(crate) fn polyak(target: &ParamStore, source: &ParamStore, tau: f64) -> Result<()> {
    for ((_, t), (_, s)) in target.named().iter().zip(source.named()) {
        t.set(&((t.as_tensor() * (1.0 - tau))? + (s.as_tensor() * tau)?)?)?;
    }
    Ok(())
}

impl<'a> PlainActor<'a> {
    /// `net`, a plain copy of `actor`'s network, with `actor`'s log-std bounds.
    pub(crate) fn new(net: &'a PlainMlp, actor: &TanhGaussianActor) -> Self {
        let [lo, hi] = actor.log_std_clamp();
        Self {
            net,
            log_std_clamp: [lo as f32, hi as f32],
        }
    }
}
