//! Fused CPU kernels with their own backward passes, for the layers that dominate a DreamerV3
//! training step.
//!
//! candle builds these from many small tensor operations, each allocating its result and, in the
//! backward pass, a zeroed gradient to add into; on a training step at the paper's batch that
//! overhead took four times the matrix products. Each kernel here is one pass over rows of the
//! input forward and one backward, on the calling thread (the learner parallelises over the
//! batch instead, see [`super::set_threads`]), and computes
//! the gradient of an argument only when it is tracked ([`Tensor::track_op`]): a detached weight,
//! as in a frozen copy of a network, costs nothing in the backward pass.
//!
//! - [`linear`]: `y = x Wᵀ (+ b)`.
//! - [`norm_act`]: `LayerNorm` then SiLU or the identity:
//!   `x̂ = (x − μ)/√(σ² + ε)`, `y = act(γ x̂ + β)`; backward
//!   `dx = (dx̂ − mean(dx̂) − x̂ mean(dx̂ x̂)) / √(σ² + ε)` with `dx̂ = γ act'(·) dy`.
//! - [`gru_gates`]: DreamerV3's GRU update from normalised gates `[r, ĉ, u]` and the state `h`:
//!   `h' = σ(u − 1) tanh(σ(r) ĉ) + (1 − σ(u − 1)) h`.
//! - [`straight_through_sample`]: a one-hot Gumbel-max sample of the unimix categorical
//!   `p = (1 − η) softmax(l) + η / C` whose gradient is that of `p` (`z = onehot + p − sg p`).
//! - [`categorical_kl`]: `KL(p_a ‖ p_b)` of two unimix categoricals, summed over the variables.
//! - [`twohot_decode`]: `symexp(Σ_k softmax(l)_k b_k)`.
//! - [`soft_cross_entropy`]: `−Σ_k t_k log softmax(l)_k` against fixed targets `t`.
//!
//! Every kernel is checked against the composed candle operations, values and gradients, in the
//! tests below.

use candle_core::{
    bail, CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Result, Shape, Storage, Tensor,
};

/// The contiguous `f32` values of a CPU storage under `layout`.
fn cpu_slice<'a>(storage: &'a CpuStorage, layout: &Layout) -> Result<&'a [f32]> {
    let data = storage.as_slice::<f32>()?;
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => bail!("fused kernel: a non-contiguous input (call .contiguous() first)"),
    }
}

/// Runs `f` on the contiguous `f32` values of `t`.
fn read<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> Result<R>) -> Result<R> {
    let t = t.contiguous()?;
    let (storage, layout) = t.storage_and_layout();
    let Storage::Cpu(cpu) = &*storage else {
        bail!("fused kernels run on the CPU only")
    };
    f(cpu_slice(cpu, layout)?)
}

/// Defines a function whose body is compiled three times, for AVX-512, for AVX2 with FMA and for
/// the baseline, and runs the widest the processor has (checked at run time). The body and the
/// `#[inline(always)]` helpers it calls vectorise inside each copy.
macro_rules! vectorised {
    ($(#[$doc:meta])* fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$doc])*
        #[allow(clippy::too_many_arguments)]
        fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            #[allow(clippy::too_many_arguments)]
            fn body($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn v4($($arg: $ty),*) $(-> $ret)? { body($($arg),*) }
                #[target_feature(enable = "avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn v3($($arg: $ty),*) $(-> $ret)? { body($($arg),*) }
                if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512vl") {
                    // SAFETY: the processor has the features v4 is compiled for.
                    return unsafe { v4($($arg),*) };
                }
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    // SAFETY: the processor has the features v3 is compiled for.
                    return unsafe { v3($($arg),*) };
                }
            }
            body($($arg),*)
        }
    };
}

/// Whether the backward pass needs the gradient of `t`.
fn wants_grad(t: &Tensor) -> bool {
    t.track_op()
}

/// `eˣ` to about one part in 10⁷, branch-free so that loops over it vectorise:
/// `eˣ = 2ᵏ eʳ` with `k = ⌊x log₂e + ½⌋`, `|r| ≤ ln 2 / 2`, `eʳ` by its Taylor series to `r⁶`
/// (remainder below `1.2·10⁻⁷`), `2ᵏ` built in the exponent bits. Inputs are clamped to
/// `[−87, 88]`, where `f32` neither underflows to subnormals nor overflows.
#[inline(always)]
fn exp(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    let k = (x * std::f32::consts::LOG2_E + 0.5).floor();
    // ln 2 split in two so that k · ln 2 is exact to f32 precision
    let r = (x - k * 0.693_359_4) + k * 2.121_944_4e-4;
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    p * f32::from_bits(((k as i32 + 127) << 23) as u32)
}

/// `1 / (1 + e⁻ˣ)`.
#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + exp(-x))
}

