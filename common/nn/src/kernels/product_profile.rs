//! The matrix products' ceiling: the gemm calls of a stretch of work, recorded by shape, then
//! run again alone.
//!
//! A training step's time is its products' plus everything around them (row kernels, copies,
//! the operands' trips through the caches, threads waiting). [`super::record_products`] notes the shape
//! and strides of every gemm call while it is on; [`rerun_products`] runs the same calls again
//! on the calling thread, one after another, on operands of random values reused from call to
//! call, and times them. Their rate is what the products reach with nothing else in the way and
//! their operands as warm as the caches can keep them: the step's fraction of it says how much
//! of its time goes to the products and how much to the rest, on the machine at hand.

use super::gemm::{gemm_raw, Operand, ProductShape};
use std::time::Instant;

/// Runs `calls` again on this thread, in order, and returns the seconds they took. Operands of
/// pseudo-random values, one buffer each for `A`, `B` and `dst` as long as the longest call
/// needs, are filled before the clock starts; empty products are skipped (none left: 0
/// seconds). Not counted in [`super::matmul_flops`].
pub fn rerun_products(calls: &[ProductShape]) -> f64 {
    let calls: Vec<_> = calls
        .iter()
        .filter(|c| c.dims.0 > 0 && c.dims.1 > 0 && c.dims.2 > 0)
        .collect();
    if calls.is_empty() {
        return 0.0;
    }
    let longest = |span: &dyn Fn(&ProductShape) -> usize| calls.iter().map(|c| span(c)).max();
    let a_len = longest(&|c| ProductShape::span(c.dims.0, c.dims.2, c.a_strides)).unwrap_or(0);
    let b_len = longest(&|c| ProductShape::span(c.dims.2, c.dims.1, c.b_strides)).unwrap_or(0);
    let dst_len =
        longest(&|c| ProductShape::span(c.dims.0, c.dims.1, (c.dst_row_stride, 1))).unwrap_or(0);
    // a cheap generator: the values only have to be finite and not all alike
    let values = |len: usize, seed: u32| -> Vec<f32> {
        let mut s = seed;
        (0..len)
            .map(|_| {
                s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                (s >> 8) as f32 / (1u32 << 24) as f32 - 0.5
            })
            .collect()
    };
    let (a, b, mut dst) = (values(a_len, 1), values(b_len, 2), values(dst_len, 3));
    let start = Instant::now();
    for c in calls {
        let operand = |data, (row_stride, col_stride)| Operand {
            data,
            row_stride,
            col_stride,
        };
        // SAFETY: each buffer spans what the longest call of its operand addresses (above),
        // and `dst` holds initialised values.
        unsafe {
            gemm_raw(
                dst.as_mut_ptr(),
                (c.dst_row_stride, c.accumulate, false),
                c.dims,
                operand(&a, c.a_strides),
                operand(&b, c.b_strides),
            )
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    std::hint::black_box(&dst);
    seconds
}
