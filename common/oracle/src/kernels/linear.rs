//! `y = x Wᵀ (+ b)` on the networks' gemm products as a candle op, the gradients of `x` and `W` only where they are tracked.

use super::*;
use ctxrace_nn::kernels::{column_sums, count_flops, dense_parts, Operand, SparseColumns};
use std::ops::Range;
use std::sync::{Mutex, PoisonError};

/// `y = x Wᵀ (+ b)` (see [`linear`]), the weight argument `W` `[out, in]`.
pub(super) struct Linear {
    /// Input columns that are mostly zero ([`SparseColumns`]).
    sparse: Option<Range<usize>>,
    /// Their non-zeros in the forward pass's input, kept for the weight's gradient when the
    /// weight takes one here (`None` otherwise: a frozen layer keeps nothing).
    gathered: Option<Mutex<Option<SparseColumns>>>,
}

impl Linear {
    /// The rows `rows` of `Wᵀ` as an operand, from the weight's values `w` (`k` inputs).
    fn weight_rows<'a>(w: &'a [f32], k: usize, rows: &Range<usize>) -> Operand<'a> {
        Operand {
            data: &w[rows.start..],
            row_stride: 1,
            col_stride: k,
        }
    }

    /// The sparse columns of `x` (`[N, k]`) and their non-zeros, if the layer has such columns
    /// and they are sparse enough: `known`, if given, or gathered from `x`.
    fn sparse_columns(
        &self,
        x: &[f32],
        k: usize,
        known: Option<SparseColumns>,
    ) -> Option<(Range<usize>, SparseColumns)> {
        let columns = self.sparse.as_ref()?;
        known
            .or_else(|| SparseColumns::gather(x, k, columns))
            .map(|s| (columns.clone(), s))
    }
}

