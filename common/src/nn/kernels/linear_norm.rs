//! `act(LayerNorm(x Wᵀ))` as one operation: the block of every DreamerV3 layer.
//!
//! As two operations the product `p = x Wᵀ` is a node of candle's graph, and the backward pass
//! gives it a zeroed gradient buffer that the normalisation's gradient is added into before the
//! product reads it. Here the product's values stay inside the operation (kept for the backward
//! pass), and `∂p` goes from the normalisation's backward straight into the product's
//! (`dx = ∂p W`, `dW = ∂pᵀ x`).

use super::linear::{product, Linear, WeightGradTape};
use super::norm_act::{norm_act_rows, norm_act_rows_bwd, Norm};
use super::*;
use std::sync::{Arc, Mutex, PoisonError};

struct LinearNormAct {
    linear: Linear,
    eps: f32,
    act: NormAct,
    /// `x Wᵀ` of the forward pass (of the trained twin's, shared, for a frozen twin).
    product: Arc<Mutex<Vec<f32>>>,
    /// The output's values, computed already by the trained twin of [`linear_norm_act_twice`]:
    /// the forward pass copies them and leaves `product` as the twin left it.
    known: Option<Tensor>,
}

impl LinearNormAct {
    /// The normalisation of the values `[γ, β]`.
    fn norm<'a>(&self, gain_bias: &'a [f32]) -> Norm<'a> {
        let (gain, bias) = gain_bias.split_at(gain_bias.len() / 2);
        Norm {
            gain,
            bias,
            eps: self.eps,
            act: self.act,
        }
    }

    /// The block on `x` with the weight argument and `[γ, β]`.
    fn apply(self, x: &Tensor, weight: &Tensor, gain_bias: &Tensor) -> Result<Tensor> {
        x.contiguous()?.apply_op3(weight, gain_bias, self)
    }
}

impl CustomOp3 for LinearNormAct {
    fn name(&self) -> &'static str {
        "ctxrace-linear-norm-act"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        if let Some(known) = &self.known {
            let out = read(known, |y| Ok(y.to_vec()))?;
            let (rows, _) = l1.shape().dims2()?;
            if known.dims().first() != Some(&rows) {
                bail!(
                    "linear_norm_act: known values {:?} for {rows} rows",
                    known.dims()
                );
            }
            return Ok((CpuStorage::F32(out), known.shape().clone()));
        }
        let (p, shape) = self.linear.fwd((s1, l1), (s2, l2), None)?;
        let CpuStorage::F32(p) = p else {
            bail!("linear_norm_act: f32 only")
        };
        let gb = cpu_slice(s3, l3)?;
        let d = gb.len() / 2;
        if d == 0 || gb.len() != 2 * d || shape.dims().last() != Some(&d) {
            bail!(
                "linear_norm_act: {d} gains and biases for outputs {:?}",
                shape.dims()
            );
        }
        let out = norm_act_rows(&p, self.norm(gb));
        *self.product.lock().unwrap_or_else(PoisonError::into_inner) = p;
        Ok((CpuStorage::F32(out), shape))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        gain_bias: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = gain_bias.elem_count() / 2;
        let (dp, dgb) = read(gain_bias, |gb| {
            read(res, |y| {
                read(grad, |dy| {
                    let p = self.product.lock().unwrap_or_else(PoisonError::into_inner);
                    if p.len() != dy.len() || y.len() != dy.len() {
                        bail!("linear_norm_act: backward pass without its forward pass");
                    }
                    let mut dgb = vec![0f32; 2 * d];
                    let dp = norm_act_rows_bwd((&p, y), self.norm(gb), dy, &mut dgb);
                    Ok((dp, dgb))
                })
            })
        })?;
        let dp = Tensor::from_vec(dp, res.shape(), res.device())?;
        let (dx, dw) = self.linear.bwd_xw(x, w, &dp)?;
        let dgb = wants_grad(gain_bias)
            .then(|| Tensor::from_vec(dgb, 2 * d, res.device()))
            .transpose()?;
        Ok((dx, dw, dgb))
    }
}

/// `act(LayerNorm(x Wᵀ))` for `x` `[N, in]`, `weight` `[out, in]` (or, with `weight_t`, the
/// transposed layout and optional weight-gradient tape of [`super::linear_t`]) and the
/// normalisation's `(gain, bias, ε)`, each of `out`: [`super::linear`] then [`super::norm_act`]
/// in one operation; the input columns `sparse_inputs` as in [`super::linear`].
pub fn linear_norm_act(
    x: &Tensor,
    weight: &Tensor,
    weight_t: Option<&Tensor>,
    tape: Option<&WeightGradTape>,
    (gain, bias, eps): (&Tensor, &Tensor, f64),
    act: NormAct,
    sparse_inputs: Option<std::ops::Range<usize>>,
) -> Result<Tensor> {
    let (linear, weight) = product(weight, weight_t, tape, sparse_inputs)?;
    let op = LinearNormAct {
        linear,
        eps: eps as f32,
        act,
        product: Arc::default(),
        known: None,
    };
    op.apply(x, &weight, &Tensor::cat(&[gain, bias], 0)?)
}

