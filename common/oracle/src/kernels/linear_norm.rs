//! `act(LayerNorm(x Wᵀ))` as one operation: the block of every DreamerV3 layer.
//!
//! As two operations the product `p = x Wᵀ` is a node of candle's graph, and the backward pass
//! gives it a zeroed gradient buffer that the normalisation's gradient is added into before the
//! product reads it. Here the product's values stay inside the operation (kept for the backward
//! pass), and `∂p` goes from the normalisation's backward straight into the product's
//! (`dx = ∂p W`, `dW = ∂pᵀ x`).

use super::linear::{product, Linear};
use super::norm_act::{norm_act_rows, norm_act_rows_bwd};
use super::*;
use ctxrace_nn::kernels::{Norm, NormAct};
use std::sync::{Mutex, PoisonError};

struct LinearNormAct {
    linear: Linear,
    eps: f32,
    act: NormAct,
    /// `x Wᵀ` of the forward pass, kept for the backward pass.
    product: Mutex<Vec<f32>>,
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

/// `act(LayerNorm(x Wᵀ))` for `x` `[N, in]`, `weight` `[out, in]` and the normalisation's `(gain, bias, ε)`, each of `out`: [`super::linear`] then [`super::norm_act`]
/// in one operation; the input columns `sparse_inputs` as in [`super::linear`].
pub fn linear_norm_act(
    x: &Tensor,
    weight: &Tensor,
    (gain, bias, eps): (&Tensor, &Tensor, f64),
    act: NormAct,
    sparse_inputs: Option<std::ops::Range<usize>>,
) -> Result<Tensor> {
    let op = LinearNormAct {
        linear: product(weight, sparse_inputs),
        eps: eps as f32,
        act,
        product: Mutex::default(),
    };
    op.apply(x, weight, &Tensor::cat(&[gain, bias], 0)?)
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
            let fused = linear_norm_act(&x, &w, (&g, &b, eps), act, None).unwrap();
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
        let fused = linear_norm_act(&x, &w, (&g, &b, eps), NormAct::Silu, Some(3..35));
        same(fused.unwrap(), composed, &[&x, &w, &g, &b], 1e-4);
    }
}
