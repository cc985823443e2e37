//! The deterministic decision of a DreamerV3, cRSSM or cMask agent
//! ([`ctxrace_nn::policy::DreamerPolicy::act`] with `deterministic`) as ONNX nodes.
//!
//! The state is `[h, z, a_{t−1}]` (`D + Z + 2` values: the GRU state, the one-hot latent, the
//! previous action); an episode starts from the policy's `(h_0, z_0)` and a zero action. One
//! decision on the scan `o` and the raw context `c`:
//!
//! ```text
//! m  = mask(tanh μ_mask(o))                 cMask: (a + 1)/2 ("unit") or σ(a) ("paper-code")
//! c' = c / context_divisor · m              cRSSM without m; DreamerV3 reads no context
//! e  = encoder(symlog o)                    symlog [o, a_{t−1}] with step_alignment = "paper-code"
//! u  = SiLU(LN([z, a_{t−1}, c'] W_inᵀ))
//! [r̂, ĉ, û] = LN([u, h] W_gᵀ)
//! r = σ(r̂),  ĉ' = tanh(r ĉ),  k = σ(û − 1),  h' = k ĉ' + (1 − k) h
//! l  = SiLU(LN([h', e] W_qᵀ)) W_rᵀ + b_r    the posterior's logits, S variables of C classes
//! z' = onehot(argmax_j ((1 − u_mix) softmax(l)_j + u_mix / C))   per variable: the mode
//! a  = tanh μ_actor([h', z', c'])
//! ```
//!
//! The mode is the class the policy's Gumbel-max sample takes with its equal noise (the first of
//! the most probable classes).

use crate::graph::{Attr, Graph};
use crate::model::{self, StateLayout, ACTION, CONTEXT, MASK, OBS, STATE_OUT};
use crate::nets::{layer, mlp};
use ctxrace_config::agents::{MaskSpace, StepAlignment, CONTEXT_DIM};
use ctxrace_nn::kernels::UPDATE_SHIFT;
use ctxrace_nn::policy::{DreamerPolicy, ACT_DIM};
use ctxrace_nn::Mlp;

/// Adds the decision of `policy` to `g` (its outputs named [`ACTION`], [`STATE_OUT`] and,
/// for cMask, [`MASK`]); returns its state's layout.
pub fn decision(g: &mut Graph, policy: &DreamerPolicy) -> StateLayout {
    let cfg = policy.config();
    let nets = policy.nets();
    let rc = *nets.rssm.config();
    let (d, z) = (rc.deter, rc.stoch * rc.classes);
    let parts = [("h", d), ("z", z), ("prev_action", ACT_DIM)];
    let layout = StateLayout(parts.map(|(name, w)| (name.to_string(), w)).to_vec());
    // the state, the initial one where an episode starts
    let (h0, z0) = policy.initial_state();
    let mut start: Vec<f32> = [h0, z0].concat();
    start.resize(layout.width(), 0.0);
    let start = g.weight("initial_state", &[1, layout.width()], &start);
    let s = model::state_in(g, &start);
    let [h, zs, prev] = g.split(&s, [d, z, ACT_DIM], "state");
    // cMask's mask, then the context the networks read
    let mask = nets
        .mask
        .as_ref()
        .map(|net| mask(g, net, cfg.mask.mask_space));
    let ctx = (rc.context_dim > 0).then(|| {
        let scale = g.scalar(policy.context_scale());
        let c = g.node("Mul", &[CONTEXT, &scale], vec![], "context");
        match &mask {
            Some(m) => g.node("Mul", &[&c, m], vec![], "masked_context"),
            None => c,
        }
    });
    // the embedding
    let mut input = g.symlog(OBS);
    if cfg.step_alignment == StepAlignment::PaperCode {
        let a = g.symlog(&prev);
        input = g.concat(&[&input, &a], "encoder_input");
    }
    let embed = mlp(g, "encoder", &nets.encoder, &input);
    // the RSSM's posterior step
    let [img_in, gates, _, _, post, post_out] = nets.rssm.layers();
    let mut x = vec![zs.as_str(), prev.as_str()];
    x.extend(ctx.as_deref());
    let x = g.concat(&x, "sequence_input");
    let u = layer(g, "rssm.img_in", img_in, &x);
    let gru_in = g.concat(&[&u, &h], "gru_input");
    let p = layer(g, "rssm.gru", gates, &gru_in);
    let h = gru(g, &p, &h, d);
    let q = g.concat(&[&h, &embed], "posterior_input");
    let hidden = layer(g, "rssm.post", post, &q);
    let logits = layer(g, "rssm.post_out", post_out, &hidden);
    let zs = mode(g, &logits, (rc.stoch, rc.classes), rc.unimix as f32);
    // the actor on [h, z, c]
    let mut head = vec![h.as_str(), zs.as_str()];
    head.extend(ctx.as_deref());
    let head = g.concat(&head, "head_input");
    let out = mlp(g, "actor", &nets.actor, &head);
    let [mean, _] = g.split(&out, [ACT_DIM; 2], "actor_out");
    let action = g.node("Tanh", &[&mean], vec![], "action");
    let state_out = g.concat(&[&h, &zs, &action], "state_out");
    g.output(&action, ACTION);
    g.output(&state_out, STATE_OUT);
    if let Some(m) = &mask {
        g.output(m, MASK);
    }
    layout
}

