//! `LayerNorm` then SiLU or the identity, in one pass per row forward and one backward.

use super::*;
use std::mem::MaybeUninit;

/// The activation after a normalisation ([`Norm`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NormAct {
    /// `y`.
    Identity,
    /// `y σ(y)`.
    Silu,
}

impl NormAct {
    /// `act(y)`.
    #[inline(always)]
    fn apply(self, y: f32) -> f32 {
        match self {
            NormAct::Identity => y,
            NormAct::Silu => silu(y),
        }
    }

    /// `act'(y)` from `y` and the forward pass's `out = act(y)`, without a second exponential:
    /// for SiLU `σ(y) = out / y` (`½ + y/4` within `10⁻³` of 0, where the division loses its
    /// digits; the series' next term is `y³/48`), and `act'(y) = σ + out (1 − σ)`.
    #[inline(always)]
    fn slope(self, y: f32, out: f32) -> f32 {
        match self {
            NormAct::Identity => 1.0,
            NormAct::Silu => {
                let s = if y.abs() > 1e-3 {
                    out / y
                } else {
                    0.25f32.mul_add(y, 0.5)
                };
                s.mul_add(1.0 - out, out)
            }
        }
    }
}

/// A normalisation's parameters: `act(γ (x − μ)/√(σ² + ε) + β)` over rows of `γ.len()`.
#[derive(Clone, Copy, Debug)]
pub struct Norm<'a> {
    /// `γ`.
    pub gain: &'a [f32],
    /// `β`, of `γ`'s length.
    pub bias: &'a [f32],
    /// `ε`.
    pub eps: f32,
    /// The activation.
    pub act: NormAct,
}

/// Mean and `1/√(σ² + ε)` of a row.
#[inline(always)]
fn row_moments<S: Isa>(x: &[f32], eps: f32) -> (f32, f32) {
    let n = x.len() as f32;
    let mean = lane_sum::<S>(x, x, |v, _| v) / n;
    let var = lane_sum::<S>(x, x, |v, _| (v - mean) * (v - mean)) / n;
    (mean, 1.0 / (var + eps).sqrt())
}

vectorised! {
    /// `out ← act(LayerNorm(x))` over the whole rows (of `gain.len()`) of `x` and `out`, each
    /// value written once (the buffer need not be initialised).
    fn norm_act_rows_uninit(x: &[f32], norm: Norm, out: &mut [MaybeUninit<f32>]) {
        let Norm { gain, bias, eps, act } = norm;
        let d = gain.len();
        if d == 0 {
            return;
        }
        let bias = &bias[..d];
        // exact-length rows: the loops below run without bounds checks, in vector lanes
        for (xr, o) in x.chunks_exact(d).zip(out.chunks_exact_mut(d)) {
            let (mean, rstd) = row_moments::<S>(xr, eps);
            let lanes = o.iter_mut().zip(xr).zip(gain.iter().zip(bias));
            match act {
                NormAct::Identity => {
                    for ((o, &x), (&g, &b)) in lanes {
                        o.write(((x - mean) * rstd).mul_add(g, b));
                    }
                }
                NormAct::Silu => {
                    for ((o, &x), (&g, &b)) in lanes {
                        o.write(NormAct::Silu.apply(((x - mean) * rstd).mul_add(g, b)));
                    }
                }
            }
        }
    }
}

/// `out ← act(LayerNorm(x))` over the whole rows (of `gain.len()`) of `x` and `out`.
pub fn norm_act_rows_into(x: &[f32], norm: Norm, out: &mut [f32]) {
    norm_act_rows_uninit(x, norm, as_uninit(out));
}

