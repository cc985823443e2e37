//! LayerNorm then SiLU (or the identity, as before the GRU's gates) over the activations of one
//! imagination step at the paper's sizes (a shard's 512 states, 256 units; 768 gates): the
//! forward pass alone, and forward and backward of their sum as one node of a training step's
//! graph costs it, candle's gradient bookkeeping included (the output's and the input's
//! gradients each a zeroed buffer plus an addition, in candle's own elementwise kernels).
#![allow(missing_docs)] // criterion's macros define undocumented functions

use candle_core::{Device, Var};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ctxrace_nn::kernels::NormAct;
use ctxrace_oracle::kernels::norm_act;
use rand::{Rng, SeedableRng};

const ROWS: usize = 512;

/// The allocator of the `ctxrace` binary.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn values(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random_range(-2.0..2.0)).collect()
}

fn norm_act_passes(c: &mut Criterion) {
    // one thread, as the learner runs each shard
    ctxrace_oracle::candle_on_one_thread();
    let mut group = c.benchmark_group("norm_act");
    group.sample_size(30);
    for (act, width) in [(NormAct::Silu, 256), (NormAct::Identity, 768)] {
        let dev = &Device::Cpu;
        let x = Var::from_vec(values(ROWS * width, 1), (ROWS, width), dev).expect("input");
        let gain = Var::from_vec(values(width, 2), width, dev).expect("gain");
        let bias = Var::from_vec(values(width, 3), width, dev).expect("bias");
        group.throughput(Throughput::Elements((ROWS * width) as u64));
        group.bench_function(format!("{act:?}_{width}_forward"), |b| {
            b.iter(|| norm_act(&x, &gain, &bias, 1e-3, act).expect("forward"))
        });
        group.bench_function(format!("{act:?}_{width}_forward_backward"), |b| {
            b.iter(|| {
                norm_act(&x, &gain, &bias, 1e-3, act)
                    .and_then(|y| y.sum_all())
                    .and_then(|l| l.backward())
                    .expect("backward")
            })
        });
    }
    group.finish();
}

criterion_group!(benches, norm_act_passes);
criterion_main!(benches);