/// `tanh x = 2 σ(2x) − 1`.
#[inline(always)]
fn tanh(x: f32) -> f32 {
    2.0 * sigmoid(2.0 * x) - 1.0
}

/// Softmax of `l` into `out`.
#[inline(always)]
fn softmax_into(l: &[f32], out: &mut [f32]) {
    let max = l.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mut sum = 0.0;
    for (o, &v) in out.iter_mut().zip(l) {
        *o = exp(v - max);
        sum += *o;
    }
    let inv = 1.0 / sum;
    out.iter_mut().for_each(|o| *o *= inv);
}

/// `out ← ∂/∂l` of a function of `p = (1 − η) softmax(l) + η/C` given `dp` and `s = softmax(l)`:
/// `(1 − η) s_k (dp_k − Σ_j s_j dp_j)`.
#[inline(always)]
fn unimix_softmax_backward(s: &[f32], dp: &[f32], keep: f32, out: &mut [f32]) {
    let dot: f32 = s.iter().zip(dp).map(|(a, b)| a * b).sum();
    for ((o, &sk), &dk) in out.iter_mut().zip(s).zip(dp) {
        *o = keep * sk * (dk - dot);
    }
}

fn dims2(t: &Tensor) -> Result<(usize, usize)> {
    match t.dims() {
        [n, d] => Ok((*n, *d)),
        other => bail!("fused kernel: expected a matrix, got shape {other:?}"),
    }
}

// ---------------------------------------------------------------- linear

/// `y = x Wᵀ (+ b)` (see [`linear`]).
struct Linear;

/// A matrix operand of [`matmul`]: its values and the strides of its rows and columns.
#[derive(Clone, Copy)]
struct Operand<'a> {
    data: &'a [f32],
    row_stride: usize,
    col_stride: usize,
}

impl<'a> Operand<'a> {
    /// A row-major `[rows, cols]` matrix.
    fn rows(data: &'a [f32], cols: usize) -> Self {
        Self {
            data,
            row_stride: cols,
            col_stride: 1,
        }
    }

    /// The transpose of a row-major `[rows, cols]` matrix.
    fn transposed(data: &'a [f32], cols: usize) -> Self {
        Self {
            data,
            row_stride: 1,
            col_stride: cols,
        }
    }
}

/// `A B` (`[m, k]` times `[k, n]`) as a new row-major `[m, n]`; with `init` (`m·n` values) the
/// product is added to it. gemm writes every value, so the buffer is not zeroed first.
fn matmul(
    m: usize,
    n: usize,
    k: usize,
    a: Operand,
    b: Operand,
    init: Option<Vec<f32>>,
) -> Vec<f32> {
    let accumulate = init.is_some();
    let mut dst = init.unwrap_or_else(|| Vec::with_capacity(m * n));
    if m == 0 || n == 0 || k == 0 {
        dst.resize(m * n, 0.0);
        return dst;
    }
    // the callers' shape checks guarantee these; the unsafe call below relies on them
    assert!(a.data.len() > (m - 1) * a.row_stride + (k - 1) * a.col_stride);
    assert!(b.data.len() > (k - 1) * b.row_stride + (n - 1) * b.col_stride);
    // SAFETY: `a` and `b` hold the m×k and k×n values their strides address (asserted above);
    // `dst` has room for m×n values, which
    // gemm writes (reading them first only when `accumulate`, where they are initialised)
    // before `set_len` exposes them.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.data.as_ptr(),
            a.col_stride as isize,
            a.row_stride as isize,
            b.data.as_ptr(),
            b.col_stride as isize,
            b.row_stride as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
        dst.set_len(m * n);
    }
    dst
}

fn linear_fwd(
    x: (&CpuStorage, &Layout),
    w: (&CpuStorage, &Layout),
    b: Option<(&CpuStorage, &Layout)>,
) -> Result<(CpuStorage, Shape)> {
    let (n, k) = x.1.shape().dims2()?;
    let (m, k2) = w.1.shape().dims2()?;
    if k != k2 {
        bail!("linear: input width {k} but weight [{m}, {k2}]");
    }
    let (x, w) = (cpu_slice(x.0, x.1)?, cpu_slice(w.0, w.1)?);
    let init = match b {
        Some((s, l)) => {
            let b = cpu_slice(s, l)?;
            if b.len() != m {
                bail!("linear: bias of {} for {m} outputs", b.len());
            }
            Some(b.repeat(n))
        }
        None => None,
    };
    let y = matmul(
        n,
        m,
        k,
        Operand::rows(x, k),
        Operand::transposed(w, k),
        init,
    );
    Ok((CpuStorage::F32(y), Shape::from((n, m))))
}

