//! A head's first layer on imagined states at the paper's sizes (`[h, z]` of 256 + 16 x 16
//! one-hot, 256 units, the 10 x 1024 states of one imagination), forward and backward (input
//! and weight gradients), with and without telling the layer that `z` is mostly zero. `z` is
//! half the input: the forward product and the weight's gradient do about half the dense work,
//! the input's gradient (a third of it) stays dense.
#![allow(missing_docs)] // criterion's macros define undocumented functions

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarBuilder;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ctxrace_nn::kernels::NormAct;
use ctxrace_oracle::{Dense, LayerNorm};
use rand::{Rng, SeedableRng};

const ROWS: usize = 10 * 1024;
const DETER: usize = 256;
const STOCH: usize = 16;
const CLASSES: usize = 16;
const UNITS: usize = 256;

/// States `[ROWS, DETER + STOCH·CLASSES]`: a dense `h`, a one-hot `z`.
fn states() -> Tensor {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let width = DETER + STOCH * CLASSES;
    let mut x = vec![0f32; ROWS * width];
    for row in x.chunks_exact_mut(width) {
        for v in &mut row[..DETER] {
            *v = rng.random_range(-1.0..1.0);
        }
        for s in 0..STOCH {
            row[DETER + s * CLASSES + rng.random_range(0..CLASSES)] = 1.0;
        }
    }
    Tensor::from_vec(x, (ROWS, width), &Device::Cpu).expect("states")
}

fn head_layer(c: &mut Criterion) {
    let vars = candle_nn::VarMap::new();
    let vb = VarBuilder::from_varmap(&vars, DType::F32, &Device::Cpu);
    let width = DETER + STOCH * CLASSES;
    let dense = Dense::new(width, UNITS, false, vb.pp("fc")).expect("layer");
    let ln = LayerNorm::new(UNITS, 1e-3, vb.pp("ln")).expect("norm");
    let sparse = dense.clone().sparse_inputs(DETER..width);
    let x = Var::from_tensor(&states()).expect("input");
    let mut group = c.benchmark_group("head_first_layer");
    group.throughput(Throughput::Elements(ROWS as u64));
    group.sample_size(20);
    for (name, layer) in [("dense", &dense), ("sparse_inputs", &sparse)] {
        group.bench_function(name, |b| {
            b.iter(|| {
                let y = layer
                    .forward_norm_act(x.as_tensor(), &ln, NormAct::Silu)
                    .expect("forward");
                y.sum_all().expect("sum").backward().expect("backward")
            })
        });
    }
    group.finish();
}

criterion_group!(benches, head_layer);
criterion_main!(benches);
