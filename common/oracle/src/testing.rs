//! Rows and comparisons the tests of the networks against their candle oracle share.

use candle_core::Tensor;
use ctxrace_nn::{Activation, Mlp, MlpShape, RssmConfig};
use rand::{Rng, SeedableRng};

/// Rows `[h, z, c]`: `h` of `d` and `c` of `c` normal values, `z` one-hot over `s` variables
/// of `classes`.
pub(crate) fn state_rows(
    rows: usize,
    (d, s, classes, c): (usize, usize, usize, usize),
    seed: u64,
) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let f = d + s * classes + c;
    let mut x = vec![0f32; rows * f];
    for row in x.chunks_exact_mut(f) {
        row[..d]
            .iter_mut()
            .for_each(|v| *v = rng.random_range(-1.5..1.5));
        for v in 0..s {
            row[d + v * classes + rng.random_range(0..classes)] = 1.0;
        }
        row[d + s * classes..]
            .iter_mut()
            .for_each(|v| *v = rng.random_range(-1.0..1.0));
    }
    x
}

/// `n` values uniform in `[−1, 1)` drawn from `seed`.
pub(crate) fn normal(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random_range(-1.0..1.0)).collect()
}

/// The values of a tensor, flattened.
pub(crate) fn vals(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

/// Asserts that `got` and `want` agree to `2e-4` relative, naming `what` where they do not.
pub(crate) fn close(got: &[f32], want: &[f32], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    for (i, (a, b)) in got.iter().zip(want).enumerate() {
        assert!(
            (a - b).abs() <= 2e-4 * (1.0 + b.abs()),
            "{what}[{i}]: {a} vs {b}"
        );
    }
}

/// A small MLP's sizes: 5 inputs, two hidden blocks of 7 of `act`, 3 outputs.
pub(crate) fn small_mlp(act: Activation) -> MlpShape {
    MlpShape {
        input: 5,
        units: 7,
        layers: 2,
        out: Some(3),
        act,
    }
}

/// A small RSSM's sizes, with a context and, if `learned_initial`, a learned initial state.
pub(crate) fn small_rssm(learned_initial: bool) -> RssmConfig {
    RssmConfig {
        deter: 8,
        hidden: 6,
        stoch: 3,
        classes: 4,
        unimix: 0.01,
        act_dim: 2,
        embed_dim: 5,
        context_dim: 2,
        learned_initial,
    }
}

/// Asserts that the networks `a` and `b` (of [`small_mlp`]'s input) give the same outputs, to
/// the bit, on two rows, naming `what` where they do not.
pub(crate) fn assert_same_outputs(a: &Mlp, b: &Mlp, what: &str) {
    let x: Vec<f32> = (0..10).map(|i| (i as f32 * 0.7).sin()).collect();
    let (mut ta, mut tb) = (a.trace(2), b.trace(2));
    a.forward(x.as_slice(), &mut ta, 0..2);
    b.forward(x.as_slice(), &mut tb, 0..2);
    assert_eq!(a.output(&ta, 0..2), b.output(&tb, 0..2), "{what}");
}
