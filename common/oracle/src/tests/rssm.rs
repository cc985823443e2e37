use crate::bridge::FromOracle;
use crate::testing::{close, normal, small_rssm, state_rows, vals};
use crate::{standalone, RssmState};
use candle_core::{Device, Tensor, Var};
use ctxrace_nn::{Rssm, StepScratch, StepTrace};

/// An imagination step's next state and its gradients in the state and the action are
/// those of the candle RSSM's sequence model, prior and sample.
#[test]
fn an_imagination_step_matches_the_candle_rssm() {
    let cfg = small_rssm(false);
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
    // the network
    let plain = Rssm::from_oracle(&rssm).unwrap();
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
