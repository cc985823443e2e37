//! The gemm calls recorded for `ctxrace bench learner`'s products' ceiling are those a layer
//! runs, with their shapes and strides, and nothing while recording is off. (Its own test binary:
//! the recording is the process's, and no other test may run beside it.)

use candle_core::{DType, Device, Tensor, Var};
use ctxrace_nn::kernels::{
    matmul_flops, record_products, recorded_products, rerun_products, ProductShape,
};
use ctxrace_oracle::kernels::linear;

#[test]
fn a_layer_records_its_three_products_and_they_replay() {
    let (n, k, m) = (5, 3, 4);
    let dev = &Device::Cpu;
    let x = Var::from_tensor(&Tensor::ones((n, k), DType::F32, dev).unwrap()).unwrap();
    let w = Var::from_tensor(&Tensor::ones((m, k), DType::F32, dev).unwrap()).unwrap();

    // off: a forward and backward pass leaves nothing recorded
    record_products(false);
    let y = linear(x.as_tensor(), w.as_tensor(), None, None).unwrap();
    y.sum_all().unwrap().backward().unwrap();
    assert!(recorded_products().is_empty());

    // on: the forward product, dx = g W and dW = gᵀ x, each with its shape, as counted
    let before = matmul_flops();
    record_products(true);
    let y = linear(x.as_tensor(), w.as_tensor(), None, None).unwrap();
    y.sum_all().unwrap().backward().unwrap();
    record_products(false);
    let calls = recorded_products();
    let mut dims: Vec<_> = calls.iter().map(|c| c.dims).collect();
    dims.sort();
    let mut expected = vec![(n, m, k), (n, k, m), (m, k, n)];
    expected.sort();
    assert_eq!(dims, expected);
    let flops: u64 = calls.iter().map(ProductShape::flops).sum();
    assert_eq!(flops, matmul_flops() - before);

    // the rerun runs them (uncounted) and takes some time
    let counted = matmul_flops();
    let seconds = rerun_products(&calls);
    assert!(seconds > 0.0 && seconds.is_finite());
    assert_eq!(matmul_flops(), counted);

    // turning recording on again starts afresh
    record_products(true);
    record_products(false);
    assert!(recorded_products().is_empty());
}

#[test]
fn a_replay_of_nothing_takes_no_time() {
    assert_eq!(rerun_products(&[]), 0.0);
}
