//! A tanh-squashed diagonal Gaussian policy, SAC's actor.
//!
//! An MLP maps the observation `o` to a mean `μ` and a log standard deviation `log σ` (clamped to
//! `[−5, 2]` unless [`TanhGaussianActor::with_log_std_clamp`] sets other bounds). An action is drawn by reparameterisation from noise `ε ~ N(0, I)` that the caller
//! draws from its own seeded generator (candle's CPU generator cannot be seeded):
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

#[cfg(any(test, feature = "oracle"))]
use super::mlp::{Activation, Mlp};
#[cfg(any(test, feature = "oracle"))]
use candle_core::{Module, Result, Tensor, D};
#[cfg(any(test, feature = "oracle"))]
use candle_nn::VarBuilder;

/// Lower bound of the log standard deviation.
pub const LOG_STD_MIN: f64 = -5.0;
/// Upper bound of the log standard deviation.
pub const LOG_STD_MAX: f64 = 2.0;

/// The default bounds `[LOG_STD_MIN, LOG_STD_MAX]` of the log standard deviation.
pub const LOG_STD_CLAMP: [f64; 2] = [LOG_STD_MIN, LOG_STD_MAX];

/// Bounds of the log standard deviation that are not finite or not increasing, by their config
/// key.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error(
    "{key} must be two finite bounds [lower, upper] with lower < upper, got [{}, {}] \
     (ctxrace's default is [{LOG_STD_MIN}, {LOG_STD_MAX}], the paper's code's [-20, 2])",
    .bounds[0],
    .bounds[1]
)]
pub struct LogStdClampError {
    /// The config key.
    pub key: String,
    /// The bounds `[lower, upper]` given.
    pub bounds: [f64; 2],
}

/// Checks bounds of the log standard deviation (finite, lower below upper), naming the config
/// key `key` in the error.
pub fn validate_log_std_clamp(
    key: &str,
    [lo, hi]: [f64; 2],
) -> std::result::Result<(), LogStdClampError> {
    if lo.is_finite() && hi.is_finite() && lo < hi {
        Ok(())
    } else {
        Err(LogStdClampError {
            key: key.to_string(),
            bounds: [lo, hi],
        })
    }
}

/// A tanh-squashed Gaussian policy `π(a | o)` over actions in `(−1, 1)^A` (see the module doc).
#[cfg(any(test, feature = "oracle"))]
#[derive(Clone, Debug)]
pub struct TanhGaussianActor {
    net: Mlp,
    act_dim: usize,
    log_std_clamp: [f64; 2],
}

#[cfg(any(test, feature = "oracle"))]
impl TanhGaussianActor {
    /// A ReLU MLP of `layers` hidden layers of `units` from `obs_dim` inputs to `2 · act_dim`
    /// outputs (means, then log standard deviations), built under `vb`.
    pub fn new(
        obs_dim: usize,
        act_dim: usize,
        units: usize,
        layers: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        let net = Mlp::new(
            obs_dim,
            units,
            layers,
            Some(2 * act_dim),
            Activation::Relu,
            vb,
        )?;
        Ok(Self {
            net,
            act_dim,
            log_std_clamp: LOG_STD_CLAMP,
        })
    }

    /// The same actor with its log standard deviation clamped to `[lower, upper]`.
    pub fn with_log_std_clamp(self, log_std_clamp: [f64; 2]) -> Self {
        Self {
            log_std_clamp,
            ..self
        }
    }

    /// The bounds `[lower, upper]` of the log standard deviation.
    pub fn log_std_clamp(&self) -> [f64; 2] {
        self.log_std_clamp
    }

    /// The network from observations to `[μ, log σ]` (before the clamp).
    pub fn net(&self) -> &Mlp {
        &self.net
    }

    /// Action size `A`.
    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// The Gaussian's mean `μ` and clamped `log σ`, each `[B, A]`, for observations `[B, O]`.
    pub fn dist(&self, obs: &Tensor) -> Result<(Tensor, Tensor)> {
        let out = self.net.forward(obs)?;
        let mean = out.narrow(D::Minus1, 0, self.act_dim)?;
        let log_std = out
            .narrow(D::Minus1, self.act_dim, self.act_dim)?
            .clamp(self.log_std_clamp[0], self.log_std_clamp[1])?;
        Ok((mean, log_std))
    }

    /// A reparameterised sample for observations `[B, O]` and standard-normal `noise` `[B, A]`:
    /// the action `[B, A]` and its log-probability `[B]`, both differentiable in the weights.
    pub fn sample(&self, obs: &Tensor, noise: &Tensor) -> Result<(Tensor, Tensor)> {
        let (mean, log_std) = self.dist(obs)?;
        squash(&mean, &log_std, noise)
    }

    /// The deterministic action `tanh(μ)`, `[B, A]`.
    pub fn mean_action(&self, obs: &Tensor) -> Result<Tensor> {
        self.dist(obs)?.0.tanh()
    }
}