/// [`linear_norm_act`] (stored weight layout) on the two paths `(x_frozen, x_trained)` of one
/// input from one product and normalisation, as [`super::linear_twice`]: `(y_frozen, y_trained)`,
/// equal values; `y_trained` takes the gradients of [`linear_norm_act`] on `x_trained`,
/// `y_frozen` only its input's.
pub fn linear_norm_act_twice(
    (x_frozen, x_trained): (&Tensor, &Tensor),
    weight: &Tensor,
    (gain, bias, eps): (&Tensor, &Tensor, f64),
    act: NormAct,
    sparse_inputs: Option<std::ops::Range<usize>>,
) -> Result<(Tensor, Tensor)> {
    let (linear, weight) = product(weight, None, None, sparse_inputs)?;
    let (eps, product) = (eps as f32, Arc::<Mutex<Vec<f32>>>::default());
    let gain_bias = Tensor::cat(&[gain, bias], 0)?;
    let trained = LinearNormAct {
        linear,
        eps,
        act,
        product: product.clone(),
        known: None,
    }
    .apply(x_trained, &weight, &gain_bias)?;
    let frozen = LinearNormAct {
        linear: Linear::frozen(None),
        eps,
        act,
        product,
        known: Some(trained.detach()),
    }
    .apply(x_frozen, &weight.detach(), &gain_bias.detach())?;
    Ok((frozen, trained))
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::*;

    #[test]
    fn linear_norm_act_matches_the_two_operations() {
        let (x, w) = (var(&[7, 5], 21), var(&[6, 5], 22));
        let (g, b) = (var(&[6], 23), var(&[6], 24));
        let eps = 1e-3;
        for act in [NormAct::Silu, NormAct::Identity] {
            let two = |p: Tensor| norm_act(&p, &g, &b, eps, act).unwrap();
            let composed = two(super::super::linear(&x, &w, None, None).unwrap());
            let fused = linear_norm_act(&x, &w, None, None, (&g, &b, eps), act, None).unwrap();
            same(fused, composed.clone(), &[&x, &w, &g, &b], 1e-4);
            // the transposed layout
            let wt = w.t().unwrap().contiguous().unwrap();
            let fused = linear_norm_act(&x, &w, Some(&wt), None, (&g, &b, eps), act, None).unwrap();
            same(fused, composed, &[&x, &w, &g, &b], 1e-4);
        }
        // input columns 3..35 one-hot, multiplied over their non-zeros
        let (x, w) = (one_hot_input(8), var(&[6, 37], 25));
        let composed = norm_act(
            &super::super::linear(&x, &w, None, None).unwrap(),
            &g,
            &b,
            eps,
            NormAct::Silu,
        )
        .unwrap();
        let wt = w.t().unwrap().contiguous().unwrap();
        for weight_t in [None, Some(&wt)] {
            let sparse = Some(3..35);
            let fused =
                linear_norm_act(&x, &w, weight_t, None, (&g, &b, eps), NormAct::Silu, sparse);
            same(fused.unwrap(), composed.clone(), &[&x, &w, &g, &b], 1e-4);
        }
    }

    #[test]
    fn linear_norm_act_twice_is_a_frozen_and_a_trained_block() {
        let (x, w) = (one_hot_input(8), var(&[6, 37], 26));
        let (g, b) = (var(&[6], 27), var(&[6], 28));
        let eps = 1e-3;
        let x_trained = x.detach();
        let pair = |(f, t): (Tensor, Tensor)| Tensor::cat(&[f, t], 0).unwrap();
        for (act, sparse) in [(NormAct::Silu, None), (NormAct::Identity, Some(3..35))] {
            let twice =
                linear_norm_act_twice((&x, &x_trained), &w, (&g, &b, eps), act, sparse).unwrap();
            let (wf, gf, bf) = (w.detach(), g.detach(), b.detach());
            let frozen = linear_norm_act(&x, &wf, None, None, (&gf, &bf, eps), act, None).unwrap();
            let trained =
                linear_norm_act(&x_trained, &w, None, None, (&g, &b, eps), act, None).unwrap();
            same(
                pair(twice),
                pair((frozen, trained)),
                &[&x, &w, &g, &b],
                1e-4,
            );
        }
    }
}
