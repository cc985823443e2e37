//! The products of a linear layer over input columns that are mostly zero.
//!
//! A DreamerV3 state is `[h, z]` with `z` the one-hot sample of `S` categorical variables of `C`
//! classes: `S` of its `S·C` values are non-zero (the straight-through sample's values are the
//! one-hot vector's). Every layer that reads a state (the heads, the actor, the RSSM's input
//! layer) multiplies those zeros in a dense product. Over such columns `c ∈ a..b` the products
//! go over the non-zeros `x_ic` of each row instead:
//!
//! - forward `y_i += Σ_{c ∈ nz(i)} x_ic Wᵀ_c` (rows of `Wᵀ`, `[in, out]`),
//! - weight gradient `dWᵀ_c += Σ_{i : c ∈ nz(i)} x_ic g_i`,
//!
//! the same sums as the dense product's without its zero terms: `C` times fewer operations on
//! `z`. The input's gradient `g W` stays dense (it is dense). Which columns are sparse is a
//! hint of the layer ([`crate::Mlp::sparse_inputs`]); any values are multiplied right, and
//! a block denser than [`MAX_DENSITY`] goes through the dense product.

use std::ops::Range;

/// The largest fraction of non-zeros at which the row-by-row products are used: each non-zero
/// costs an `out`-long multiply-add from memory, a few times the dense kernel's cost per
/// operation, so beyond this the dense product is faster.
pub(super) const MAX_DENSITY: f64 = 0.125;

/// The non-zeros of the columns `a..b` of a row-major matrix, row by row (compressed rows), the
/// columns counted from `a`.
#[derive(Debug)]
pub struct SparseColumns {
    /// Row `i`'s non-zeros are `starts[i]..starts[i + 1]` of `columns` and `values`.
    starts: Vec<usize>,
    columns: Vec<usize>,
    values: Vec<f32>,
}

impl SparseColumns {
    /// The non-zeros of `columns` of `x` (`[rows, width]`), or `None` if more than
    /// `MAX_DENSITY` (an eighth) of them are non-zero (or the range is empty or outside the
    /// width).
    pub fn gather(x: &[f32], width: usize, columns: &Range<usize>) -> Option<Self> {
        if columns.is_empty() || columns.end > width || width == 0 {
            return None;
        }
        let rows = x.len() / width;
        let limit = (MAX_DENSITY * (rows * columns.len()) as f64) as usize;
        let mut sparse = Self {
            starts: Vec::with_capacity(rows + 1),
            columns: Vec::with_capacity(limit),
            values: Vec::with_capacity(limit),
        };
        sparse.starts.push(0);
        let mut masks = vec![0u32; columns.len().div_ceil(32)];
        for row in x.chunks_exact(width) {
            non_zero_masks(&row[columns.clone()], &mut masks);
            for (i, &mask) in masks.iter().enumerate() {
                let mut bits = mask;
                while bits != 0 {
                    if sparse.values.len() == limit {
                        return None;
                    }
                    let c = i * 32 + bits.trailing_zeros() as usize;
                    sparse.columns.push(c);
                    sparse.values.push(row[columns.start + c]);
                    bits &= bits - 1;
                }
            }
            sparse.starts.push(sparse.values.len());
        }
        Some(sparse)
    }

    /// No rows yet (for [`SparseColumns::append`]).
    pub fn empty() -> Self {
        Self {
            starts: vec![0],
            columns: Vec::new(),
            values: Vec::new(),
        }
    }

    /// The rows `r`.
    pub fn rows(&self, r: std::ops::Range<usize>) -> SparseRows<'_> {
        SparseRows {
            starts: &self.starts[r.start..=r.end],
            columns: &self.columns,
            values: &self.values,
        }
    }

    /// Every row.
    pub fn all(&self) -> SparseRows<'_> {
        self.rows(0..self.starts.len() - 1)
    }

    /// The number of rows.
    pub fn row_count(&self) -> usize {
        self.starts.len() - 1
    }

    /// `other`'s rows after these.
    pub fn append(&mut self, other: &Self) {
        let base = self.values.len();
        self.starts
            .extend(other.starts[1..].iter().map(|s| s + base));
        self.columns.extend_from_slice(&other.columns);
        self.values.extend_from_slice(&other.values);
    }
}

