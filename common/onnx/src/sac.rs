//! The deterministic decision of a SAC agent ([`ctxrace_nn::policy::SacPolicy::act`] with
//! `deterministic`) as ONNX nodes.
//!
//! The state is the `F − 1` newest scans before this one, oldest first (`(F − 1)·O` values for
//! `F = frames` and scans of `O` values); an episode starts with the first scan in every place,
//! as the policy fills its emptied stack. One decision on the scan `o`:
//!
//! ```text
//! x = [state, o]                  the F frames, oldest first
//! a = tanh μ(x)                   μ: the actor's means (a ReLU MLP)
//! state_out = x without its oldest frame
//! ```
//!
//! An agent whose deterministic action is not this is refused: one that adds exploration
//! noise to every action (`explore_noise > 0`), or one that carries its frame stack into the
//! next episode (`reset_frame_stack = false`, which a first decision's fresh stack cannot
//! express).

use crate::graph::Graph;
use crate::model::{self, StateLayout, ACTION, OBS, STATE_OUT};
use crate::nets::mlp;
use crate::ExportError;
use ctxrace_nn::policy::{SacPolicy, ACT_DIM};

/// Adds the decision of `policy` to `g` (its outputs named [`ACTION`] and [`STATE_OUT`]);
/// returns its state's layout, or why it has no deterministic model.
pub fn decision(g: &mut Graph, policy: &SacPolicy) -> Result<StateLayout, ExportError> {
    if policy.explore_noise() > 0.0 {
        return Err(ExportError::ExploreNoise(policy.explore_noise()));
    }
    if !policy.resets_frame_stack() {
        return Err(ExportError::CarriedFrameStack);
    }
    let (frames, o) = (policy.frames(), policy.frame_dim());
    let layout = StateLayout(
        (1..frames)
            .rev()
            .map(|k| (format!("scan[t-{k}]"), o))
            .collect(),
    );
    // the stack, filled with the scan where an episode starts
    let repeats = g.ints(&[1, frames as i64 - 1]);
    let start = g.node("Tile", &[OBS, &repeats], vec![], "filled_stack");
    let s = model::state_in(g, &start);
    let stacked = g.concat(&[&s, OBS], "stack");
    let out = mlp(g, "actor", policy.actor(), &stacked);
    let [mean, _] = g.split(&out, [ACT_DIM; 2], "actor_out");
    let action = g.node("Tanh", &[&mean], vec![], "action");
    let (from, to, axis) = (
        g.ints(&[o as i64]),
        g.ints(&[(frames * o) as i64]),
        g.ints(&[1]),
    );
    let state_out = g.node("Slice", &[&stacked, &from, &to, &axis], vec![], "kept");
    g.output(&action, ACTION);
    g.output(&state_out, STATE_OUT);
    Ok(layout)
}
