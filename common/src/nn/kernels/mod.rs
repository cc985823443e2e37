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
//! One file per kernel, each checked against the composed candle operations, values and
//! gradients, in its tests; the vectorised dispatch and the branch-free maths they share are here.

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

mod categorical;
mod gru;
mod linear;
mod norm_act;
mod twohot;

pub use categorical::{categorical_kl, straight_through_sample};
pub use gru::gru_gates;
pub use linear::{linear, matmul_flops};
pub use norm_act::{norm_act, NormAct};
pub use twohot::{soft_cross_entropy, twohot_decode};

/// Helpers of the kernels' tests.
#[cfg(test)]
mod testing {
    use candle_core::Tensor;
    pub(super) use candle_core::{Device, Var, D};

    pub(super) fn var(shape: &[usize], seed: u64) -> Var {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n: usize = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| rng.random_range(-2.0..2.0)).collect();
        Var::from_tensor(&Tensor::from_vec(v, shape, &Device::Cpu).unwrap()).unwrap()
    }

    pub(super) fn vals(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1().unwrap()
    }

    /// Asserts that `fused` and `composed` agree in value and in the gradients of `vars` of the
    /// weighted sum `Σ w · y`.
    pub(super) fn same(fused: Tensor, composed: Tensor, vars: &[&Var], tol: f32) {
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
}
