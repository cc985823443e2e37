//! Fused CPU row kernels with their own backward passes, for the layers that dominate a
//! DreamerV3 training step: one pass over rows of the input forward and one backward, on the
//! calling thread (the learner parallelises over the batch instead). The networks
//! ([`super::layer`], [`super::rssm`], [`super::losses`]) call the row functions; around each, a candle custom op (only with
//! `cfg(test)` or the `oracle` feature) lets the tests hold it to the composed candle operations,
//! values and gradients. The ops compute the gradient of an argument only when it is tracked
//! ([`Tensor::track_op`]).
//!
//! - [`linear`]: `y = x Wᵀ (+ b)`.
//! - [`linear_norm_act`]: a bias-free [`linear`] then [`norm_act`] as one operation (the product
//!   stays inside it, so the backward pass hands the normalisation's gradient straight to the
//!   product's, without a graph node, a zeroed buffer and an addition in between).
//! - [`sparse_inputs`]: the products of [`linear`] and [`linear_norm_act`] over input columns
//!   that are mostly zero (the one-hot latent of a state), over their non-zeros only.
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
//! - [`adam_update`], [`sum_of_squares`]: the elementwise part of an Adam step.
//!
//! - [`record_products`], [`rerun_products`]: the gemm calls of a stretch of work, noted by
//!   shape and run again alone (the products' ceiling of `ctxrace bench learner`).
//!
//! One file per kernel, each checked against the composed candle operations, values and
//! gradients, in its tests; the vectorised dispatch and the branch-free maths they share are here.

#[cfg(any(test, feature = "oracle"))]
use candle_core::{
    bail, CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Result, Shape, Storage, Tensor,
};
use isa::Isa;

/// The contiguous `f32` values of a CPU storage under `layout`.
#[cfg(any(test, feature = "oracle"))]
fn cpu_slice<'a>(storage: &'a CpuStorage, layout: &Layout) -> Result<&'a [f32]> {
    let data = storage.as_slice::<f32>()?;
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => bail!("fused kernel: a non-contiguous input (call .contiguous() first)"),
    }
}

/// Runs `f` on the contiguous `f32` values of `t`.
#[cfg(any(test, feature = "oracle"))]
fn read<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> Result<R>) -> Result<R> {
    let t = t.contiguous()?;
    let (storage, layout) = t.storage_and_layout();
    let Storage::Cpu(cpu) = &*storage else {
        bail!("fused kernels run on the CPU only")
    };
    f(cpu_slice(cpu, layout)?)
}

/// Defines a function whose body is compiled three times, for AVX-512, for AVX2 with FMA and for
/// the baseline, and runs the widest the processor has (checked at run time; AVX-512 only with the
/// `avx512` feature). The body and the `#[inline(always)]` helpers it calls vectorise inside each
/// copy; the body is generic over the copy's instruction set `S` ([`isa::Isa`]), which the
/// reductions ([`lane_sum`], [`lane_max`]) take.
macro_rules! vectorised {
    ($(#[$doc:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$doc])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            #[allow(clippy::too_many_arguments)]
            fn body<S: $crate::kernels::isa::Isa>($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn v4($($arg: $ty),*) $(-> $ret)? {
                    body::<$crate::kernels::isa::Avx512>($($arg),*)
                }
                #[target_feature(enable = "avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn v3($($arg: $ty),*) $(-> $ret)? {
                    body::<$crate::kernels::isa::Avx2>($($arg),*)
                }
                if cfg!(feature = "avx512")
                    && std::is_x86_feature_detected!("avx512f")
                    && std::is_x86_feature_detected!("avx512vl")
                {
                    // SAFETY: the processor has the features v4 is compiled for.
                    return unsafe { v4($($arg),*) };
                }
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    // SAFETY: the processor has the features v3 is compiled for.
                    return unsafe { v3($($arg),*) };
                }
            }
            body::<$crate::kernels::isa::Scalar>($($arg),*)
        }
    };
}

/// Whether the backward pass needs the gradient of `t`.
#[cfg(any(test, feature = "oracle"))]
fn wants_grad(t: &Tensor) -> bool {
    t.track_op()
}