impl Linear {
    pub(super) fn fwd(
        &self,
        x: (&CpuStorage, &Layout),
        w: (&CpuStorage, &Layout),
        b: Option<(&CpuStorage, &Layout)>,
    ) -> Result<(CpuStorage, Shape)> {
        let (n, k) = x.1.shape().dims2()?;
        let (m, k2) = w.1.shape().dims2()?;
        if k != k2 {
            bail!(
                "linear: input width {k} but weight {:?}",
                w.1.shape().dims()
            );
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
        let Some((columns, sparse)) = self.sparse_columns(x, k, None) else {
            let wt = Self::weight_rows(w, k, &(0..k));
            let y = matmul(n, m, k, Operand::rows(x, k), wt, init);
            return Ok((CpuStorage::F32(y), Shape::from((n, m))));
        };
        let mut y = init;
        for part in dense_parts(k, &columns) {
            let xs = Operand {
                data: &x[part.start..],
                row_stride: k,
                col_stride: 1,
            };
            let wt = Self::weight_rows(w, k, &part);
            y = Some(matmul(n, m, part.len(), xs, wt, y));
        }
        let mut y = y.unwrap_or_else(|| vec![0f32; n * m]);
        // the sparse columns' rows of Wᵀ, from W [m, k]
        let mut wt = vec![0f32; columns.len() * m];
        for (j, w_j) in w.chunks_exact(k).enumerate() {
            for (c, &v) in w_j[columns.clone()].iter().enumerate() {
                wt[c * m + j] = v;
            }
        }
        sparse.all().add_products(&wt, m, &mut y);
        count_flops(2 * m * sparse.all().nonzeros());
        if let Some(kept) = &self.gathered {
            *kept.lock().unwrap_or_else(PoisonError::into_inner) = Some(sparse);
        }
        Ok((CpuStorage::F32(y), Shape::from((n, m))))
    }

    /// The weight's gradient `[m, k]` for `x` `[n, k]` whose columns
    /// `columns` are `sparse` and the output gradient `g` `[n, m]`: `dWᵀ = xᵀ g` by gemm over
    /// the other columns, row by row over the non-zeros of these.
    fn sparse_weight_grad(
        &self,
        (x, g): (&[f32], &[f32]),
        (n, k, m): (usize, usize, usize),
        columns: &Range<usize>,
        sparse: &SparseColumns,
    ) -> Vec<f32> {
        let mut dwt = vec![0f32; k * m];
        for part in dense_parts(k, columns) {
            let xt = Operand {
                data: &x[part.start..],
                row_stride: 1,
                col_stride: k,
            };
            let block = matmul(part.len(), m, n, xt, Operand::rows(g, m), None);
            dwt[part.start * m..part.end * m].copy_from_slice(&block);
        }
        sparse
            .all()
            .add_weight_grads(g, m, &mut dwt[columns.start * m..columns.end * m]);
        count_flops(2 * m * sparse.all().nonzeros());
        let mut dw = vec![0f32; m * k];
        for (c, row) in dwt.chunks_exact(m).enumerate() {
            for (j, &v) in row.iter().enumerate() {
                dw[j * k + c] = v;
            }
        }
        dw
    }

    /// The gradients of `x` `[N, in]` and of the weight for `y = x Wᵀ` (each if wanted):
    /// `dx = g W`, `dW = gᵀ x`.
    pub(super) fn bwd_xw(
        &self,
        x: &Tensor,
        w: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (want_x, want_w) = (wants_grad(x), wants_grad(w));
        let (rows, input) = dims2(x)?;
        let (output, _) = dims2(w)?;
        let (dx, dw) = read(grad, |g| {
            let dx = want_x.then(|| {
                read(w, |wv| {
                    let wv = Operand::rows(wv, input);
                    Ok(matmul(
                        rows,
                        input,
                        output,
                        Operand::rows(g, output),
                        wv,
                        None,
                    ))
                })
            });
            let dw = want_w.then(|| {
                read(x, |xv| {
                    let gathered = self.gathered.as_ref().and_then(|kept| {
                        kept.lock().unwrap_or_else(PoisonError::into_inner).take()
                    });
                    if let Some((columns, sparse)) = self.sparse_columns(xv, input, gathered) {
                        let dims = (rows, input, output);
                        return Ok(self.sparse_weight_grad((xv, g), dims, &columns, &sparse));
                    }
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
        self.fwd((s1, l1), (s2, l2), None)
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        self.bwd_xw(x, w, grad)
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
        self.fwd((s1, l1), (s2, l2), Some((s3, l3)))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (dx, dw) = self.bwd_xw(x, w, grad)?;
        let db = if wants_grad(b) {
            let outputs = b.elem_count();
            let db = read(grad, |g| {
                let mut db = vec![0f32; outputs];
                if outputs > 0 {
                    column_sums(g, &mut db);
                }
                Ok(db)
            })?;
            Some(Tensor::from_vec(db, outputs, b.device())?)
        } else {
            None
        };
        Ok((dx, dw, db))
    }
}

/// `x Wᵀ + b` for `x` `[N, in]`, `weight` `[out, in]` and an optional `bias` `[out]`; the input
/// columns `sparse_inputs`, if given, are mostly zero and multiplied by their non-zeros
/// ([`SparseColumns`]).
pub fn linear(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    sparse_inputs: Option<Range<usize>>,
) -> Result<Tensor> {
    apply(x, weight, bias, product(weight, sparse_inputs))
}

/// The op of `x Wᵀ` for `weight` `[out, in]` whose input columns `sparse` are mostly zero.
pub(super) fn product(weight: &Tensor, sparse: Option<Range<usize>>) -> Linear {
    // the non-zeros are kept from the forward pass only for a weight gradient computed here
    let gathered = (sparse.is_some() && wants_grad(weight)).then(|| Mutex::new(None));
    Linear { gathered, sparse }
}

fn apply(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>, op: Linear) -> Result<Tensor> {
    let x = x.contiguous()?;
    match bias {
        Some(b) => x.apply_op3(weight, b, op),
        None => x.apply_op2(weight, op),
    }
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::*;

    #[test]
    fn sparse_inputs_give_the_dense_products_values_and_gradients() {
        let (x, w, b) = (one_hot_input(9), var(&[6, 37], 42), var(&[6], 43));
        let composed = || {
            x.matmul(&w.t().unwrap())
                .unwrap()
                .broadcast_add(&b)
                .unwrap()
        };
        for columns in [3..35, 0..35, 3..37] {
            let sparse = Some(columns);
            same(
                linear(&x, &w, Some(&b), sparse).unwrap(),
                composed(),
                &[&x, &w, &b],
                1e-5,
            );
        }
        // a dense block under the hint is multiplied densely, with the same results
        let dense = var(&[9, 37], 44);
        same(
            linear(&dense, &w, None, Some(3..35)).unwrap(),
            dense.matmul(&w.t().unwrap()).unwrap(),
            &[&dense, &w],
            1e-5,
        );
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
            linear(&x, &w, Some(&b), None).unwrap(),
            composed,
            &[&x, &w, &b],
            1e-5,
        );
        same(
            linear(&x, &w, None, None).unwrap(),
            x.matmul(&w.t().unwrap()).unwrap(),
            &[&x, &w],
            1e-5,
        );
        // a detached weight receives no gradient; the input still does
        let y = linear(&x, &w.as_tensor().detach(), None, None).unwrap();
        let g = y.sum_all().unwrap().backward().unwrap();
        assert!(g.get(&w).is_none() && g.get(&x).is_some());
    }
}
