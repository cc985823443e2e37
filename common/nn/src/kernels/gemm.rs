//! The matrix products on gemm: every product of a layer goes through [`gemm_raw`], which counts
//! its floating-point operations ([`matmul_flops`]) and, while [`record_products`] is on, notes
//! its shape for [`super::product_profile`] to run again alone.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};

/// Floating-point operations of the matrix products run so far in this process, over all threads.
static MATMUL_FLOPS: AtomicU64 = AtomicU64::new(0);

/// Floating-point operations of the linear layers' matrix products run so far in this process
/// (forward and backward, `2 m n k` per `[m, k] × [k, n]` product), over all threads: the
/// counter behind the learner's `flops/*` metrics and `ctxrace bench learner`'s fraction of peak.
pub fn matmul_flops() -> u64 {
    MATMUL_FLOPS.load(Ordering::Relaxed)
}

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
    pub(super) fn span(
        rows: usize,
        cols: usize,
        (row_stride, col_stride): (usize, usize),
    ) -> usize {
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
fn note(shape: ProductShape) {
    if RECORDING.load(Ordering::Relaxed) {
        RECORDED
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(shape);
    }
}

/// Counts `flops` floating-point operations of the products done outside gemm.
pub fn count_flops(flops: usize) {
    MATMUL_FLOPS.fetch_add(flops as u64, Ordering::Relaxed);
}

/// A matrix operand of [`gemm_into`]: its values and the strides of its rows and columns.
#[derive(Clone, Copy)]
pub struct Operand<'a> {
    /// The values, from the first element on.
    pub data: &'a [f32],
    /// The distance between consecutive rows' elements.
    pub row_stride: usize,
    /// The distance between consecutive columns' elements.
    pub col_stride: usize,
}

impl<'a> Operand<'a> {
    /// A row-major `[rows, cols]` matrix.
    pub fn rows(data: &'a [f32], cols: usize) -> Self {
        Self {
            data,
            row_stride: cols,
            col_stride: 1,
        }
    }

    /// The transpose of a row-major `[rows, cols]` matrix.
    pub fn transposed(data: &'a [f32], cols: usize) -> Self {
        Self {
            data,
            row_stride: 1,
            col_stride: cols,
        }
    }
}

/// `dst ← A B`, or `dst += A B` with `accumulate`, for `A` `[m, k]`, `B` `[k, n]` and `dst` the
/// `[m, n]` whose rows start `row_stride` apart in `dst` (a block of columns of a wider matrix
/// when `row_stride > n`).
pub fn gemm_into(
    dst: &mut [f32],
    row_stride: usize,
    accumulate: bool,
    (m, n, k): (usize, usize, usize),
    a: Operand,
    b: Operand,
) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(n <= row_stride && dst.len() >= (m - 1) * row_stride + n);
    if k == 0 {
        if !accumulate {
            dst.chunks_mut(row_stride).for_each(|r| r[..n].fill(0.0));
        }
        return;
    }
    // SAFETY: `dst` holds the m rows of n values at `row_stride` (asserted above), initialised.
    unsafe {
        gemm_raw(
            dst.as_mut_ptr(),
            (row_stride, accumulate, true),
            (m, n, k),
            a,
            b,
        )
    }
}

/// gemm of `A B` into the `[m, n]` at `dst` with rows `row_stride` apart (see [`gemm_into`]),
/// on this thread; with `counted` it counts its operations and notes its shape
/// ([`record_products`]), as every product of a layer does (a replay's do not).
///
/// # Safety
/// `dst` must address `m` rows of `n` values at `row_stride`, initialised if `accumulate`.
pub(super) unsafe fn gemm_raw(
    dst: *mut f32,
    (row_stride, accumulate, counted): (usize, bool, bool),
    (m, n, k): (usize, usize, usize),
    a: Operand,
    b: Operand,
) {
    if counted {
        count_flops(2 * m * n * k);
        note(ProductShape {
            dims: (m, n, k),
            a_strides: (a.row_stride, a.col_stride),
            b_strides: (b.row_stride, b.col_stride),
            dst_row_stride: row_stride,
            accumulate,
        });
    }
    // the callers' shape checks guarantee these; the unsafe call below relies on them
    assert!(a.data.len() > (m - 1) * a.row_stride + (k - 1) * a.col_stride);
    assert!(b.data.len() > (k - 1) * b.row_stride + (n - 1) * b.col_stride);
    // SAFETY: `a` and `b` hold the m×k and k×n values their strides address (asserted above);
    // `dst` is as the caller promises.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst,
            1,
            row_stride as isize,
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
    }
}