vectorised! {
    /// The backward pass of [`norm_act_rows_into`] over the whole rows of `x`, its output `y`
    /// and `dy`: `dx` (each value written once) and `dgb = [dγ, dβ]` (accumulated; empty for a
    /// frozen normalisation, whose parameters' gradients are not computed).
    fn norm_act_rows_bwd_uninit(
        xy: (&[f32], &[f32]),
        norm: Norm,
        dy: &[f32],
        dgb: &mut [f32],
        dx: &mut [MaybeUninit<f32>],
    ) {
        let Norm { gain, bias, eps, act } = norm;
        let (x, y) = xy;
        let d = gain.len();
        if d == 0 {
            return;
        }
        let bias = &bias[..d];
        let frozen = dgb.is_empty();
        let (dgain, dbias) = dgb.split_at_mut(dgb.len().min(d));
        let mut xh = vec![0f32; d];
        let mut dxh = vec![0f32; d];
        let rows = x.chunks_exact(d).zip(dy.chunks_exact(d)).zip(dx.chunks_exact_mut(d));
        for (((xr, dyr), dxr), yr) in rows.zip(y.chunks_exact(d)) {
            let (mean, rstd) = row_moments::<S>(xr, eps);
            // x̂, and the gradient at x̂, γ act'(·) dy, in one pass ([∂γ, ∂β] added unless frozen)
            let lanes = xh.iter_mut().zip(dxh.iter_mut()).zip(xr.iter().zip(dyr.iter().zip(yr)));
            let params = gain.iter().zip(bias);
            match (act, frozen) {
                (NormAct::Identity, true) => {
                    for (((h, o), (&x, (&dy, _))), (&g, _)) in lanes.zip(params) {
                        *h = (x - mean) * rstd;
                        *o = dy * g;
                    }
                }
                (NormAct::Silu, true) => {
                    for (((h, o), (&x, (&dy, &y))), (&g, &b)) in lanes.zip(params) {
                        *h = (x - mean) * rstd;
                        *o = dy * NormAct::Silu.slope(h.mul_add(g, b), y) * g;
                    }
                }
                (act, false) => {
                    let sums = dgain.iter_mut().zip(dbias.iter_mut());
                    for ((((h, o), (&x, (&dy, &y))), (&g, &b)), (dg, db)) in
                        lanes.zip(params).zip(sums)
                    {
                        *h = (x - mean) * rstd;
                        let pre = dy * act.slope(h.mul_add(g, b), y);
                        *dg = pre.mul_add(*h, *dg);
                        *db += pre;
                        *o = pre * g;
                    }
                }
            }
            let m1 = lane_sum::<S>(&dxh, &dxh, |v, _| v) / d as f32;
            let m2 = lane_sum::<S>(&dxh, &xh, |v, w| v * w) / d as f32;
            for ((o, &g), &h) in dxr.iter_mut().zip(&dxh).zip(&xh) {
                o.write(rstd * (-h).mul_add(m2, g - m1));
            }
        }
    }
}

/// The backward pass of [`norm_act_rows_into`] over the whole rows of `x`, its output `y` (of
/// `x`'s length; the activation's slope is read from it) and `dy`: `dx` (overwritten) and
/// `dgb = [dγ, dβ]` (accumulated; empty for a frozen normalisation: not computed).
pub fn norm_act_rows_bwd_into(
    (x, y): (&[f32], &[f32]),
    norm: Norm,
    dy: &[f32],
    dgb: &mut [f32],
    dx: &mut [f32],
) {
    assert_eq!(x.len(), y.len(), "norm_act backward: the output's length");
    let d = norm.gain.len();
    assert!(
        dgb.is_empty() || dgb.len() == 2 * d,
        "norm_act backward: [dγ, dβ] of {d}"
    );
    norm_act_rows_bwd_uninit((x, y), norm, dy, dgb, as_uninit(dx));
}

/// `x` as a buffer that a kernel writing each value once may fill: the same memory, every value
/// of which it overwrites with an initialised one.
fn as_uninit(x: &mut [f32]) -> &mut [MaybeUninit<f32>] {
    // SAFETY: `MaybeUninit<f32>` has the layout of `f32`; the kernels write only initialised
    // values through the view, so `x` stays initialised.
    unsafe { &mut *(x as *mut [f32] as *mut [MaybeUninit<f32>]) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn silu_slope_from_the_output_matches_its_derivative() {
        // near 0 (the series), both signs, and far out where σ or 1 − σ underflows
        let ys = (-2000..=2000)
            .map(|i| i as f32 * 0.05)
            .chain((-40..=40).map(|i| i as f32 * 5e-5))
            .chain([-120.0, -87.5, 87.5, 120.0, 0.0]);
        for y in ys {
            let (s, out) = (1.0 / (1.0 + (-y as f64).exp()), NormAct::Silu.apply(y));
            let exact = s * (1.0 + y as f64 * (1.0 - s));
            let slope = NormAct::Silu.slope(y, out) as f64;
            // single precision of the output, about |y| 6·10⁻⁸ (its digits of 1 − σ are what
            // the slope's out (1 − σ) reads for large y; the exponential form loses as many)
            assert!(
                (slope - exact).abs() <= 3e-7 * y.abs().max(1.0) as f64,
                "SiLU'({y}) from the output {out}: {slope}, exactly {exact}"
            );
        }
    }
}