/// The tanh-Gaussian sample `a = tanh(μ + σ ε)` and its log-probability summed over the last
/// dimension, for `mean`, `log_std` and `noise` `ε` of one shape `[…, A]` (see the module doc).
#[cfg(any(test, feature = "oracle"))]
pub fn squash(mean: &Tensor, log_std: &Tensor, noise: &Tensor) -> Result<(Tensor, Tensor)> {
    let u = (mean + log_std.exp()?.mul(noise)?)?;
    let action = u.tanh()?;
    // log N(u; μ, σ), with (u − μ)/σ = ε
    let log_normal = ((noise.sqr()? * -0.5)? - log_std)?
        .affine(1.0, -0.5 * (2.0 * std::f64::consts::PI).ln())?;
    let log_jacobian = log_one_minus_tanh_sq(&u)?;
    let log_prob = (log_normal - log_jacobian)?.sum(D::Minus1)?;
    Ok((action, log_prob))
}

/// [`squash`] on plain rows (the learner's hand-differentiated SAC): from the actor's outputs
/// `out` (`[B, 2A]`: means, then log standard deviations before the clamp to `log_std_clamp`)
/// and the noise `[B, A]`, the actions into `action` `[B, A]` and their log-probabilities into
/// `log_prob` `[B]`.
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

