//! The matrix products' ceiling: the gemm calls of a stretch of work, recorded by shape, then
//! run again alone.
//!
//! A training step's time is its products' plus everything around them (row kernels, copies,
//! the operands' trips through the caches, threads waiting). [`record_products`] notes the shape
//! and strides of every gemm call while it is on; [`replay_products`] runs the same calls again
//! on the calling thread, one after another, on operands of random values reused from call to
//! call, and times them. Their rate is what the products reach with nothing else in the way and
//! their operands as warm as the caches can keep them: the step's fraction of it says how much
//! of its time goes to the products and how much to the rest, on the machine at hand.

use super::linear::{gemm_raw, Operand};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, PoisonError};
use std::time::Instant;

/// Whether gemm calls are being recorded.
static RECORDING: AtomicBool = AtomicBool::new(false);
/// The calls recorded since [`record_products`] turned recording on.
static RECORDED: Mutex<Vec<ProductShape>> = Mutex::new(Vec::new());

/// One gemm call: `dst (+)= A B` with `A` `[m, k]`, `B` `[k, n]` and `dst` `[m, n]`, each
/// addressed by the strides it had.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ProductShape {
    /// `m`, `n`, `k`.
    pub dims: (usize, usize, usize),
    /// `A`'s row and column strides.
    pub a_strides: (usize, usize),
    /// `B`'s row and column strides.
    pub b_strides: (usize, usize),
    /// The distance between `dst`'s rows.
    pub dst_row_stride: usize,
    /// Whether the product was added to `dst`.
    pub accumulate: bool,
}

impl ProductShape {
    /// `2 m n k`.
    pub fn flops(&self) -> u64 {
        let (m, n, k) = self.dims;
        2 * (m * n * k) as u64
    }

    /// Values an operand of `rows` x `cols` at `strides` spans.
    fn span(rows: usize, cols: usize, (row_stride, col_stride): (usize, usize)) -> usize {
        (rows - 1) * row_stride + (cols - 1) * col_stride + 1
    }
}

/// Turns the recording of gemm calls on (clearing what an earlier recording left) or off.
pub fn record_products(on: bool) {
    if on {
        RECORDED
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clear();
    }
    RECORDING.store(on, Ordering::Relaxed);
}

/// The calls recorded so far (recording stays as it is).
pub fn recorded_products() -> Vec<ProductShape> {
    RECORDED
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .clone()
}

/// Notes a call, if recording.
pub(super) fn note(shape: ProductShape) {
    if RECORDING.load(Ordering::Relaxed) {
        RECORDED
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(shape);
    }
}

/// Runs `calls` again on this thread, in order, and returns the seconds they took. Operands of
/// pseudo-random values, one buffer each for `A`, `B` and `dst` as long as the longest call
/// needs, are filled before the clock starts; empty products are skipped (none left: 0
/// seconds). Not counted in [`super::matmul_flops`].
pub fn replay_products(calls: &[ProductShape]) -> f64 {
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