/// `eˣ` to about one part in 10⁷, branch-free and on float and integer bits only, so that loops
/// over it vectorise (a float-to-integer `as` cast or `floor` would not):
/// `eˣ = 2ᵏ eʳ` with `k = round(x log₂e)`, `|r| ≤ ln 2 / 2`, `eʳ` by its Taylor series to `r⁶`
/// (remainder below `1.2·10⁻⁷`), `2ᵏ` built in the exponent bits. `k` is rounded by adding
/// `1.5·2²³`, which leaves it in the low mantissa bits. Inputs are clamped to `[−87, 88]`, where
/// `f32` neither underflows to subnormals nor overflows. The series is in fused multiply-adds
/// ([`f32::mul_add`]: one instruction in the kernels' AVX-512 and AVX2 copies, and on aarch64;
/// in the baseline copy on x86 without FMA a call to libm's `fmaf`: the same values, slower).
#[inline(always)]
fn exp(x: f32) -> f32 {
    exp_in_range(x.clamp(-87.0, 88.0))
}

/// [`exp`] of an `x` already in `[−87, 88]`.
#[inline(always)]
fn exp_in_range(x: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0; // 1.5·2²³
    let shifted = x.mul_add(std::f32::consts::LOG2_E, ROUND);
    let k = shifted - ROUND;
    // ln 2 split in two so that k · ln 2 is exact to f32 precision
    let r = k.mul_add(2.121_944_4e-4, k.mul_add(-0.693_359_4, x));
    let mut p: f32 = 1.0 / 720.0;
    for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
        p = p.mul_add(r, c);
    }
    // the low bits of `shifted` hold k (two's complement); k + 127 ∈ [1, 254] after the clamp
    let biased = shifted
        .to_bits()
        .wrapping_sub(ROUND.to_bits())
        .wrapping_add(127);
    p * f32::from_bits(biased << 23)
}

/// `ln x` for `x > 0` (finite, normal) to about one part in 10⁷, branch-free so that loops over it
/// vectorise: `x = m 2ᵉ` with `m ∈ [√½, √2)` from the float's bits, `ln x = e ln 2 + ln m`,
/// `ln m = 2 atanh s = 2 (s + s³/3 + … + s⁹/9)` with `s = (m − 1)/(m + 1)`, `|s| ≤ 0.172`
/// (remainder below `4·10⁻¹⁰`).
#[inline(always)]
fn ln(x: f32) -> f32 {
    let bits = x.to_bits();
    // the mantissa as [1, 2), halved into [√½, √2) when above √2
    let m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    let big = m > std::f32::consts::SQRT_2;
    let m = if big { 0.5 * m } else { m };
    let e = ((bits >> 23) & 0xff) as i32 - 127 + i32::from(big);
    let s = (m - 1.0) / (m + 1.0);
    let s2 = s * s;
    let series = s * (2.0 + s2 * (2.0 / 3.0 + s2 * (0.4 + s2 * (2.0 / 7.0 + s2 * (2.0 / 9.0)))));
    e as f32 * std::f32::consts::LN_2 + series
}

/// `1 + e⁻ˣ`, with `x` clamped to `[−80, 87]` (`σ(−80) < 2·10⁻³⁵` stays a normal float;
/// `σ(87)` is 1 in `f32`); NaN stays NaN. One clamp serves [`exp`]'s range too: the denominator
/// of [`sigmoid`] and [`silu`].
#[inline(always)]
fn one_plus_exp_neg(x: f32) -> f32 {
    1.0 + exp_in_range((-x).clamp(-87.0, 80.0))
}

/// `1 / (1 + e⁻ˣ)` on [`one_plus_exp_neg`]: the kernels' own σ, vectorisable and not bit-equal
/// to [`crate::sigmoid`] (which the policies and the learner's passes use). The reciprocal is a
/// division: on Zen 4 it runs beside the multiply-adds, and the SiLU forward pass of 512 rows of
/// 256 (`cargo bench -p ctxrace-nn --bench norm_act`) took 88-94 µs with it against 108-110 µs
/// with three Newton steps from a bit-trick guess (AVX2 copies: 124-148 against 152-161 µs).
#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    1.0 / one_plus_exp_neg(x)
}

