//! Fused CPU row kernels with their own backward passes, for the layers that dominate a
//! DreamerV3 training step: one pass over rows of the input forward and one backward, on the
//! calling thread (the learner parallelises over the batch instead). The networks
//! ([`super::layer`], [`super::rssm`], [`super::losses`]) call the row functions; the tests'
//! oracle (the `ctxrace-oracle` crate, a dev-dependency only) wraps each in a candle custom op
//! and holds it to the composed candle operations, values and gradients, which is why the row
//! functions, their parameters and the gemm products are public.
//!
//! - [`column_sums`], [`dense_parts`]: around the products `y = x Wᵀ (+ b)` ([`gemm_into`]).
//! - [`SparseColumns`]: the products over input columns that are mostly zero (the one-hot
//!   latent of a state), over their non-zeros only.
//! - [`norm_act_rows_into`]: `LayerNorm` then SiLU or the identity ([`Norm`], [`NormAct`]):
//!   `x̂ = (x − μ)/√(σ² + ε)`, `y = act(γ x̂ + β)`; backward
//!   `dx = (dx̂ − mean(dx̂) − x̂ mean(dx̂ x̂)) / √(σ² + ε)` with `dx̂ = γ act'(·) dy`.
//! - [`gru_rows`]: DreamerV3's GRU update from normalised gates `[r, ĉ, u]` and the state `h`:
//!   `h' = σ(u − 1) tanh(σ(r) ĉ) + (1 − σ(u − 1)) h`.
//! - [`sample_rows`], [`probs_rows_bwd`]: a one-hot Gumbel-max sample of the unimix categorical
//!   `p = (1 − η) softmax(l) + η / C` ([`Unimix`]) whose gradient is that of `p`
//!   (`z = onehot + p − sg p`).
//! - [`kl_rows`]: `KL(p_a ‖ p_b)` of two unimix categoricals, summed over the variables.
//! - [`decode_rows`]: `symexp(Σ_k softmax(l)_k b_k)`.
//! - [`cross_entropy_rows`]: `−Σ_k t_k log softmax(l)_k` against fixed targets `t`.
//!
//! - [`adam_update`], [`sum_of_squares`]: the elementwise part of an Adam step.
//!
//! - [`record_products`], [`rerun_products`]: the gemm calls of a stretch of work, noted by
//!   shape and run again alone (the products' ceiling of `ctxrace bench learner`).
//!
//! One file per kernel; the vectorised dispatch and the branch-free maths they share are here.

use isa::Isa;

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
/// 256 (`cargo bench -p ctxrace-oracle --bench norm_act`) took 88-94 µs with it against 108-110 µs
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
pub const LANES: usize = 16;

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

mod adam;
mod categorical;
mod gemm;
mod gru;
pub(crate) mod isa;
mod linear;
mod norm_act;
mod product_profile;
mod sparse_inputs;
mod twohot;

pub use adam::{adam_update, sum_of_squares, AdamLengthError, AdamStep};
pub use gemm::{matmul_flops, record_products, recorded_products, ProductShape};
pub use gru::UPDATE_SHIFT;
pub use norm_act::NormAct;
pub use product_profile::rerun_products;

// the row kernels: for the networks (`crate::layer`, `crate::rssm`) and the oracle's candle ops
pub use categorical::{kl_rows, kl_rows_bwd, probs_rows_bwd, sample_rows, Unimix, PAPER_CLASSES};
pub use gemm::{count_flops, gemm_into, Operand};
pub use gru::{gru_rows, gru_rows_bwd};
pub use linear::{column_sums, dense_parts};
pub use norm_act::{norm_act_rows_bwd_into, norm_act_rows_into, Norm};
pub use sparse_inputs::{SparseColumns, SparseRows};
pub use twohot::{cross_entropy_rows, cross_entropy_rows_bwd, decode_rows, decode_rows_bwd};

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
