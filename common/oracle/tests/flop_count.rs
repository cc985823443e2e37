//! The matrix-product FLOP counter behind `ctxrace bench learner`'s fraction of peak counts
//! `2 m n k` per product, forward and backward, and `2 m` per non-zero of sparse input columns. (Its own test binary: the counter is the
//! process's, and no other test may run beside it.)

use candle_core::{DType, Device, Tensor, Var};
use ctxrace_nn::kernels::matmul_flops;
use ctxrace_oracle::kernels::linear;

#[test]
fn a_linear_layer_counts_its_forward_and_backward_products() {
    let (n, k, m) = (5, 3, 4);
    let dev = &Device::Cpu;
    let x = Var::from_tensor(&Tensor::ones((n, k), DType::F32, dev).unwrap()).unwrap();
    let w = Var::from_tensor(&Tensor::ones((m, k), DType::F32, dev).unwrap()).unwrap();
    let product = (2 * n * m * k) as u64;

    // a frozen layer on a constant input: the forward product only
    let before = matmul_flops();
    let y = linear(&x.as_tensor().detach(), &w.as_tensor().detach(), None, None).unwrap();
    assert_eq!(matmul_flops() - before, product);
    drop(y);

    // tracked input and weight: forward, then dx = g W and dW = gᵀ x
    let before = matmul_flops();
    let y = linear(x.as_tensor(), w.as_tensor(), None, None).unwrap();
    y.sum_all().unwrap().backward().unwrap();
    assert_eq!(matmul_flops() - before, 3 * product);

    // input columns 3..35 told sparse, one non-zero each row there: the dense columns' product
    // and 2 m operations per non-zero, forward and for the weight's gradient; dx stays dense
    let k = 35;
    let mut values = vec![0f32; n * k];
    for i in 0..n {
        values[i * k..i * k + 3].fill(1.0);
        values[i * k + 3 + 5 * i] = 2.0;
    }
    let x = Var::from_tensor(&Tensor::from_vec(values, (n, k), dev).unwrap()).unwrap();
    let w = Var::from_tensor(&Tensor::ones((m, k), DType::F32, dev).unwrap()).unwrap();
    let (dense_part, sparse_part) = ((2 * n * m * 3) as u64, (2 * m * n) as u64);
    let before = matmul_flops();
    let y = linear(x.as_tensor(), w.as_tensor(), None, Some(3..k)).unwrap();
    assert_eq!(matmul_flops() - before, dense_part + sparse_part);
    y.sum_all().unwrap().backward().unwrap();
    let dx = (2 * n * m * k) as u64;
    assert_eq!(matmul_flops() - before, 2 * (dense_part + sparse_part) + dx);
}