/// The gradients of `x` `[N, in]` and `W` `[out, in]` for `y = x Wᵀ` (each if wanted):
/// `dx = g W`, `dW = gᵀ x`.
fn linear_bwd(x: &Tensor, w: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
    let (want_x, want_w) = (wants_grad(x), wants_grad(w));
    let (rows, input) = dims2(x)?;
    let (output, _) = dims2(w)?;
    let (dx, dw) = read(grad, |g| {
        let dx = want_x.then(|| {
            read(w, |wv| {
                let (g, wv) = (Operand::rows(g, output), Operand::rows(wv, input));
                Ok(matmul(rows, input, output, g, wv, None))
            })
        });
        let dw = want_w.then(|| {
            read(x, |xv| {
                let (gt, xv) = (Operand::transposed(g, output), Operand::rows(xv, input));
                Ok(matmul(output, input, rows, gt, xv, None))
            })
        });
        Ok((dx.transpose()?, dw.transpose()?))
    })?;
    Ok((
        dx.map(|v| Tensor::from_vec(v, x.shape(), x.device()))
            .transpose()?,
        dw.map(|v| Tensor::from_vec(v, w.shape(), w.device()))
            .transpose()?,
    ))
}

impl CustomOp2 for Linear {
    fn name(&self) -> &'static str {
        "ctxrace-linear"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        linear_fwd((s1, l1), (s2, l2), None)
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        linear_bwd(x, w, grad)
    }
}

impl CustomOp3 for Linear {
    fn name(&self) -> &'static str {
        "ctxrace-linear-bias"
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
        linear_fwd((s1, l1), (s2, l2), Some((s3, l3)))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (dx, dw) = linear_bwd(x, w, grad)?;
        let db = if wants_grad(b) {
            Some(grad.sum(0)?)
        } else {
            None
        };
        Ok((dx, dw, db))
    }
}

/// `x Wᵀ + b` for `x` `[N, in]`, `weight` `[out, in]` and an optional `bias` `[out]`.
pub fn linear(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    let x = x.contiguous()?;
    match bias {
        Some(b) => x.apply_op3(weight, b, Linear),
        None => x.apply_op2(weight, Linear),
    }
}

// ---------------------------------------------------------------- LayerNorm + activation

/// The activation after a [`norm_act`] normalisation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NormAct {
    /// `y`.
    Identity,
    /// `y σ(y)`.
    Silu,
}

impl NormAct {
    /// `(act(y), act'(y))`.
    #[inline(always)]
    fn eval(self, y: f32) -> (f32, f32) {
        match self {
            NormAct::Identity => (y, 1.0),
            NormAct::Silu => {
                let s = sigmoid(y);
                (y * s, s * (1.0 + y * (1.0 - s)))
            }
        }
    }
}

struct NormActOp {
    eps: f32,
    act: NormAct,
}

/// Lanes of the sums below: independent partial sums let them vectorise (a single running sum
/// of floats cannot be reordered by the compiler).
const LANES: usize = 16;

