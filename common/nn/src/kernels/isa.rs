//! The instruction set a kernel's copy is compiled for (by `vectorised!`), as a type: the
//! kernels' bodies are generic over it, and the few steps the compiler cannot vectorise well on
//! its own, the horizontal reductions of a vector of partial sums, are written per instruction set.
//!
//! A reduction adds (or takes the maximum of) the [`LANES`](super::LANES) partial results by
//! halves, lane `l` with lane `l + 8`, then `l + 4`, `l + 2` and `l + 1`, in every copy: the
//! scalar copy in that order too, so that the three copies give the same bits. Left to itself,
//! the compiler reduces the lanes one after the other (fifteen dependent additions, about 50
//! cycles on Zen 4, as long as summing a row of 256 values), and a tree written on arrays makes
//! it split the accumulator into pairs of lanes instead.

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// The partial results a reduction combines: one per lane.
pub(super) type Lanes = [f32; 16];

/// What a reduction does to two lanes.
#[derive(Clone, Copy)]
pub(super) enum Op {
    Sum,
    Max,
}

/// An instruction set a kernel's copy is compiled for.
pub(super) trait Isa {
    /// `op` over the lanes of `acc`, by halves.
    fn reduce(acc: Lanes, op: Op) -> f32;

    /// `Σ_l acc_l`, by halves.
    #[inline(always)]
    fn sum(acc: Lanes) -> f32 {
        Self::reduce(acc, Op::Sum)
    }

    /// `max_l acc_l`, by halves (a NaN lane may or may not be passed on).
    #[inline(always)]
    fn max(acc: Lanes) -> f32 {
        Self::reduce(acc, Op::Max)
    }
}

/// The portable copy.
pub(super) struct Scalar;

impl Isa for Scalar {
    /// Lane `l` with `l + 8`, `l + 4`, `l + 2`, `l + 1`.
    #[inline(always)]
    fn reduce(mut acc: Lanes, op: Op) -> f32 {
        for half in [8, 4, 2, 1] {
            for l in 0..half {
                acc[l] = match op {
                    Op::Sum => acc[l] + acc[l + half],
                    Op::Max => acc[l].max(acc[l + half]),
                };
            }
        }
        acc[0]
    }
}

/// The copy for AVX-512 (x86-64-v4).
#[cfg(target_arch = "x86_64")]
pub(super) struct Avx512;

/// The copy for AVX2 with FMA (x86-64-v3).
#[cfg(target_arch = "x86_64")]
pub(super) struct Avx2;

/// The last three halvings of an 8-lane vector's two halves `lo`, `hi` with `op`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn reduce_halves(lo: __m256, hi: __m256, op: Op) -> f32 {
    let add = |a, b| match op {
        Op::Sum => _mm_add_ps(a, b),
        Op::Max => _mm_max_ps(a, b),
    };
    let eight = [_mm256_castps256_ps128(lo), _mm256_extractf128_ps::<1>(lo)];
    let eight_hi = [_mm256_castps256_ps128(hi), _mm256_extractf128_ps::<1>(hi)];
    // l + 8: the two vectors; l + 4: their 128-bit halves
    let four = add(add(eight[0], eight_hi[0]), add(eight[1], eight_hi[1]));
    let two = add(four, _mm_movehl_ps(four, four));
    _mm_cvtss_f32(add(two, _mm_movehdup_ps(two)))
}

#[cfg(target_arch = "x86_64")]
impl Isa for Avx2 {
    #[inline(always)]
    fn reduce(acc: Lanes, op: Op) -> f32 {
        // SAFETY: called only from the AVX2 copies, on a processor with AVX2
        unsafe { reduce_avx2(&acc, op) }
    }
}

/// `acc` reduced by halves with `op`, its two halves in two 256-bit loads.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn reduce_avx2(acc: &Lanes, op: Op) -> f32 {
    // SAFETY: `acc` holds 16 values
    let (lo, hi) = unsafe {
        (
            _mm256_loadu_ps(acc.as_ptr()),
            _mm256_loadu_ps(acc.as_ptr().add(8)),
        )
    };
    reduce_halves(lo, hi, op)
}

#[cfg(target_arch = "x86_64")]
impl Isa for Avx512 {
    #[inline(always)]
    fn reduce(acc: Lanes, op: Op) -> f32 {
        // SAFETY: called only from the AVX-512 copies, on a processor with AVX-512
        unsafe { reduce_avx512(&acc, op) }
    }
}

/// `acc` reduced by halves with `op`, its two halves from one 512-bit load.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn reduce_avx512(acc: &Lanes, op: Op) -> f32 {
    // SAFETY: `acc` holds 16 values
    let v = unsafe { _mm512_loadu_ps(acc.as_ptr()) };
    let lo = _mm512_castps512_ps256(v);
    let hi = _mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(_mm512_castps_pd(v)));
    reduce_halves(lo, hi, op)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_copy_reduces_by_the_same_halves() {
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            // spread over many magnitudes, so that the order of the additions shows in the bits
            (rng % 2001) as f32 * 1e-3 * 10f32.powi((rng >> 20) as i32 % 9 - 4) - 1.0
        };
        for _ in 0..2000 {
            let acc: Lanes = std::array::from_fn(|_| next());
            let h8: [f32; 8] = std::array::from_fn(|l| acc[l] + acc[l + 8]);
            let h4: [f32; 4] = std::array::from_fn(|l| h8[l] + h8[l + 4]);
            let expected = (h4[0] + h4[2]) + (h4[1] + h4[3]);
            let sum = Scalar::sum(acc);
            assert_eq!(sum.to_bits(), expected.to_bits(), "{acc:?}");
            let max = acc.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            assert_eq!(Scalar::max(acc), max);
            #[cfg(target_arch = "x86_64")]
            {
                if std::is_x86_feature_detected!("avx2") {
                    assert_eq!(Avx2::sum(acc).to_bits(), sum.to_bits(), "AVX2 {acc:?}");
                    assert_eq!(Avx2::max(acc), max, "AVX2 {acc:?}");
                }
                if std::is_x86_feature_detected!("avx512f") {
                    assert_eq!(Avx512::sum(acc).to_bits(), sum.to_bits(), "AVX-512 {acc:?}");
                    assert_eq!(Avx512::max(acc), max, "AVX-512 {acc:?}");
                }
            }
        }
    }
}
