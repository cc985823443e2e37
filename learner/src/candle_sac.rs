//! The tests' candle oracle for SAC's twin critics (SAC's and cMask's mask SAC's): the same
//! networks composed of candle operations, which the hand-differentiated passes are held to.

use candle_core::{Module, Result, Tensor, D};
use candle_nn::VarBuilder;
use ctxrace_nn::Activation;
use ctxrace_oracle::Mlp;

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
    pub(crate) fn forward(&self, obs: &Tensor, action: &Tensor) -> Result<(Tensor, Tensor)> {
        let x = Tensor::cat(&[obs, action], D::Minus1)?;
        Ok((
            self.q1.forward(&x)?.squeeze(D::Minus1)?,
            self.q2.forward(&x)?.squeeze(D::Minus1)?,
        ))
    }

    /// `min(Q_1, Q_2)` `[B]`.
    pub(crate) fn min(&self, obs: &Tensor, action: &Tensor) -> Result<Tensor> {
        let (q1, q2) = self.forward(obs, action)?;
        q1.minimum(&q2)
    }
}
