//! `y = x Wᵀ (+ b)`: the row kernels around the layers' gemm products (the bias gradient, the
//! input's dense columns).

use std::ops::Range;

vectorised! {
    /// `sums += Σ_i g_i` over the rows `g_i` of `g` (`sums.len()` values each): the bias gradient
    /// (candle's `sum(0)` walks the strided path, a fifth of a SAC step).
    pub fn column_sums(g: &[f32], sums: &mut [f32]) {
        for row in g.chunks_exact(sums.len()) {
            for (s, &v) in sums.iter_mut().zip(row) {
                *s += v;
            }
        }
    }
}

/// The input columns of `0..k` outside `sparse`: at most two ranges, empty ones left out.
pub fn dense_parts(k: usize, sparse: &Range<usize>) -> impl Iterator<Item = Range<usize>> {
    [0..sparse.start, sparse.end..k]
        .into_iter()
        .filter(|r| !r.is_empty())
}
