//! From the oracle's candle modules to the networks and back: a network with the weights a
//! candle module holds now ([`FromOracle::from_oracle`], for [`Mlp`] and [`Rssm`]), and a
//! network's parameter gradients added into candle's `GradStore` under that module's tensors
//! ([`AddGradsTo::add_grads_to`]), so that the tests compare values and gradients tensor by
//! tensor. (Traits, since ctxrace-nn's types take no inherent methods here: in scope, they are
//! called as the networks' own, `Mlp::from_oracle(&module)`.)

use super::{Dense, LayerNorm, Mlp as CandleMlp, Rssm as CandleRssm};
use candle_core::{backprop::GradStore, bail, Result, Tensor};
use ctxrace_nn::kernels::NormAct;
use ctxrace_nn::layer::{After, NormParams};
use ctxrace_nn::{Activation, Layer, Mlp, MlpGrads, Rssm};

/// A network of ctxrace-nn copied from its candle module in the oracle.
pub trait FromOracle: Sized {
    /// The candle module.
    type Oracle;

    /// The network with the weights `oracle` holds now.
    fn from_oracle(oracle: &Self::Oracle) -> Result<Self>;
}

/// A network's parameter gradients handed back to candle.
pub trait AddGradsTo {
    /// The candle module the network was copied from ([`FromOracle::from_oracle`]).
    type Oracle;
    /// The network's parameter gradients.
    type Grads;

    /// The gradients `grads` of this network's parameters (copied from `oracle`,
    /// [`FromOracle::from_oracle`]) added into `store` under `oracle`'s tensors.
    fn add_grads_to(
        &self,
        grads: Self::Grads,
        oracle: &Self::Oracle,
        store: &mut GradStore,
    ) -> Result<()>;
}

/// The values of a contiguous CPU tensor.
fn values(t: &Tensor) -> Result<Vec<f32>> {
    t.flatten_all()?.to_vec1::<f32>()
}

/// The layer `dense` followed by its normalisation and activation `norm`, or else a ReLU if
/// `relu`, or else nothing.
fn layer_from_oracle(
    dense: &Dense,
    norm: Option<(&LayerNorm, NormAct)>,
    relu: bool,
) -> Result<Layer> {
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
    let layer = Layer::from_values(values(dense.weight())?, (outputs, inputs), bias, after);
    Ok(match dense.sparse_columns() {
        Some(columns) => layer.sparse_inputs(columns.clone()),
        None => layer,
    })
}

impl FromOracle for Mlp {
    type Oracle = CandleMlp;

    fn from_oracle(mlp: &CandleMlp) -> Result<Self> {
        let (hidden, head, act) = mlp.parts();
        let mut layers = Vec::with_capacity(hidden.len() + 1);
        for (dense, ln) in hidden {
            layers.push(match (act, ln) {
                (Activation::SiluNorm, Some(ln)) => {
                    layer_from_oracle(dense, Some((ln, NormAct::Silu)), false)?
                }
                (Activation::Relu, None) => layer_from_oracle(dense, None, true)?,
                _ => bail!("MLP: a hidden layer of {act:?} without its normalisation"),
            });
        }
        if let Some(head) = head {
            layers.push(layer_from_oracle(head, None, false)?);
        }
        Ok(Mlp::from_layers(layers))
    }
}

impl AddGradsTo for Mlp {
    type Oracle = CandleMlp;
    type Grads = MlpGrads;

    fn add_grads_to(&self, grads: MlpGrads, mlp: &CandleMlp, store: &mut GradStore) -> Result<()> {
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

impl FromOracle for Rssm {
    type Oracle = CandleRssm;

    fn from_oracle(rssm: &CandleRssm) -> Result<Self> {
        let [img_in, gates, prior, prior_out, post, post_out] = rssm.blocks();
        let layer = |(dense, norm)| layer_from_oracle(dense, norm, false);
        let layers = [
            layer(img_in)?,
            layer(gates)?,
            layer(prior)?,
            layer(prior_out)?,
            layer(post)?,
            layer(post_out)?,
        ];
        let initial_w = rssm.initial_weight().map(|w| w.to_vec1()).transpose()?;
        Ok(Rssm::from_layers(*rssm.config(), layers, initial_w))
    }
}