/// `Σ_i f(a_i, b_i)` over two slices of one length, in [`LANES`] partial sums.
#[inline(always)]
fn lane_sum(a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> f32) -> f32 {
    let mut acc = [0f32; LANES];
    let (ca, cb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (xa, xb) in ca.zip(cb) {
        for l in 0..LANES {
            acc[l] += f(xa[l], xb[l]);
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(&x, &y)| f(x, y)).sum();
    acc.iter().sum::<f32>() + tail
}

/// Mean and `1/√(σ² + ε)` of a row.
#[inline(always)]
fn row_moments(x: &[f32], eps: f32) -> (f32, f32) {
    let n = x.len() as f32;
    let mean = lane_sum(x, x, |v, _| v) / n;
    let var = lane_sum(x, x, |v, _| (v - mean) * (v - mean)) / n;
    (mean, 1.0 / (var + eps).sqrt())
}

vectorised! {
    /// `out` (whole rows of `gain.len()`) ← `act(LayerNorm(x))` of the rows of `x` from the first.
    fn norm_act_rows(x: &[f32], gain: &[f32], bias: &[f32], out: &mut [f32], eps: f32, act: NormAct) {
        let d = gain.len();
        for (xr, o) in x.chunks(d).zip(out.chunks_mut(d)) {
            let (mean, rstd) = row_moments(xr, eps);
            match act {
                NormAct::Identity => {
                    for j in 0..d {
                        o[j] = (xr[j] - mean) * rstd * gain[j] + bias[j];
                    }
                }
                NormAct::Silu => {
                    for j in 0..d {
                        o[j] = NormAct::Silu.eval((xr[j] - mean) * rstd * gain[j] + bias[j]).0;
                    }
                }
            }
        }
    }
}

vectorised! {
    /// The backward pass of [`norm_act_rows`] over the rows of `dx`: `dx`, and
    /// `dgb = [dγ, dβ]` accumulated.
    fn norm_act_rows_bwd(
        x: &[f32],
        gain: &[f32],
        bias: &[f32],
        dy: &[f32],
        dx: &mut [f32],
        dgb: &mut [f32],
        eps: f32,
        act: NormAct,
    ) {
        let d = gain.len();
        let (dgain, dbias) = dgb.split_at_mut(d);
        let mut xh = vec![0f32; d];
        let mut dxh = vec![0f32; d];
        for ((xr, dyr), dxr) in x.chunks(d).zip(dy.chunks(d)).zip(dx.chunks_mut(d)) {
            let (mean, rstd) = row_moments(xr, eps);
            for j in 0..d {
                xh[j] = (xr[j] - mean) * rstd;
            }
            // dxh ← the gradient at the activation's input
            match act {
                NormAct::Identity => dxh.copy_from_slice(dyr),
                NormAct::Silu => {
                    for j in 0..d {
                        dxh[j] = dyr[j] * NormAct::Silu.eval(xh[j] * gain[j] + bias[j]).1;
                    }
                }
            }
            for j in 0..d {
                dgain[j] += dxh[j] * xh[j];
                dbias[j] += dxh[j];
                dxh[j] *= gain[j];
            }
            let m1 = lane_sum(&dxh, &dxh, |v, _| v) / d as f32;
            let m2 = lane_sum(&dxh, &xh, |v, w| v * w) / d as f32;
            for j in 0..d {
                dxr[j] = rstd * (dxh[j] - m1 - xh[j] * m2);
            }
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
        let mut out = vec![0f32; x.len()];
        norm_act_rows(x, g, b, &mut out, self.eps, self.act);
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        gain: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = gain.elem_count();
        let want_params = wants_grad(gain) || wants_grad(bias);
        let (dx, sums) = read(x, |x| {
            read(gain, |g| {
                read(bias, |b| {
                    read(grad, |dy| {
                        let mut dx = vec![0f32; x.len()];
                        let mut dgb = vec![0f32; 2 * d];
                        norm_act_rows_bwd(x, g, b, dy, &mut dx, &mut dgb, self.eps, self.act);
                        Ok((dx, dgb))
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

// ---------------------------------------------------------------- GRU gates

struct GruGates;

/// The gate values of one element: `(r, c, u)` with `c = tanh(r ĉ)` and `u = σ(û − 1)`.
#[inline(always)]
fn gates(pr: f32, pc: f32, pu: f32) -> (f32, f32, f32) {
    let r = sigmoid(pr);
    (r, tanh(r * pc), sigmoid(pu - 1.0))
}

vectorised! {
    /// `out` (whole rows of `size`) ← the GRU update of the gate rows `p` and states `h`.
    fn gru_rows(p: &[f32], h: &[f32], out: &mut [f32], size: usize) {
        for ((pr, hr), o) in p.chunks(3 * size).zip(h.chunks(size)).zip(out.chunks_mut(size)) {
            for j in 0..size {
                let (_, c, u) = gates(pr[j], pr[size + j], pr[2 * size + j]);
                o[j] = u * c + (1.0 - u) * hr[j];
            }
        }
    }
}

vectorised! {
    /// The backward pass of [`gru_rows`] over the rows of `dp` (`3 size` each) and `dh`.
    fn gru_rows_bwd(p: &[f32], h: &[f32], g: &[f32], dp: &mut [f32], dh: &mut [f32], size: usize) {
        let rows = p.chunks(3 * size).zip(h.chunks(size)).zip(g.chunks(size));
        for (((pr, hr), gr), (dpr, dhr)) in rows.zip(dp.chunks_mut(3 * size).zip(dh.chunks_mut(size))) {
            for j in 0..size {
                let (pc, gj) = (pr[size + j], gr[j]);
                let (rg, c, u) = gates(pr[j], pc, pr[2 * size + j]);
                let dpre_c = gj * u * (1.0 - c * c);
                dpr[j] = dpre_c * pc * rg * (1.0 - rg);
                dpr[size + j] = dpre_c * rg;
                dpr[2 * size + j] = gj * (c - hr[j]) * u * (1.0 - u);
                dhr[j] = gj * (1.0 - u);
            }
        }
    }
}

impl CustomOp2 for GruGates {
    fn name(&self) -> &'static str {
        "ctxrace-gru-gates"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (p, h) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?);
        let (rows, size) = l2.shape().dims2()?;
        if p.len() != 3 * rows * size {
            bail!(
                "gru_gates: gates {:?} for a state {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let mut out = vec![0f32; h.len()];
        gru_rows(p, h, &mut out, size);
        Ok((CpuStorage::F32(out), l2.shape().clone()))
    }

    fn bwd(
        &self,
        parts: &Tensor,
        h: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (rows, size) = dims2(h)?;
        let (dp, dh) = read(parts, |p| {
            read(h, |hv| {
                read(grad, |g| {
                    let mut dp = vec![0f32; 3 * rows * size];
                    let mut dh = vec![0f32; rows * size];
                    gru_rows_bwd(p, hv, g, &mut dp, &mut dh, size);
                    Ok((dp, dh))
                })
            })
        })?;
        Ok((
            wants_grad(parts)
                .then(|| Tensor::from_vec(dp, parts.shape(), parts.device()))
                .transpose()?,
            wants_grad(h)
                .then(|| Tensor::from_vec(dh, h.shape(), h.device()))
                .transpose()?,
        ))
    }
}

/// DreamerV3's GRU update `σ(u − 1) tanh(σ(r) ĉ) + (1 − σ(u − 1)) h` from gates `[N, 3S]`
/// (`[r, ĉ, u]`, already normalised) and the state `h` `[N, S]`.
pub fn gru_gates(parts: &Tensor, h: &Tensor) -> Result<Tensor> {
    parts.contiguous()?.apply_op2(&h.contiguous()?, GruGates)
}

// ---------------------------------------------------------------- categorical latents

/// A unimix categorical over `classes`: `p = (1 − unimix) softmax(l) + unimix / classes`.
#[derive(Clone, Copy, Debug)]
struct Unimix {
    classes: usize,
    unimix: f32,
}

impl Unimix {
    /// `(s, p)`: the softmax of `l` and the mixed probabilities.
    #[inline(always)]
    fn probs(&self, l: &[f32], s: &mut [f32], p: &mut [f32]) {
        softmax_into(l, s);
        let floor = self.unimix / self.classes as f32;
        for (pk, &sk) in p.iter_mut().zip(s.iter()) {
            *pk = (1.0 - self.unimix) * sk + floor;
        }
    }
}

struct StraightThrough(Unimix);

impl CustomOp2 for StraightThrough {
    fn name(&self) -> &'static str {
        "ctxrace-straight-through"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (l, u) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?);
        let c = self.0.classes;
        if l.len() != u.len() || l.len() % c != 0 {
            bail!(
                "straight_through_sample: logits {:?}, uniforms {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let mut out = vec![0f32; l.len()];
        let (mut s, mut p) = (vec![0f32; c], vec![0f32; c]);
        for (i, o) in out.chunks_mut(c).enumerate() {
            let at = i * c;
            self.0.probs(&l[at..at + c], &mut s, &mut p);
            let mut best = (0, f32::NEG_INFINITY);
            for k in 0..c {
                // Gumbel-max: argmax of ln p + g with g = −ln(−ln U), i.e. of p / (−ln U)
                let score = p[k] / -u[at + k].ln();
                if score > best.1 {
                    best = (k, score);
                }
            }
            o[best.0] = 1.0;
        }
        let rows = l1.shape().dims()[0];
        Ok((CpuStorage::F32(out), Shape::from((rows, l.len() / rows))))
    }

    fn bwd(
        &self,
        logits: &Tensor,
        _uniform: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        if !wants_grad(logits) {
            return Ok((None, None));
        }
        let c = self.0.classes;
        let dl = read(logits, |l| {
            read(grad, |g| {
                let mut dl = vec![0f32; l.len()];
                let (mut s, mut p) = (vec![0f32; c], vec![0f32; c]);
                for (i, d) in dl.chunks_mut(c).enumerate() {
                    let at = i * c;
                    self.0.probs(&l[at..at + c], &mut s, &mut p);
                    unimix_softmax_backward(&s, &g[at..at + c], 1.0 - self.0.unimix, d);
                }
                Ok(dl)
            })
        })?;
        Ok((
            Some(Tensor::from_vec(dl, logits.shape(), logits.device())?),
            None,
        ))
    }
}

/// A straight-through one-hot sample `[N, S·C]` of the unimix categoricals with logits
/// `[N, S, C]`, drawn by Gumbel-max from uniforms `U ∈ (0, 1)` of the same shape: forward the
/// exact one-hot, backward the gradient of the probabilities.
pub fn straight_through_sample(logits: &Tensor, uniform: &Tensor, unimix: f64) -> Result<Tensor> {
    let classes = *logits.dims().last().unwrap_or(&0);
    if logits.rank() != 3 || classes == 0 {
        bail!(
            "straight_through_sample: logits [N, S, C], got {:?}",
            logits.dims()
        );
    }
    let op = StraightThrough(Unimix {
        classes,
        unimix: unimix as f32,
    });
    logits.contiguous()?.apply_op2(&uniform.contiguous()?, op)
}

struct Kl(Unimix);

impl CustomOp2 for Kl {
    fn name(&self) -> &'static str {
        "ctxrace-categorical-kl"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (la, lb) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?);
        if la.len() != lb.len() {
            bail!(
                "categorical_kl: logits {:?} and {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let rows = l1.shape().dims()[0];
        let (c, per_row) = (self.0.classes, la.len() / rows.max(1));
        let mut out = vec![0f32; rows];
        let mut buf = vec![0f32; 4 * c];
        for (i, o) in out.iter_mut().enumerate() {
            for v in (i * per_row..(i + 1) * per_row).step_by(c) {
                let (sa, rest) = buf.split_at_mut(c);
                let (pa, rest) = rest.split_at_mut(c);
                let (sb, pb) = rest.split_at_mut(c);
                self.0.probs(&la[v..v + c], sa, pa);
                self.0.probs(&lb[v..v + c], sb, pb);
                *o += pa
                    .iter()
                    .zip(pb.iter())
                    .map(|(a, b)| a * (a.ln() - b.ln()))
                    .sum::<f32>();
            }
        }
        Ok((CpuStorage::F32(out), Shape::from(rows)))
    }

    fn bwd(
        &self,
        la_t: &Tensor,
        lb_t: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (want_a, want_b) = (wants_grad(la_t), wants_grad(lb_t));
        if !want_a && !want_b {
            return Ok((None, None));
        }
        let c = self.0.classes;
        let keep = 1.0 - self.0.unimix;
        let (da, db) = read(la_t, |la| {
            read(lb_t, |lb| {
                read(grad, |g| {
                    let per_row = la.len() / g.len().max(1);
                    // per variable: its c gradients of a, then its c of b
                    let mut both = vec![0f32; 2 * la.len()];
                    let mut buf = vec![0f32; 5 * c];
                    for (i, out) in both.chunks_mut(2 * c).enumerate() {
                        let v = i * c;
                        let gi = g[v / per_row];
                        let (sa, rest) = buf.split_at_mut(c);
                        let (pa, rest) = rest.split_at_mut(c);
                        let (sb, rest) = rest.split_at_mut(c);
                        let (pb, dp) = rest.split_at_mut(c);
                        self.0.probs(&la[v..v + c], sa, pa);
                        self.0.probs(&lb[v..v + c], sb, pb);
                        let (da, db) = out.split_at_mut(c);
                        if want_a {
                            for k in 0..c {
                                dp[k] = gi * (pa[k].ln() - pb[k].ln() + 1.0);
                            }
                            unimix_softmax_backward(sa, dp, keep, da);
                        }
                        if want_b {
                            for k in 0..c {
                                dp[k] = -gi * pa[k] / pb[k];
                            }
                            unimix_softmax_backward(sb, dp, keep, db);
                        }
                    }
                    let (da, db) = both.chunks(2 * c).map(|v| v.split_at(c)).fold(
                        (Vec::with_capacity(la.len()), Vec::with_capacity(la.len())),
                        |(mut da, mut db), (a, b)| {
                            da.extend_from_slice(a);
                            db.extend_from_slice(b);
                            (da, db)
                        },
                    );
                    Ok((da, db))
                })
            })
        })?;
        let dev = la_t.device();
        Ok((
            want_a
                .then(|| Tensor::from_vec(da, la_t.shape(), dev))
                .transpose()?,
            want_b
                .then(|| Tensor::from_vec(db, lb_t.shape(), dev))
                .transpose()?,
        ))
    }
}

/// `KL(p_a ‖ p_b)` `[N]` of the unimix categoricals with logits `[N, S, C]`, summed over the
/// `S` variables.
pub fn categorical_kl(logits_a: &Tensor, logits_b: &Tensor, unimix: f64) -> Result<Tensor> {
    let classes = *logits_a.dims().last().unwrap_or(&0);
    if logits_a.rank() != 3 || classes == 0 || logits_a.dims() != logits_b.dims() {
        bail!(
            "categorical_kl: logits [N, S, C] of one shape, got {:?} and {:?}",
            logits_a.dims(),
            logits_b.dims()
        );
    }
    let op = Kl(Unimix {
        classes,
        unimix: unimix as f32,
    });
    logits_a
        .contiguous()?
        .apply_op2(&logits_b.contiguous()?, op)
}

// ---------------------------------------------------------------- two-hot heads

struct TwohotDecode {
    bins: Vec<f32>,
}

impl CustomOp1 for TwohotDecode {
    fn name(&self) -> &'static str {
        "ctxrace-twohot-decode"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = cpu_slice(s, l)?;
        let k = self.bins.len();
        let mut out = vec![0f32; x.len() / k];
        let mut p = vec![0f32; k];
        for (i, o) in out.iter_mut().enumerate() {
            softmax_into(&x[i * k..(i + 1) * k], &mut p);
            let m: f32 = p.iter().zip(&self.bins).map(|(a, b)| a * b).sum();
            *o = m.signum() * (m.abs().exp() - 1.0);
        }
        let dims = l.shape().dims();
        Ok((CpuStorage::F32(out), Shape::from(&dims[..dims.len() - 1])))
    }

    fn bwd(&self, logits: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let k = self.bins.len();
        let dl = read(logits, |x| {
            read(grad, |g| {
                let mut dl = vec![0f32; x.len()];
                let mut p = vec![0f32; k];
                for (i, d) in dl.chunks_mut(k).enumerate() {
                    let r = i;
                    softmax_into(&x[r * k..(r + 1) * k], &mut p);
                    let m: f32 = p.iter().zip(&self.bins).map(|(a, b)| a * b).sum();
                    let dm = g[r] * m.abs().exp();
                    for j in 0..k {
                        d[j] = p[j] * (self.bins[j] - m) * dm;
                    }
                }
                Ok(dl)
            })
        })?;
        Ok(Some(Tensor::from_vec(dl, logits.shape(), logits.device())?))
    }
}

/// `symexp(Σ_k softmax(l)_k b_k)` over the last dimension of `logits` `[…, K]` for bins `b`.
pub fn twohot_decode(logits: &Tensor, bins: &[f32]) -> Result<Tensor> {
    if logits.dims().last() != Some(&bins.len()) {
        bail!(
            "twohot_decode: logits {:?} for {} bins",
            logits.dims(),
            bins.len()
        );
    }
    logits.contiguous()?.apply_op1(TwohotDecode {
        bins: bins.to_vec(),
    })
}

struct SoftCrossEntropy;

impl CustomOp2 for SoftCrossEntropy {
    fn name(&self) -> &'static str {
        "ctxrace-soft-cross-entropy"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (l, t) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?);
        let (rows, k) = l1.shape().dims2()?;
        if l.len() != t.len() {
            bail!(
                "soft_cross_entropy: logits {:?}, targets {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let mut out = vec![0f32; rows];
        for (i, o) in out.iter_mut().enumerate() {
            let at = i * k;
            let (lr, tr) = (&l[at..at + k], &t[at..at + k]);
            let max = lr.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let lse = max + lr.iter().map(|&v| exp(v - max)).sum::<f32>().ln();
            *o = tr.iter().zip(lr).map(|(tk, lk)| tk * (lse - lk)).sum();
        }
        Ok((CpuStorage::F32(out), Shape::from(rows)))
    }

    fn bwd(
        &self,
        logits: &Tensor,
        target: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        if wants_grad(target) {
            bail!("soft_cross_entropy: the targets must be detached");
        }
        let (_, k) = dims2(logits)?;
        let dl = read(logits, |l| {
            read(target, |t| {
                read(grad, |g| {
                    let mut dl = vec![0f32; l.len()];
                    let mut p = vec![0f32; k];
                    for (i, d) in dl.chunks_mut(k).enumerate() {
                        let r = i;
                        softmax_into(&l[r * k..(r + 1) * k], &mut p);
                        let tr = &t[r * k..(r + 1) * k];
                        let total: f32 = tr.iter().sum();
                        for j in 0..k {
                            d[j] = g[r] * (p[j] * total - tr[j]);
                        }
                    }
                    Ok(dl)
                })
            })
        })?;
        Ok((
            Some(Tensor::from_vec(dl, logits.shape(), logits.device())?),
            None,
        ))
    }
}

/// `−Σ_k t_k log softmax(l)_k` `[N]` of logits `[N, K]` against (detached) targets `[N, K]`.
pub fn soft_cross_entropy(logits: &Tensor, target: &Tensor) -> Result<Tensor> {
    logits
        .contiguous()?
        .apply_op2(&target.contiguous()?, SoftCrossEntropy)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var, D};

    fn var(shape: &[usize], seed: u64) -> Var {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n: usize = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| rng.random_range(-2.0..2.0)).collect();
        Var::from_tensor(&Tensor::from_vec(v, shape, &Device::Cpu).unwrap()).unwrap()
    }

    fn vals(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1().unwrap()
    }

    /// Asserts that `fused` and `composed` agree in value and in the gradients of `vars` of the
    /// weighted sum `Σ w · y`.
    fn same(fused: Tensor, composed: Tensor, vars: &[&Var], tol: f32) {
        let (a, b) = (vals(&fused), vals(&composed));
        assert_eq!(fused.dims(), composed.dims());
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= tol * (1.0 + y.abs()), "value {x} vs {y}");
        }
        let w = var(fused.dims(), 99);
        let ga = fused
            .mul(w.as_tensor())
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let gb = composed
            .mul(w.as_tensor())
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        for v in vars {
            let (x, y) = (vals(ga.get(v).unwrap()), vals(gb.get(v).unwrap()));
            for (p, q) in x.iter().zip(&y) {
                assert!(
                    (p - q).abs() <= tol * (1.0 + q.abs()),
                    "gradient {p} vs {q}"
                );
            }
        }
    }

    #[test]
    fn linear_matches_matmul_and_skips_frozen_weights() {
        let (x, w, b) = (var(&[5, 3], 1), var(&[4, 3], 2), var(&[4], 3));
        let composed = x
            .matmul(&w.t().unwrap())
            .unwrap()
            .broadcast_add(&b)
            .unwrap();
        same(
            linear(&x, &w, Some(&b)).unwrap(),
            composed,
            &[&x, &w, &b],
            1e-5,
        );
        same(
            linear(&x, &w, None).unwrap(),
            x.matmul(&w.t().unwrap()).unwrap(),
            &[&x, &w],
            1e-5,
        );
        // a detached weight receives no gradient; the input still does
        let y = linear(&x, &w.as_tensor().detach(), None).unwrap();
        let g = y.sum_all().unwrap().backward().unwrap();
        assert!(g.get(&w).is_none() && g.get(&x).is_some());
    }

    #[test]
    fn norm_act_matches_the_composed_layer_norm() {
        let (x, g, b) = (var(&[6, 8], 4), var(&[8], 5), var(&[8], 6));
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
        same(
            fused(NormAct::Silu),
            candle_nn::ops::silu(&ln).unwrap(),
            &[&x, &g, &b],
            1e-4,
        );
    }

    #[test]
    fn gru_gates_match_the_composed_cell() {
        let (p, h) = (var(&[4, 9], 10), var(&[4, 3], 11));
        let n = 3;
        let reset = candle_nn::ops::sigmoid(&p.narrow(1, 0, n).unwrap()).unwrap();
        let cand = reset
            .mul(&p.narrow(1, n, n).unwrap())
            .unwrap()
            .tanh()
            .unwrap();
        let update =
            candle_nn::ops::sigmoid(&(p.narrow(1, 2 * n, n).unwrap() - 1.0).unwrap()).unwrap();
        let composed =
            (update.mul(&cand).unwrap() + (1.0 - &update).unwrap().mul(&h).unwrap()).unwrap();
        same(gru_gates(&p, &h).unwrap(), composed, &[&p, &h], 1e-5);
    }

    /// The composed unimix probabilities of logits `[N, S, C]`.
    fn probs(l: &Tensor, unimix: f64) -> Tensor {
        let c = l.dims()[2] as f64;
        ((candle_nn::ops::softmax(l, D::Minus1).unwrap() * (1.0 - unimix)).unwrap() + unimix / c)
            .unwrap()
    }

    #[test]
    fn straight_through_samples_are_one_hot_with_the_probability_gradient() {
        let l = var(&[3, 2, 4], 12);
        let u = Tensor::full(0.5f32, (3, 2, 4), &Device::Cpu).unwrap();
        let z = straight_through_sample(&l, &u, 0.01).unwrap();
        assert_eq!(z.dims(), &[3, 8]);
        let p = probs(&l, 0.01);
        // equal uniforms: the sample is the most likely class
        let want = p
            .argmax(D::Minus1)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<u32>()
            .unwrap();
        for (row, k) in vals(&z).chunks(4).zip(want) {
            let mut onehot = [0f32; 4];
            onehot[k as usize] = 1.0;
            assert_eq!(row, onehot);
        }
        let composed = (z.detach().reshape((3, 2, 4)).unwrap() + &p)
            .unwrap()
            .sub(&p.detach())
            .unwrap()
            .reshape((3, 8))
            .unwrap();
        same(z, composed, &[&l], 1e-5);
    }

    #[test]
    fn categorical_kl_matches_the_composed_divergence() {
        let (a, b) = (var(&[3, 2, 4], 13), var(&[3, 2, 4], 14));
        let (pa, pb) = (probs(&a, 0.01), probs(&b, 0.01));
        let composed = pa
            .mul(&(pa.log().unwrap() - pb.log().unwrap()).unwrap())
            .unwrap()
            .sum(D::Minus1)
            .unwrap()
            .sum(D::Minus1)
            .unwrap();
        same(
            categorical_kl(&a, &b, 0.01).unwrap(),
            composed,
            &[&a, &b],
            1e-4,
        );
        let g = categorical_kl(&a, &b.as_tensor().detach(), 0.01)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(g.get(&a).is_some() && g.get(&b).is_none());
    }

    #[test]
    fn twohot_heads_match_the_composed_softmax() {
        let l = var(&[5, 7], 15);
        let bins: Vec<f32> = (0..7).map(|k| -3.0 + k as f32).collect();
        let b = Tensor::new(bins.as_slice(), &Device::Cpu).unwrap();
        let m = candle_nn::ops::softmax(&l, D::Minus1)
            .unwrap()
            .broadcast_mul(&b)
            .unwrap()
            .sum(D::Minus1)
            .unwrap();
        let symexp = m
            .sign()
            .unwrap()
            .mul(&(m.abs().unwrap().exp().unwrap() - 1.0).unwrap())
            .unwrap();
        same(twohot_decode(&l, &bins).unwrap(), symexp, &[&l], 1e-4);

        let t = var(&[5, 7], 16).as_tensor().abs().unwrap().detach();
        let composed = t
            .mul(&candle_nn::ops::log_softmax(&l, D::Minus1).unwrap())
            .unwrap()
            .sum(D::Minus1)
            .unwrap()
            .neg()
            .unwrap();
        same(soft_cross_entropy(&l, &t).unwrap(), composed, &[&l], 1e-4);
    }
}
