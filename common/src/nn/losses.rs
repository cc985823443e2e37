//! Networks on plain row-major `f32` buffers, differentiated by hand: the learner's behaviour
//! step (imagination through the RSSM, the heads, the losses, over thousands of rows a shard)
//! runs on these rather than through candle's graph.
//!
//! candle records a node and allocates a tensor per operation, and its backward pass gives every
//! edge a zeroed gradient buffer to add into, copies for each concatenation and slice, and
//! cannot skip a gradient nobody reads (the first imagined state's, the critic's last row's).
//! Here a forward pass writes into buffers a caller keeps from one training step to the next
//! ([`MlpTrace`], [`StepTrace`]), and a backward pass computes just the gradients it is asked for,
//! on the same fused row kernels and gemm products as the candle modules
//! ([`crate::nn::kernels`]). The weights are copied out of the candle modules they mirror
//! ([`PlainMlp::new`], [`PlainRssm::new`]) or read by name from the learner's weights
//! ([`PlainMlp::from_weights`], [`PlainRssm::from_weights`]: the acting policies run on these at
//! batch 1, [`PlainRssm::posterior_step`]) and the parameters' gradients go back as candle
//! tensors keyed by them ([`PlainMlp::add_grads_to`]), so optimisers and checkpoints are
//! unchanged. Each piece is checked against its candle module, values and gradients.

mod layer;
mod parameters;
mod rssm;

pub use layer::{InputGrad, LayerGrads, MlpGrads, MlpTrace, NonZeros, PlainLayer, PlainMlp, Rows};
pub use parameters::{
    copy, count, ctxrace_draw, fan_avg_draw, init, init_with, load_safetensors, polyak,
    to_safetensors, update_each, Draw, NamedTensor, Parameters,
};
pub use rssm::{ObserveTrace, PlainRssm, RssmGrads, StepScratch, StepTrace};

use super::kernels::{
    cross_entropy_rows, cross_entropy_rows_bwd, decode_rows, decode_rows_bwd, kl_rows, kl_rows_bwd,
    Unimix,
};

/// `out_i = symexp(Σ_k softmax(l_i)_k b_k)` for the rows `l_i` of `logits` (`bins.len()` values
/// each): the two-hot heads' decoded values ([`crate::nn::TwoHot::decode`]).
pub fn twohot_decode(logits: &[f32], bins: &[f32], out: &mut [f32]) {
    decode_rows(logits, bins, out);
}

/// The backward pass of [`twohot_decode`]: `dl` from the values' gradients `g`.
pub fn twohot_decode_backward(logits: &[f32], bins: &[f32], g: &[f32], dl: &mut [f32]) {
    decode_rows_bwd(logits, bins, g, dl);
}

/// `out_i = −Σ_k t_ik log softmax(l_i)_k` for the rows of `logits` and of fixed `targets`
/// ([`crate::nn::kernels::soft_cross_entropy`]).
pub fn soft_cross_entropy(logits: &[f32], targets: &[f32], out: &mut [f32]) {
    if !out.is_empty() {
        cross_entropy_rows(logits, targets, out);
    }
}

/// The backward pass of [`soft_cross_entropy`]: `dl` from the losses' gradients `g`.
pub fn soft_cross_entropy_backward(logits: &[f32], targets: &[f32], g: &[f32], dl: &mut [f32]) {
    if !g.is_empty() {
        cross_entropy_rows_bwd(logits, targets, g, dl);
    }
}

/// `out_i = KL(p_a ‖ p_b)` of the unimix categoricals (`classes` each, mixed with `unimix`
/// uniform) with logits the rows `a_i` and `b_i`, summed over each row's variables
/// ([`crate::nn::kernels::categorical_kl`]).
pub fn categorical_kl(a: &[f32], b: &[f32], classes: usize, unimix: f32, out: &mut [f32]) {
    out.fill(0.0);
    if out.is_empty() || classes == 0 {
        return;
    }
    let per_row = a.len() / out.len();
    kl_rows(Unimix { classes, unimix }, a, b, per_row, out);
}