/// Some consecutive rows of a [`SparseColumns`].
#[derive(Clone, Copy)]
pub struct SparseRows<'a> {
    /// Row `i`'s non-zeros are `starts[i]..starts[i + 1]` of `columns` and `values`.
    starts: &'a [usize],
    columns: &'a [usize],
    values: &'a [f32],
}

impl SparseRows<'_> {
    /// The number of non-zeros.
    pub fn nonzeros(&self) -> usize {
        self.starts[self.starts.len() - 1] - self.starts[0]
    }

    /// `y_i += Σ x_ic Wᵀ_c` for `y` `[rows, out]` and `wt` the rows of `Wᵀ` of the columns.
    pub fn add_products(&self, wt: &[f32], out: usize, y: &mut [f32]) {
        add_row_products(self.starts, self.columns, self.values, wt, out, y);
    }

    /// `dWᵀ_c += Σ_i x_ic g_i` for `g` `[rows, out]` and `dwt` the rows of `dWᵀ` of the columns.
    pub fn add_weight_grads(&self, g: &[f32], out: usize, dwt: &mut [f32]) {
        add_column_grads(self.starts, self.columns, self.values, g, out, dwt);
    }
}

vectorised! {
    /// Bit `b` of `masks[i]` set where `block[32 i + b]` is not ±0 (compared on the bits with the
    /// sign cleared, branch-free, so that each 32 values are a few vector instructions).
    fn non_zero_masks(block: &[f32], masks: &mut [u32]) {
        for (mask, chunk) in masks.iter_mut().zip(block.chunks(32)) {
            let mut m = 0u32;
            for (b, v) in chunk.iter().enumerate() {
                m |= u32::from(v.to_bits() << 1 != 0) << b;
            }
            *mask = m;
        }
    }
}

vectorised! {
    /// `y_i += Σ_j values_j wt_{columns_j}` over each row's non-zeros `j` (rows of `out` values).
    fn add_row_products(
        starts: &[usize],
        columns: &[usize],
        values: &[f32],
        wt: &[f32],
        out: usize,
        y: &mut [f32],
    ) {
        for (i, y_i) in y.chunks_exact_mut(out).enumerate() {
            for j in starts[i]..starts[i + 1] {
                let (c, v) = (columns[j], values[j]);
                for (d, &w) in y_i.iter_mut().zip(&wt[c * out..(c + 1) * out]) {
                    *d += v * w;
                }
            }
        }
    }
}

vectorised! {
    /// `dwt_{columns_j} += values_j g_i` over each row `i`'s non-zeros `j` (rows of `out` values).
    fn add_column_grads(
        starts: &[usize],
        columns: &[usize],
        values: &[f32],
        g: &[f32],
        out: usize,
        dwt: &mut [f32],
    ) {
        for (i, g_i) in g.chunks_exact(out).enumerate() {
            for j in starts[i]..starts[i + 1] {
                let (c, v) = (columns[j], values[j]);
                for (d, &gv) in dwt[c * out..(c + 1) * out].iter_mut().zip(g_i) {
                    *d += v * gv;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gathers_the_non_zeros_and_declines_dense_blocks() {
        // 2 rows of width 6, columns 1..5 sparse
        let x = [9.0, 0.0, 2.0, 0.0, 0.0, 7.0, 8.0, 0.0, 0.0, 0.0, -1.0, 6.0];
        assert!(
            SparseColumns::gather(&x, 6, &(1..5)).is_none(),
            "2 of 8 is over 1/8"
        );
        let mut wide = vec![0f32; 2 * 20];
        wide[3] = 2.0;
        wide[20 + 17] = -1.0;
        let s = SparseColumns::gather(&wide, 20, &(2..20)).unwrap();
        assert_eq!(s.starts, [0, 1, 2]);
        assert_eq!(s.columns, [1, 15]);
        assert_eq!(s.values, [2.0, -1.0]);
        assert!(SparseColumns::gather(&wide, 20, &(2..21)).is_none());
        assert!(SparseColumns::gather(&wide, 20, &(4..4)).is_none());
    }
}