/// `log(1 − tanh² u) = 2 (log 2 − |u| − log(1 + e^{−2|u|}))`, elementwise and stable for any `u`.
#[cfg(any(test, feature = "oracle"))]
fn log_one_minus_tanh_sq(u: &Tensor) -> Result<Tensor> {
    let abs = u.abs()?;
    let log1p_exp = (abs.affine(-2.0, 0.0)?.exp()? + 1.0)?.log()?;
    ((abs + log1p_exp)? * -2.0)? + 2.0 * std::f64::consts::LN_2
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::ParamStore;
    use candle_core::Device;

    fn t(v: &[f32], shape: (usize, usize)) -> Tensor {
        Tensor::from_slice(v, shape, &Device::Cpu).unwrap()
    }

    /// The formula of the module doc in f64, naive `log(1 − tanh² u)` (stable for moderate `u`).
    fn expected(mean: &[f64], log_std: &[f64], eps: &[f64]) -> (Vec<f64>, f64) {
        let mut lp = 0.0;
        let mut a = Vec::new();
        for j in 0..mean.len() {
            let u = mean[j] + log_std[j].exp() * eps[j];
            a.push(u.tanh());
            lp += -0.5 * eps[j] * eps[j] - log_std[j] - 0.5 * (2.0 * std::f64::consts::PI).ln();
            lp -= (1.0 - u.tanh().powi(2)).ln();
        }
        (a, lp)
    }

    #[test]
    fn log_prob_matches_hand_computed_values_in_1d_and_2d() {
        // 1-D: μ = 0.3, log σ = −0.5, ε = 0.7: u = 0.3 + e^{−0.5}·0.7 = 0.724572...
        let (a, lp) = squash(&t(&[0.3], (1, 1)), &t(&[-0.5], (1, 1)), &t(&[0.7], (1, 1))).unwrap();
        let (ea, elp) = expected(&[0.3], &[-0.5], &[0.7]);
        let u: f64 = 0.3 + (-0.5f64).exp() * 0.7;
        let by_hand = -0.5 * 0.49 + 0.5 - 0.918_938_533_204_672_7 - (1.0 - u.tanh().powi(2)).ln();
        assert!((elp - by_hand).abs() < 1e-12);
        assert!((a.to_vec2::<f32>().unwrap()[0][0] as f64 - ea[0]).abs() < 1e-6);
        assert!(
            (lp.to_vec1::<f32>().unwrap()[0] as f64 - elp).abs() < 1e-5,
            "{lp} vs {elp}"
        );

        // 2-D, two rows: the log-probability sums over the action dimensions of each row
        let mean = [[-1.2, 0.4], [0.0, 2.0]];
        let log_std = [[0.1, -2.0], [-5.0, 1.0]];
        let eps = [[1.5, -0.3], [0.0, -1.1]];
        let flat = |m: [[f64; 2]; 2]| m.iter().flatten().map(|&x| x as f32).collect::<Vec<_>>();
        let (a, lp) = squash(
            &t(&flat(mean), (2, 2)),
            &t(&flat(log_std), (2, 2)),
            &t(&flat(eps), (2, 2)),
        )
        .unwrap();
        let (a, lp) = (a.to_vec2::<f32>().unwrap(), lp.to_vec1::<f32>().unwrap());
        for r in 0..2 {
            let (ea, elp) = expected(&mean[r], &log_std[r], &eps[r]);
            assert!(
                (lp[r] as f64 - elp).abs() < 1e-4 * elp.abs().max(1.0),
                "row {r}: {} vs {elp}",
                lp[r]
            );
            for j in 0..2 {
                assert!((a[r][j] as f64 - ea[j]).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn stable_jacobian_agrees_with_the_naive_formula_and_stays_finite_beyond_it() {
        let us: Vec<f32> = (-60..=60).map(|i| i as f32 * 0.05).collect();
        let stable =
            log_one_minus_tanh_sq(&Tensor::new(us.as_slice(), &Device::Cpu).unwrap()).unwrap();
        for (u, s) in us.iter().zip(stable.to_vec1::<f32>().unwrap()) {
            let naive = (1.0 - (*u as f64).tanh().powi(2)).ln();
            assert!((s as f64 - naive).abs() < 1e-5, "u = {u}: {s} vs {naive}");
        }
        // where f32's naive 1 − tanh² u is 0, the stable form is −2|u| + 2 log 2 to f32 precision
        let big =
            log_one_minus_tanh_sq(&Tensor::new(&[20f32, -30.0], &Device::Cpu).unwrap()).unwrap();
        assert_eq!((1.0 - 20f32.tanh().powi(2)).ln(), f32::NEG_INFINITY);
        for (u, s) in [20f64, 30.0].iter().zip(big.to_vec1::<f32>().unwrap()) {
            assert!(
                (s as f64 - (2.0 * std::f64::consts::LN_2 - 2.0 * u)).abs() < 1e-4,
                "{s}"
            );
        }
    }

    #[test]
    fn jacobian_gradient_is_minus_two_tanh_including_at_zero() {
        let u = candle_core::Var::new(&[-3f32, -0.5, 0.0, 0.5, 12.0], &Device::Cpu).unwrap();
        let grads = log_one_minus_tanh_sq(u.as_tensor())
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let g = grads.get(&u).unwrap().to_vec1::<f32>().unwrap();
        for (u, g) in [-3f32, -0.5, 0.0, 0.5, 12.0].iter().zip(g) {
            assert!((g + 2.0 * u.tanh()).abs() < 1e-5, "u = {u}: {g}");
        }
    }

    #[test]
    fn actor_heads_are_mean_and_clamped_log_std() {
        let ps = ParamStore::new();
        let actor = TanhGaussianActor::new(3, 2, 8, 2, ps.builder()).unwrap();
        ps.init(0).unwrap();
        // zero output weights: the outputs are the output bias [μ, log σ] for any observation
        for (name, var) in ps.named() {
            if name == "out.weight" {
                var.set(&var.zeros_like().unwrap()).unwrap();
            } else if name == "out.bias" {
                var.set(&t(&[0.5, -0.2, 3.0, -9.0], (1, 4)).reshape(4).unwrap())
                    .unwrap();
            }
        }
        let obs = t(&[0.1, -0.4, 2.0, 1.0, 1.0, 1.0], (2, 3));
        let (mean, log_std) = actor.dist(&obs).unwrap();
        assert_eq!(mean.to_vec2::<f32>().unwrap(), vec![vec![0.5, -0.2]; 2]);
        assert_eq!(
            log_std.to_vec2::<f32>().unwrap(),
            vec![vec![LOG_STD_MAX as f32, LOG_STD_MIN as f32]; 2]
        );
        let det = actor.mean_action(&obs).unwrap().to_vec2::<f32>().unwrap();
        assert!(
            (det[0][0] - 0.5f32.tanh()).abs() < 1e-7 && (det[1][1] - (-0.2f32).tanh()).abs() < 1e-7
        );
        let noise = t(&[0.3, -1.0, 0.0, 0.0], (2, 2));
        let (a, lp) = actor.sample(&obs, &noise).unwrap();
        let (ea, elp) = expected(&[0.5, -0.2], &[2.0, -5.0], &[0.3, -1.0]);
        let (a, lp) = (a.to_vec2::<f32>().unwrap(), lp.to_vec1::<f32>().unwrap());
        assert!((a[0][0] as f64 - ea[0]).abs() < 1e-6 && (a[0][1] as f64 - ea[1]).abs() < 1e-6);
        assert!((lp[0] as f64 - elp).abs() < 1e-4, "{} vs {elp}", lp[0]);
        assert_eq!(a[1], det[1]);
        // the paper's code's bounds [−20, 2] keep the raw −9
        let (_, log_std) = actor.with_log_std_clamp([-20.0, 2.0]).dist(&obs).unwrap();
        assert_eq!(log_std.to_vec2::<f32>().unwrap(), vec![vec![2.0, -9.0]; 2]);
        assert!(validate_log_std_clamp("sac.log_std_clamp", [-20.0, 2.0]).is_ok());
        for bad in [[2.0, -20.0], [1.0, 1.0], [f64::NAN, 2.0]] {
            let err = validate_log_std_clamp("sac.log_std_clamp", bad)
                .unwrap_err()
                .to_string();
            assert!(err.contains("sac.log_std_clamp must be"), "{err}");
        }
    }
}
