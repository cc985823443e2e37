//! `LayerNorm` then SiLU or the identity as a candle op, around [`norm_act_rows_into`].

use super::*;
use ctxrace_nn::kernels::{norm_act_rows_bwd_into, norm_act_rows_into, Norm, NormAct};

struct NormActOp {
    eps: f32,
    act: NormAct,
}

/// `act(LayerNorm(x))` of the whole rows (of `γ.len()`) of `x`, in a new buffer.
pub(super) fn norm_act_rows(x: &[f32], norm: Norm) -> Vec<f32> {
    let d = norm.gain.len();
    let mut out = vec![0f32; x.len() / d.max(1) * d];
    norm_act_rows_into(x, norm, &mut out);
    out
}

/// [`norm_act_rows_bwd_into`] with `dx` in a new buffer, over the whole rows of `x` and `dy`.
pub(super) fn norm_act_rows_bwd(
    (x, y): (&[f32], &[f32]),
    norm: Norm,
    dy: &[f32],
    dgb: &mut [f32],
) -> Vec<f32> {
    let d = norm.gain.len();
    let mut dx = vec![0f32; (x.len() / d.max(1)).min(dy.len() / d.max(1)) * d];
    norm_act_rows_bwd_into((x, y), norm, dy, dgb, &mut dx);
    dx
}

impl NormActOp {
    /// The normalisation with gain `g` and bias `b`.
    fn on<'a>(&self, g: &'a [f32], b: &'a [f32]) -> Norm<'a> {
        Norm {
            gain: g,
            bias: b,
            eps: self.eps,
            act: self.act,
        }
    }
}

impl CustomOp3 for NormActOp {
    fn name(&self) -> &'static str {
        "ctxrace-norm-act"
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
        let (x, g, b) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?, cpu_slice(s3, l3)?);
        let d = g.len();
        if d == 0 || x.len() % d != 0 || b.len() != d {
            bail!("norm_act: input {:?} for a gain of {d}", l1.shape());
        }
        let out = norm_act_rows(x, self.on(g, b));
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        gain: &Tensor,
        bias: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = gain.elem_count();
        let want_params = wants_grad(gain) || wants_grad(bias);
        let (dx, sums) = read(x, |x| {
            read(res, |y| {
                read(gain, |g| {
                    read(bias, |b| {
                        read(grad, |dy| {
                            // a frozen normalisation's (empty): not computed
                            let mut dgb = vec![0f32; if want_params { 2 * d } else { 0 }];
                            let dx = norm_act_rows_bwd((x, y), self.on(g, b), dy, &mut dgb);
                            Ok((dx, dgb))
                        })
                    })
                })
            })
        })?;
        let dx = wants_grad(x)
            .then(|| Tensor::from_vec(dx, x.shape(), x.device()))
            .transpose()?;
        if !want_params {
            return Ok((dx, None, None));
        }
        let dg = Tensor::from_slice(&sums[..d], d, x.device())?;
        let db = Tensor::from_slice(&sums[d..], d, x.device())?;
        Ok((
            dx,
            wants_grad(gain).then_some(dg),
            wants_grad(bias).then_some(db),
        ))
    }
}

/// `act(γ (x − μ)/√(σ² + ε) + β)` over the last dimension of `x`, with `gain` γ and `bias` β of
/// that size.
pub fn norm_act(
    x: &Tensor,
    gain: &Tensor,
    bias: &Tensor,
    eps: f64,
    act: NormAct,
) -> Result<Tensor> {
    x.contiguous()?.apply_op3(
        gain,
        bias,
        NormActOp {
            eps: eps as f32,
            act,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::*;
    use ctxrace_nn::kernels::LANES;

    #[test]
    fn norm_act_matches_the_composed_layer_norm() {
        // rows shorter than the kernels' lanes, and rows of two lanes' chunks and a tail
        for width in [8, 2 * LANES + 8] {
            matches_the_composed_layer_norm(width);
        }
    }

    fn matches_the_composed_layer_norm(width: usize) {
        let (x, g, b) = (var(&[6, width], 4), var(&[width], 5), var(&[width], 6));
        let eps = 1e-3;
        let centred = x
            .broadcast_sub(&x.mean_keepdim(D::Minus1).unwrap())
            .unwrap();
        let var_ = centred.sqr().unwrap().mean_keepdim(D::Minus1).unwrap();
        let ln = centred
            .broadcast_div(&(var_ + eps).unwrap().sqrt().unwrap())
            .unwrap()
            .broadcast_mul(&g)
            .unwrap()
            .broadcast_add(&b)
            .unwrap();
        let fused = |act| norm_act(&x, &g, &b, eps, act).unwrap();
        same(fused(NormAct::Identity), ln.clone(), &[&x, &g, &b], 1e-4);
        let silu = candle_nn::ops::silu(&ln).unwrap();
        same(fused(NormAct::Silu), silu.clone(), &[&x, &g, &b], 1e-4);
        // frozen: γ and β constants, the input's gradient only
        let (gc, bc) = (g.as_tensor().detach(), b.as_tensor().detach());
        for (act, composed) in [(NormAct::Identity, ln), (NormAct::Silu, silu)] {
            let frozen = norm_act(&x, &gc, &bc, eps, act).unwrap();
            same(frozen, composed, &[&x], 1e-4);
        }
    }
}