/// The backward pass of [`categorical_kl`] from the divergences' gradients `g`: the logits'
/// gradients into `da` and `db`, each left alone when empty.
pub fn categorical_kl_backward(
    a: &[f32],
    b: &[f32],
    g: &[f32],
    (classes, unimix): (usize, f32),
    (da, db): (&mut [f32], &mut [f32]),
) {
    if g.is_empty() || classes == 0 {
        return;
    }
    let per_row = a.len() / g.len();
    kl_rows_bwd(Unimix { classes, unimix }, a, b, g, per_row, da, db);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::rssm::standalone;
    use crate::nn::{Activation, Mlp, ParamStore, RssmConfig, RssmState};
    use candle_core::{Device, Tensor, Var};
    use rand::{Rng, SeedableRng};

    /// Networks built from [`crate::nn::Weights::initial`] and initialised from a seed are, to
    /// the byte, the candle modules the same seed initialised (names, shapes, values: a seed
    /// still gives the same run), and they save and load their weights.
    #[test]
    fn networks_initialised_in_place_are_the_candle_stores_to_the_byte() {
        let rssm_cfg = RssmConfig {
            deter: 8,
            hidden: 6,
            stoch: 3,
            classes: 4,
            unimix: 0.01,
            act_dim: 2,
            embed_dim: 5,
            context_dim: 2,
            learned_initial: true,
        };
        for act in [Activation::SiluNorm, Activation::Relu] {
            let shape = crate::nn::MlpShape {
                input: 5,
                units: 7,
                layers: 2,
                out: Some(3),
                act,
            };
            let store = ParamStore::new();
            Mlp::new(5, 7, 2, Some(3), act, store.builder().pp("encoder")).unwrap();
            crate::nn::Rssm::new(rssm_cfg, store.builder().pp("rssm")).unwrap();
            store.init(19).unwrap();
            let mut fresh = crate::nn::Weights::initial();
            let mut encoder = PlainMlp::from_weights(&mut fresh, "encoder.", &shape).unwrap();
            let mut rssm = PlainRssm::from_weights(&mut fresh, "rssm.", rssm_cfg).unwrap();
            fresh.finish().unwrap();
            let nets: &mut [&mut dyn Parameters] = &mut [&mut encoder, &mut rssm];
            init(nets, 19);
            let bytes = to_safetensors(nets).unwrap();
            assert_eq!(bytes, store.to_bytes().unwrap(), "{act:?}");
            assert_eq!(count(nets), store.count());
            init(nets, 20);
            assert_ne!(to_safetensors(nets).unwrap(), bytes);
            load_safetensors(nets, &bytes).unwrap();
            assert_eq!(to_safetensors(nets).unwrap(), bytes);
            // the forward pass reads the loaded weights (the transpose is refreshed)
            let copied = PlainMlp::new(
                &Mlp::new(5, 7, 2, Some(3), act, store.builder().pp("encoder")).unwrap(),
            )
            .unwrap();
            let x: Vec<f32> = (0..10).map(|i| (i as f32 * 0.7).sin()).collect();
            let (mut a, mut b) = (encoder.trace(2), copied.trace(2));
            encoder.forward(x.as_slice(), &mut a, 0..2);
            copied.forward(x.as_slice(), &mut b, 0..2);
            assert_eq!(encoder.output(&a, 0..2), copied.output(&b, 0..2), "{act:?}");
        }
    }

    /// Weights of another architecture are refused by name and leave the network unchanged;
    /// Polyak averaging and copies blend tensor by tensor.
    #[test]
    fn loading_checks_names_and_polyak_blends() {
        let shape = |units| crate::nn::MlpShape {
            input: 3,
            units,
            layers: 1,
            out: Some(2),
            act: Activation::Relu,
        };
        let build = |units, seed| {
            let mut net =
                PlainMlp::from_weights(&mut crate::nn::Weights::initial(), "q.", &shape(units))
                    .unwrap();
            init(&mut net, seed);
            net
        };
        let (mut a, b, other) = (build(4, 1), build(4, 2), build(5, 1));
        let before = to_safetensors(&a).unwrap();
        let err = load_safetensors(&mut a, &to_safetensors(&other).unwrap()).unwrap_err();
        assert!(err.to_string().contains("q.l0.fc.weight"), "{err}");
        assert_eq!(to_safetensors(&a).unwrap(), before);
        let original = a.clone();
        polyak(&mut a, &b, 0.25);
        for ((x, y), z) in a.tensors().iter().zip(b.tensors()).zip(original.tensors()) {
            for ((x, y), z) in x.values.iter().zip(y.values).zip(z.values) {
                assert_eq!(*x, z * 0.75 + y * 0.25);
            }
        }
        copy(&mut a, &b);
        assert_eq!(to_safetensors(&a).unwrap(), to_safetensors(&b).unwrap());
    }

    /// A network read by name from the learner's weights is the one copied out of its candle
    /// module, for both activations and under a prefix.
    #[test]
    fn a_network_read_by_name_equals_the_one_copied_from_its_candle_module() {
        for act in [Activation::SiluNorm, Activation::Relu] {
            let store = ParamStore::new();
            let mlp = Mlp::new(5, 7, 2, Some(3), act, store.builder().pp("encoder")).unwrap();
            store.init(11).unwrap();
            let shape = crate::nn::MlpShape {
                input: 5,
                units: 7,
                layers: 2,
                out: Some(3),
                act,
            };
            let mut weights =
                crate::nn::Weights::from_safetensors(&store.to_bytes().unwrap()).unwrap();
            let read = PlainMlp::from_weights(&mut weights, "encoder.", &shape).unwrap();
            weights.finish().unwrap();
            let copied = PlainMlp::new(&mlp).unwrap();
            let x: Vec<f32> = (0..10).map(|i| (i as f32 * 0.7).sin()).collect();
            let (mut a, mut b) = (read.trace(2), copied.trace(2));
            read.forward(x.as_slice(), &mut a, 0..2);
            copied.forward(x.as_slice(), &mut b, 0..2);
            assert_eq!(read.output(&a, 0..2), copied.output(&b, 0..2), "{act:?}");
        }
    }

    /// Rows `[h, z, c]`: `h` of `d` and `c` of `c` normal values, `z` one-hot over `s` variables
    /// of `classes`.
    fn state_rows(
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

    fn normal(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| rng.random_range(-1.0..1.0)).collect()
    }

    fn vals(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1().unwrap()
    }

    fn close(got: &[f32], want: &[f32], what: &str) {
        assert_eq!(got.len(), want.len(), "{what}: lengths");
        for (i, (a, b)) in got.iter().zip(want).enumerate() {
            assert!(
                (a - b).abs() <= 2e-4 * (1.0 + b.abs()),
                "{what}[{i}]: {a} vs {b}"
            );
        }
    }

    /// A plain MLP's outputs, input gradient and parameter gradients are the candle module's,
    /// over all rows and over a range of them, with sparse inputs, LayerNorm + SiLU and ReLU.
    #[test]
    fn plain_mlps_match_the_candle_modules() {
        let dims = (4, 4, 16, 2);
        let (f, rows) = (4 + 64 + 2, 37);
        for act in [Activation::SiluNorm, Activation::Relu] {
            let ps = ParamStore::new();
            let mlp = Mlp::new(f, 24, 2, Some(5), act, ps.builder().pp("m"))
                .unwrap()
                .sparse_inputs(4..68);
            ps.init(3).unwrap();
            let x = state_rows(rows, dims, 1);
            let w = normal(rows * 5, 2);
            let xv = Var::from_vec(x.clone(), (rows, f), &Device::Cpu).unwrap();
            let wt = Tensor::from_vec(w.clone(), (rows, 5), &Device::Cpu).unwrap();
            let plain = PlainMlp::new(&mlp).unwrap();
            let mut trace = plain.trace(rows);
            plain.forward(&x, &mut trace, 0..rows);
            for span in [0..rows, 5..16] {
                // the candle loss over the rows `span` only
                let rows_of_x = xv.as_tensor().narrow(0, span.start, span.len()).unwrap();
                let y = candle_core::Module::forward(&mlp, &rows_of_x).unwrap();
                let loss = y
                    .mul(&wt.narrow(0, span.start, span.len()).unwrap())
                    .unwrap();
                let want = loss.sum_all().unwrap().backward().unwrap();
                close(plain.output(&trace, span.clone()), &vals(&y), "output");
                let mut grads = plain.zero_grads();
                let mut dx = vec![0f32; rows * f];
                let xs = &x[span.start * f..span.end * f];
                let dy = &w[span.start * 5..span.end * 5];
                let target = InputGrad {
                    data: &mut dx[span.start * f..],
                    row_stride: f,
                    columns: 0..f,
                    accumulate: false,
                };
                plain.backward(
                    xs,
                    &mut trace,
                    span.clone(),
                    dy,
                    Some(&mut grads),
                    Some(target),
                );
                close(
                    &dx,
                    &vals(want.get(xv.as_tensor()).unwrap()),
                    "input gradient",
                );
                let mut got = candle_core::backprop::GradStore::default();
                plain.add_grads_to(grads, &mlp, &mut got).unwrap();
                for (name, v) in ps.named() {
                    let g =
                        |s: &candle_core::backprop::GradStore| vals(s.get(v.as_tensor()).unwrap());
                    close(&g(&got), &g(&want), &name);
                }
            }
        }
    }

    /// A plain imagination step's next state and its gradients in the state and the action are
    /// those of the candle RSSM's sequence model, prior and sample.
    #[test]
    fn a_plain_imagination_step_matches_the_rssm() {
        let cfg = RssmConfig {
            deter: 8,
            hidden: 6,
            stoch: 3,
            classes: 4,
            unimix: 0.01,
            act_dim: 2,
            embed_dim: 5,
            context_dim: 2,
            learned_initial: false,
        };
        let (_, rssm) = standalone(cfg, 4).unwrap();
        let (n, f) = (9, 8 + 12 + 2);
        let state = state_rows(n, (8, 3, 4, 2), 5);
        let action = normal(n * 2, 6);
        let uniform: Vec<f32> = normal(n * 12, 7).iter().map(|v| 0.5 + 0.45 * v).collect();
        let d_next = normal(n * f, 8);
        // candle
        let dev = &Device::Cpu;
        let column = |lo: usize, w: usize| {
            let t = Tensor::from_vec(state.clone(), (n, f), dev).unwrap();
            Var::from_tensor(&t.narrow(1, lo, w).unwrap().contiguous().unwrap()).unwrap()
        };
        let (deter, stoch, ctx) = (column(0, 8), column(8, 12), column(20, 2));
        let act = Var::from_vec(action.clone(), (n, 2), dev).unwrap();
        let prev = RssmState {
            deter: deter.as_tensor().clone(),
            stoch: stoch.as_tensor().clone(),
        };
        let u = Tensor::from_vec(uniform.clone(), (n, 3, 4), dev).unwrap();
        let frozen = rssm.frozen();
        let next_deter = frozen
            .deter_step(&prev, act.as_tensor(), Some(ctx.as_tensor()))
            .unwrap();
        let next_stoch = frozen
            .sample(&frozen.prior_logits(&next_deter).unwrap(), &u)
            .unwrap();
        let next = RssmState {
            deter: next_deter,
            stoch: next_stoch,
        };
        let g = Tensor::from_vec(d_next.clone(), (n, f), dev).unwrap();
        let loss = (next
            .deter
            .mul(&g.narrow(1, 0, 8).unwrap())
            .unwrap()
            .sum_all()
            .unwrap()
            + next
                .stoch
                .mul(&g.narrow(1, 8, 12).unwrap())
                .unwrap()
                .sum_all()
                .unwrap())
        .unwrap();
        let want = loss.backward().unwrap();
        // plain
        let plain = PlainRssm::new(&rssm).unwrap();
        let mut trace = StepTrace::default();
        let mut got_next = vec![0f32; n * f];
        plain.step(&state, &action, &uniform, &mut trace, &mut got_next);
        let part = |rows: &[f32], lo: usize, w: usize| -> Vec<f32> {
            rows.chunks_exact(f)
                .flat_map(|r| r[lo..lo + w].to_vec())
                .collect()
        };
        close(&part(&got_next, 0, 8), &vals(&next.deter), "h'");
        close(&part(&got_next, 8, 12), &vals(&next.stoch), "z'");
        close(&part(&got_next, 20, 2), &part(&state, 20, 2), "c");
        let mut d_action = vec![0f32; n * 2];
        let mut d_state = vec![0f32; n * f];
        let mut scratch = StepScratch::default();
        plain.step_backward(
            &mut trace,
            &d_next,
            &mut d_action,
            Some(&mut d_state),
            &mut scratch,
        );
        close(&d_action, &vals(want.get(act.as_tensor()).unwrap()), "∂a");
        close(
            &part(&d_state, 0, 8),
            &vals(want.get(deter.as_tensor()).unwrap()),
            "∂h",
        );
        close(
            &part(&d_state, 8, 12),
            &vals(want.get(stoch.as_tensor()).unwrap()),
            "∂z",
        );
    }
}
