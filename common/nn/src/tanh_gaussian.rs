//! A tanh-squashed diagonal Gaussian policy, SAC's actor (and cMask's mask actor), on rows.
//!
//! An MLP maps the observation `o` to a mean `μ` and a log standard deviation `log σ` (clamped to
//! `[−5, 2]` unless a config's `log_std_clamp` sets other bounds). An action is drawn by
//! reparameterisation from noise `ε ~ N(0, I)` that the caller draws from its own seeded
//! generator:
//!
//! ```text
//! u = μ + σ ε,    a = tanh(u) ∈ (−1, 1)^A
//! log π(a | o) = Σ_j [ log N(u_j; μ_j, σ_j) − log(1 − tanh² u_j) ]
//! log N(u; μ, σ) = −ε²/2 − log σ − log(2π)/2
//! ```
//!
//! `1 − tanh² u` underflows to zero for `|u| ≳ 9` in `f32`, so the Jacobian term uses the stable
//! identity `log(1 − tanh² u) = 2 (log 2 − u − softplus(−2u))`. Expanding
//! `softplus(x) = max(x, 0) + log(1 + e^{−|x|})` gives the form computed here,
//! `2 (log 2 − |u| − log(1 + e^{−2|u|}))`, whose every piece is bounded and whose gradient at
//! `u = 0` is the exact `0` (a literal `max(x, 0)` would give a one-sided gradient there).

pub use ctxrace_config::agents::{LOG_STD_CLAMP, LOG_STD_MAX, LOG_STD_MIN};

/// The squashed sample of the module doc on rows (the learner's hand-differentiated SAC; the
/// oracle's `squash` on candle tensors): from the actor's outputs `out` (`[B, 2A]`: means,
/// then log standard deviations before the clamp to `log_std_clamp`) and the noise `[B, A]`,
/// the actions into `action` `[B, A]` and their log-probabilities into `log_prob` `[B]`.
pub fn squash_rows(
    out: &[f32],
    noise: &[f32],
    [lo, hi]: [f32; 2],
    action: &mut [f32],
    log_prob: &mut [f32],
) {
    let a = noise.len() / log_prob.len().max(1);
    let half_ln_2pi = 0.5 * (2.0 * std::f32::consts::PI).ln();
    let rows = out.chunks_exact(2 * a).zip(noise.chunks_exact(a));
    for ((o, eps), (act, lp)) in rows.zip(action.chunks_exact_mut(a).zip(log_prob.iter_mut())) {
        *lp = 0.0;
        for j in 0..a {
            let log_std = o[a + j].clamp(lo, hi);
            let u = o[j] + log_std.exp() * eps[j];
            act[j] = u.tanh();
            let log_jacobian =
                2.0 * (std::f32::consts::LN_2 - u.abs() - (-2.0 * u.abs()).exp().ln_1p());
            *lp += -0.5 * eps[j] * eps[j] - log_std - half_ln_2pi - log_jacobian;
        }
    }
}

/// The backward pass of [`squash_rows`] (the same noise and log-std bounds): the outputs'
/// gradients `d_out` `[B, 2A]` from the
/// actions' `d_action` `[B, A]` and the log-probabilities' `d_log_prob` `[B]`. With
/// `u = μ + σ ε`: `∂u = ∂a (1 − a²) + 2 a ∂log π` (`∂ −log(1 − tanh² u)/∂u = 2 tanh u`),
/// `∂μ = ∂u`, `∂log σ = ∂u σ ε − ∂log π` inside the clamp (half at its bounds, as candle's
/// `clamp` splits a tie; none beyond them).
pub fn squash_rows_backward(
    out: &[f32],
    (noise, [lo, hi]): (&[f32], [f32; 2]),
    action: &[f32],
    (d_action, d_log_prob): (&[f32], &[f32]),
    d_out: &mut [f32],
) {
    let a = noise.len() / d_log_prob.len().max(1);
    for (i, (d, &dlp)) in d_out.chunks_exact_mut(2 * a).zip(d_log_prob).enumerate() {
        for j in 0..a {
            let (k, raw) = (i * a + j, out[i * 2 * a + a + j]);
            let act = action[k];
            let du = d_action[k] * (1.0 - act * act) + 2.0 * act * dlp;
            d[j] = du;
            let inside = if lo < raw && raw < hi {
                1.0
            } else if raw == lo || raw == hi {
                0.5
            } else {
                0.0
            };
            let std = raw.clamp(lo, hi).exp();
            d[a + j] = inside * (du * std * noise[k] - dlp);
        }
    }
}
