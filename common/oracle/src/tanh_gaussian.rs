//! The oracle's tanh-squashed Gaussian policy (candle modules), SAC's actor: the formulas of
//! [`ctxrace_nn::tanh_gaussian`] composed of candle operations, which
//! [`ctxrace_nn::tanh_gaussian::squash_rows`] and its backward pass are checked against.

use super::mlp::Mlp;
use candle_core::{Module, Result, Tensor, D};
use candle_nn::VarBuilder;
use ctxrace_nn::tanh_gaussian::LOG_STD_CLAMP;
use ctxrace_nn::Activation;

/// A tanh-squashed Gaussian policy `π(a | o)` over actions in `(−1, 1)^A` (see [`ctxrace_nn::tanh_gaussian`]).
#[derive(Clone, Debug)]
pub struct TanhGaussianActor {
    net: Mlp,
    act_dim: usize,
    log_std_clamp: [f64; 2],
}

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
/// dimension, for `mean`, `log_std` and `noise` `ε` of one shape `[…, A]` (see [`ctxrace_nn::tanh_gaussian`]).
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

/// `log(1 − tanh² u) = 2 (log 2 − |u| − log(1 + e^{−2|u|}))`, elementwise and stable for any `u`.
fn log_one_minus_tanh_sq(u: &Tensor) -> Result<Tensor> {
    let abs = u.abs()?;
    let log1p_exp = (abs.affine(-2.0, 0.0)?.exp()? + 1.0)?.log()?;
    ((abs + log1p_exp)? * -2.0)? + 2.0 * std::f64::consts::LN_2
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ParamStore;
    use candle_core::Device;
    use ctxrace_nn::tanh_gaussian::{LOG_STD_MAX, LOG_STD_MIN};

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
    }
}