/// cMask's mask of the scan: `mask_value(tanh μ)` of the mask actor's means, in `space`
/// ([`ctxrace_nn::dreamer::mask_value`]).
fn mask(g: &mut Graph, net: &Mlp, space: MaskSpace) -> String {
    let out = mlp(g, "mask", net, OBS);
    let [mean, _] = g.split(&out, [CONTEXT_DIM; 2], "mask_out");
    let a = g.node("Tanh", &[&mean], vec![], "mask_tanh");
    match space {
        MaskSpace::Unit => {
            let half = g.scalar(0.5);
            let scaled = g.node("Mul", &[&a, &half], vec![], "mask_half");
            g.node("Add", &[&scaled, &half], vec![], "mask")
        }
        MaskSpace::PaperCode => g.node("Sigmoid", &[&a], vec![], "mask"),
    }
}

/// DreamerV3's GRU update of `h` (`D` values) from the normalised gates `p` (`[r̂, ĉ, û]`,
/// `3 D`): `h' = k tanh(σ(r̂) ĉ) + (1 − k) h` with `k = σ(û − s)`, `s` the networks'
/// [`UPDATE_SHIFT`].
fn gru(g: &mut Graph, p: &str, h: &str, d: usize) -> String {
    let [r, c, k] = g.split(p, [d; 3], "gates");
    let one = g.scalar(1.0);
    let shift = g.scalar(UPDATE_SHIFT);
    let r = g.node("Sigmoid", &[&r], vec![], "reset");
    let rc = g.node("Mul", &[&r, &c], vec![], "reset_cand");
    let c = g.node("Tanh", &[&rc], vec![], "candidate");
    let k = g.node("Sub", &[&k, &shift], vec![], "update_pre");
    let k = g.node("Sigmoid", &[&k], vec![], "update");
    let keep = g.node("Sub", &[&one, &k], vec![], "keep");
    let new = g.node("Mul", &[&k, &c], vec![], "update_new");
    let old = g.node("Mul", &[&keep, h], vec![], "update_old");
    g.node("Add", &[&new, &old], vec![], "h")
}

/// The one-hot mode of each of the `stoch` variables of `classes` classes whose logits are the
/// rows of `logits` (`(B, stoch·classes)`), under the uniform mixture `unimix`.
fn mode(g: &mut Graph, logits: &str, (stoch, classes): (usize, usize), unimix: f32) -> String {
    let by_variable = g.ints(&[0, stoch as i64, classes as i64]);
    let l = g.node("Reshape", &[logits, &by_variable], vec![], "logits");
    let s = g.node("Softmax", &[&l], vec![Attr::Int("axis", -1)], "softmax");
    let (keep, floor) = (g.scalar(1.0 - unimix), g.scalar(unimix / classes as f32));
    let s = g.node("Mul", &[&s, &keep], vec![], "mixed");
    let p = g.node("Add", &[&s, &floor], vec![], "probs");
    let argmax = vec![Attr::Int("axis", -1), Attr::Int("keepdims", 0)];
    let best = g.node("ArgMax", &[&p], argmax, "class");
    let depth = g.ints(&[classes as i64]);
    let values = g.weight("onehot_values", &[2], &[0.0, 1.0]);
    let onehot = g.node(
        "OneHot",
        &[&best, &depth, &values],
        vec![Attr::Int("axis", -1)],
        "onehot",
    );
    let flat = g.ints(&[0, (stoch * classes) as i64]);
    g.node("Reshape", &[&onehot, &flat], vec![], "z")
}
