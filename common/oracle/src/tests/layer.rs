use crate::bridge::{AddGradsTo, FromOracle};
use crate::testing::{assert_same_outputs, close, normal, small_mlp, state_rows, vals};
use crate::{Mlp as CandleMlp, ParamStore};
use candle_core::{Device, Tensor, Var};
use ctxrace_nn::{Activation, InputGrad, Mlp, Weights};

/// A network read by name from the learner's weights is the one copied out of its candle
/// module, for both activations and under a prefix.
#[test]
fn a_network_read_by_name_equals_the_one_copied_from_its_candle_module() {
    for act in [Activation::SiluNorm, Activation::Relu] {
        let store = ParamStore::new();
        let mlp = CandleMlp::new(5, 7, 2, Some(3), act, store.builder().pp("encoder")).unwrap();
        store.init(11).unwrap();
        let shape = small_mlp(act);
        let mut weights = Weights::from_safetensors(&store.to_bytes().unwrap()).unwrap();
        let read = Mlp::from_weights(&mut weights, "encoder.", &shape).unwrap();
        weights.finish().unwrap();
        let copied = Mlp::from_oracle(&mlp).unwrap();
        assert_same_outputs(&read, &copied, &format!("{act:?}"));
    }
}

/// An MLP's outputs, input gradient and parameter gradients are the candle module's,
/// over all rows and over a range of them, with sparse inputs, LayerNorm + SiLU and ReLU.
#[test]
fn mlps_match_their_candle_oracle() {
    let dims = (4, 4, 16, 2);
    let (f, rows) = (4 + 64 + 2, 37);
    for act in [Activation::SiluNorm, Activation::Relu] {
        let ps = ParamStore::new();
        let mlp = CandleMlp::new(f, 24, 2, Some(5), act, ps.builder().pp("m"))
            .unwrap()
            .sparse_inputs(4..68);
        ps.init(3).unwrap();
        let x = state_rows(rows, dims, 1);
        let w = normal(rows * 5, 2);
        let xv = Var::from_vec(x.clone(), (rows, f), &Device::Cpu).unwrap();
        let wt = Tensor::from_vec(w.clone(), (rows, 5), &Device::Cpu).unwrap();
        let plain = Mlp::from_oracle(&mlp).unwrap();
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
                let g = |s: &candle_core::backprop::GradStore| vals(s.get(v.as_tensor()).unwrap());
                close(&g(&got), &g(&want), &name);
            }
        }
    }
}
