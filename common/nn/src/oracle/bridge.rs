//! From the oracle's candle modules to the networks and back: a network with the weights a
//! candle module holds now ([`Mlp::from_oracle`], [`Rssm::from_oracle`]), and a network's
//! parameter gradients added into candle's `GradStore` under that module's tensors
//! ([`Mlp::add_grads_to`]), so that the tests compare values and gradients tensor by tensor.

use super::{Dense, LayerNorm, Mlp as CandleMlp, Rssm as CandleRssm};
use crate::kernels::NormAct;
use crate::layer::{After, NormParams};
use crate::{Activation, Layer, Mlp, MlpGrads, Rssm};
use candle_core::{backprop::GradStore, bail, Result, Tensor};

/// The values of a contiguous CPU tensor.
fn values(t: &Tensor) -> Result<Vec<f32>> {
    t.flatten_all()?.to_vec1::<f32>()
}

impl Layer {
    /// The layer `dense` followed by its normalisation and activation `norm`, or else a ReLU if
    /// `relu`, or else nothing.
    fn from_oracle(dense: &Dense, norm: Option<(&LayerNorm, NormAct)>, relu: bool) -> Result<Self> {
        let (outputs, inputs) = dense.weight().dims2()?;
        let after = match (norm, relu) {
            (Some((ln, act)), _) => {
                let (gain, bias, eps) = ln.parts();
                After::Norm(NormParams {
                    gain: values(gain)?,
                    bias: values(bias)?,
                    eps: eps as f32,
                    act,
                })
            }
            (None, true) => After::Relu,
            (None, false) => After::Nothing,
        };
        let bias = dense.bias().map(values).transpose()?;
        let layer = Self::from_values(values(dense.weight())?, (outputs, inputs), bias, after);
        Ok(match dense.sparse_columns() {
            Some(columns) => layer.sparse_inputs(columns.clone()),
            None => layer,
        })
    }
}

impl Mlp {
    /// The network with the weights `mlp` holds now.
    pub fn from_oracle(mlp: &CandleMlp) -> Result<Self> {
        let (hidden, head, act) = mlp.parts();
        let mut layers = Vec::with_capacity(hidden.len() + 1);
        for (dense, ln) in hidden {
            layers.push(match (act, ln) {
                (Activation::SiluNorm, Some(ln)) => {
                    Layer::from_oracle(dense, Some((ln, NormAct::Silu)), false)?
                }
                (Activation::Relu, None) => Layer::from_oracle(dense, None, true)?,
                _ => bail!("MLP: a hidden layer of {act:?} without its normalisation"),
            });
        }
        if let Some(head) = head {
            layers.push(Layer::from_oracle(head, None, false)?);
        }
        Ok(Self { layers })
    }

    /// The gradients `grads` of this network's parameters (copied from `mlp`,
    /// [`Mlp::from_oracle`]) added into `store` under `mlp`'s tensors.
    pub fn add_grads_to(
        &self,
        grads: MlpGrads,
        mlp: &CandleMlp,
        store: &mut GradStore,
    ) -> Result<()> {
        let (hidden, head, _) = mlp.parts();
        let mut params = Vec::new();
        for (dense, ln) in hidden
            .iter()
            .map(|(d, ln)| (d, ln.as_ref()))
            .chain(head.map(|h| (h, None)))
        {
            params.push(dense.weight());
            params.extend(dense.bias());
            if let Some(ln) = ln {
                let (gain, bias, _) = ln.parts();
                params.extend([gain, bias]);
            }
        }
        let grads = grads.into_tensors(self);
        if grads.len() != params.len() {
            bail!(
                "{} gradients for the {} tensors of the candle MLP",
                grads.len(),
                params.len()
            );
        }
        for (param, grad) in params.into_iter().zip(grads) {
            let grad = Tensor::from_vec(grad, param.shape(), param.device())?;
            let sum = match store.get(param) {
                Some(g) => (g + grad)?,
                None => grad,
            };
            store.insert(param, sum);
        }
        Ok(())
    }
}

impl Rssm {
    /// The model with the weights `rssm` holds now.
    pub fn from_oracle(rssm: &CandleRssm) -> Result<Self> {
        let [img_in, gates, prior, prior_out, post, post_out] = rssm.blocks();
        let layer = |(dense, norm)| Layer::from_oracle(dense, norm, false);
        Ok(Self {
            cfg: *rssm.config(),
            img_in: layer(img_in)?,
            gates: layer(gates)?,
            prior: Mlp {
                layers: vec![layer(prior)?, layer(prior_out)?],
            },
            post: layer(post)?,
            post_out: layer(post_out)?,
            initial_w: rssm.initial_weight().map(|w| w.to_vec1()).transpose()?,
            initial_name: String::new(),
        })
    }
}