/// `x σ(x) = x / (1 + e⁻ˣ)`: one division and no multiplication (the forward pass of 512 rows of
/// 256 through LayerNorm+SiLU: 69.7 -> 66.8 µs against `x σ(x)`).
#[inline(always)]
fn silu(x: f32) -> f32 {
    x / one_plus_exp_neg(x)
}

/// `tanh x = 2 σ(2x) − 1`.
#[inline(always)]
fn tanh(x: f32) -> f32 {
    2.0 * sigmoid(2.0 * x) - 1.0
}

/// Lanes of the sums below: independent partial sums let them vectorise (a single running sum
/// of floats cannot be reordered by the compiler).
const LANES: usize = 16;

/// `Σ_i f(a_i, b_i)` over two slices of one length, in [`LANES`] partial sums reduced by
/// halves ([`Isa::sum`]).
#[inline(always)]
fn lane_sum<S: Isa>(a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> f32) -> f32 {
    let mut acc = [0f32; LANES];
    let (ca, cb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (xa, xb) in ca.zip(cb) {
        for l in 0..LANES {
            acc[l] += f(xa[l], xb[l]);
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(&x, &y)| f(x, y)).sum();
    S::sum(acc) + tail
}

/// The largest value of `x` (`−∞` if empty), in [`LANES`] partial maxima reduced by halves
/// ([`Isa::max`]).
#[inline(always)]
fn lane_max<S: Isa>(x: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; LANES];
    let chunks = x.chunks_exact(LANES);
    let tail = chunks
        .remainder()
        .iter()
        .copied()
        .fold(f32::NEG_INFINITY, f32::max);
    for c in chunks {
        for l in 0..LANES {
            acc[l] = acc[l].max(c[l]);
        }
    }
    S::max(acc).max(tail)
}

/// Softmax of `l` into `out`.
#[inline(always)]
fn softmax_into<S: Isa>(l: &[f32], out: &mut [f32]) {
    let max = lane_max::<S>(l);
    for (o, &v) in out.iter_mut().zip(l) {
        *o = exp(v - max);
    }
    let inv = 1.0 / lane_sum::<S>(out, out, |v, _| v);
    out.iter_mut().for_each(|o| *o *= inv);
}

/// `out ← ∂/∂l` of a function of `p = (1 − η) softmax(l) + η/C` given `dp` and `s = softmax(l)`:
/// `(1 − η) s_k (dp_k − Σ_j s_j dp_j)`.
#[inline(always)]
fn unimix_softmax_backward<S: Isa>(s: &[f32], dp: &[f32], keep: f32, out: &mut [f32]) {
    let dot = lane_sum::<S>(s, dp, |a, b| a * b);
    for ((o, &sk), &dk) in out.iter_mut().zip(s).zip(dp) {
        *o = keep * sk * (dk - dot);
    }
}

#[cfg(any(test, feature = "oracle"))]
fn dims2(t: &Tensor) -> Result<(usize, usize)> {
    match t.dims() {
        [n, d] => Ok((*n, *d)),
        other => bail!("fused kernel: expected a matrix, got shape {other:?}"),
    }
}

mod adam;
mod categorical;
mod gemm;
mod gru;
pub(crate) mod isa;
mod linear;
#[cfg(any(test, feature = "oracle"))]
mod linear_norm;
mod norm_act;
mod product_profile;
mod sparse_inputs;
mod twohot;

pub use adam::{adam_update, sum_of_squares, AdamLengthError, AdamStep};
pub use gemm::{matmul_flops, record_products, recorded_products, ProductShape};
pub use norm_act::NormAct;
pub use product_profile::rerun_products;

// the candle custom ops around the row kernels: the tests' oracle (`oracle` feature)
#[cfg(any(test, feature = "oracle"))]
pub use categorical::{categorical_kl, straight_through_sample};
#[cfg(any(test, feature = "oracle"))]
pub use gru::gru_gates;
#[cfg(any(test, feature = "oracle"))]
pub use linear::linear;
#[cfg(any(test, feature = "oracle"))]
pub use linear_norm::linear_norm_act;
#[cfg(any(test, feature = "oracle"))]
pub use norm_act::norm_act;
#[cfg(any(test, feature = "oracle"))]
pub use twohot::{soft_cross_entropy, twohot_decode};
// the row kernels, for the networks (`crate::layer`, `crate::rssm`)
pub(crate) use categorical::{kl_rows, kl_rows_bwd, probs_rows_bwd, sample_rows, Unimix};
pub(crate) use gemm::{count_flops, gemm_into, Operand};
pub(crate) use gru::{gru_rows, gru_rows_bwd};
pub(crate) use linear::{column_sums, dense_parts};
pub(crate) use norm_act::{norm_act_rows_bwd_into, norm_act_rows_into, Norm};
pub(crate) use sparse_inputs::{SparseColumns, SparseRows};
pub(crate) use twohot::{cross_entropy_rows, cross_entropy_rows_bwd, decode_rows, decode_rows_bwd};

#[cfg(test)]
mod tests {
    #[test]
    fn exp_and_sigmoid_match_std_to_single_precision() {
        // the unclamped range [−87, 88]
        for i in -1990..=2010 {
            let x = i as f32 * 0.0437;
            let (ours, std) = (super::exp(x), x.exp());
            assert!(
                (ours - std).abs() <= 4e-7 * std,
                "exp({x}) = {ours}, std {std}"
            );
            let s = 1.0 / (1.0 + (-x).exp());
            assert!((super::sigmoid(x) - s).abs() <= 1e-6, "sigmoid({x})");
            if x >= -80.0 {
                let rel = (super::sigmoid(x) - s).abs() / s;
                assert!(rel <= 4e-7, "sigmoid({x}): relative error {rel}");
            }
        }
        for i in 1..=4000 {
            let x = i as f32 * 0.00025 + (i as f32 * 0.37).sin().abs() * 1e-6;
            let (ours, std) = (super::ln(x), x.ln());
            assert!(
                (ours - std).abs() <= 3e-7 * (1.0 + std.abs()),
                "ln({x}) = {ours}, std {std}"
            );
        }
        for x in [1e-30f32, 1e-7, 0.5, 1.0, 1.5, 2.0, 1e7, 3e30] {
            assert!(
                (super::ln(x) - x.ln()).abs() <= 3e-7 * (1.0 + x.ln().abs()),
                "ln({x})"
            );
        }
        // clamped where f32 would overflow or turn subnormal
        assert!(super::exp(200.0).is_finite() && super::exp(-200.0) > 0.0);
        assert!(super::sigmoid(-200.0) >= 0.0 && super::sigmoid(200.0) == 1.0);
        assert!(super::sigmoid(f32::NAN).is_nan());
        let l = [0.5f32; 37].map(|v| v * 3.0);
        assert_eq!(super::lane_max::<super::isa::Scalar>(&l), 1.5);
        let sum = super::lane_sum::<super::isa::Scalar>(&l, &l, |a, b| a * b);
        assert!((sum - 37.0 * 2.25).abs() < 1e-4);
    }
}

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

    /// `[rows, 3 + 32 + 2]` with columns `3..35` two one-hot groups of 16 (values not 1).
    pub(super) fn one_hot_input(rows: usize) -> Var {
        let dense = vals(var(&[rows, 5], 41).as_tensor());
        let mut x = vec![0f32; rows * 37];
        for i in 0..rows {
            let row = &mut x[i * 37..(i + 1) * 37];
            row[..3].copy_from_slice(&dense[i * 5..i * 5 + 3]);
            row[35..].copy_from_slice(&dense[i * 5 + 3..i * 5 + 5]);
            row[3 + (i * 7) % 16] = 1.0 + i as f32 * 0.25;
            row[19 + (i * 3) % 16] = -0.5;
        }
        Var::from_tensor(&Tensor::from_vec(x, (rows, 37), &Device::Cpu).unwrap()).unwrap()
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
