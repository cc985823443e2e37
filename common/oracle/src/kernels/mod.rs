//! The candle custom ops around ctxrace-nn's row kernels ([`ctxrace_nn::kernels`]): each op runs
//! the kernel the networks run, forward and backward, so that the tests hold the kernel to the
//! composed candle operations, values and gradients, and the oracle's modules ([`crate::Dense`],
//! [`crate::LayerNorm`], [`crate::Rssm`]) compose them. The ops compute the gradient of an
//! argument only when it is tracked ([`Tensor::track_op`]).
//!
//! - [`linear`]: `y = x Wᵀ (+ b)`.
//! - [`linear_norm_act`]: a bias-free [`linear`] then [`norm_act`] as one operation (the product
//!   stays inside it, so the backward pass hands the normalisation's gradient straight to the
//!   product's, without a graph node, a zeroed buffer and an addition in between).
//! - [`linear`] and [`linear_norm_act`] over input columns that are mostly zero (the one-hot
//!   latent of a state) multiply over their non-zeros only ([`ctxrace_nn::kernels::SparseColumns`]).
//! - [`norm_act`]: `LayerNorm` then SiLU or the identity.
//! - [`gru_gates`]: DreamerV3's GRU update from normalised gates `[r, ĉ, u]` and the state `h`.
//! - [`straight_through_sample`]: a one-hot Gumbel-max sample of the unimix categorical whose
//!   gradient is that of its probabilities.
//! - [`categorical_kl`]: `KL(p_a ‖ p_b)` of two unimix categoricals, summed over the variables.
//! - [`twohot_decode`]: `symexp(Σ_k softmax(l)_k b_k)`.
//! - [`soft_cross_entropy`]: `−Σ_k t_k log softmax(l)_k` against fixed targets `t`.
//!
//! One file per op, each checked against the composed candle operations, values and gradients,
//! in its tests.

use candle_core::{
    bail, CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Result, Shape, Storage, Tensor,
};
use ctxrace_nn::kernels::{gemm_into, Operand};

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

/// Whether the backward pass needs the gradient of `t`.
fn wants_grad(t: &Tensor) -> bool {
    t.track_op()
}

fn dims2(t: &Tensor) -> Result<(usize, usize)> {
    match t.dims() {
        [n, d] => Ok((*n, *d)),
        other => bail!("fused kernel: expected a matrix, got shape {other:?}"),
    }
}

/// `A B` (`[m, k]` times `[k, n]`) as a new row-major `[m, n]` on the networks' gemm product
/// ([`gemm_into`], counted as theirs are); with `init` (`m·n` values) the product is added to it.
fn matmul(
    m: usize,
    n: usize,
    k: usize,
    a: Operand,
    b: Operand,
    init: Option<Vec<f32>>,
) -> Vec<f32> {
    let accumulate = init.is_some();
    let mut dst = init.unwrap_or_else(|| vec![0f32; m * n]);
    gemm_into(&mut dst, n, accumulate, (m, n, k), a, b);
    dst
}

mod categorical;
mod gru;
mod linear;
mod linear_norm;
mod norm_act;
mod twohot;

pub use categorical::{categorical_kl, straight_through_sample};
pub use gru::gru_gates;
pub use linear::linear;
pub use linear_norm::linear_norm_act;
pub use norm_act::norm_act;
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
