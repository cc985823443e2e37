//! DreamerV3's acting networks (encoder, RSSM, actor and cMask's mask actor) and the batch-1
//! policy that runs them in the actors: at each step the observation updates the posterior
//! state, the actor reads `[h, z, c]` and (cMask) the mask actor masks the context first.
//! The learner trains the same [`PolicyNets`] and ships their weights ("policy"); the policy
//! reads them by name and acts with the networks' forward passes at batch 1.

use super::{PolicyError, Result, ACT_DIM};
use crate::dreamer::{mask_value, uniform_rows, PolicyNets};
use crate::tanh_gaussian::squash_rows;
use crate::{sigmoid, symlog_value, MlpTrace, ObserveTrace, Weights, WeightsError};
use ctxrace_config::agents::{DreamerConfig, StepAlignment, CONTEXT_DIM};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// The networks that act, read by name from the policy weights `bytes` of `cfg` for
/// observations of `obs_dim` (safetensors, the names [`PolicyNets`] gives), every tensor used.
fn read_nets(
    cfg: &DreamerConfig,
    obs_dim: usize,
    bytes: &[u8],
) -> std::result::Result<PolicyNets, WeightsError> {
    let mut weights = Weights::from_safetensors(bytes)?;
    let nets = PolicyNets::from_weights(cfg, obs_dim, ACT_DIM, &mut weights)?;
    weights.finish()?;
    Ok(nets)
}

/// The buffers of one step, kept from step to step.
#[derive(Debug, Default)]
struct ActingTraces {
    /// `symlog o` (`symlog [o, a_{t−1}]` with [`StepAlignment::PaperCode`]).
    input: Vec<f32>,
    encoder: MlpTrace,
    rssm: ObserveTrace,
    /// `[h, z, c]`.
    head_input: Vec<f32>,
    actor: MlpTrace,
    mask: MlpTrace,
}

/// The acting side of DreamerV3 at batch 1: keeps the recurrent state and the previous action.
pub struct DreamerPolicy {
    cfg: DreamerConfig,
    obs_dim: usize,
    nets: PolicyNets,
    traces: ActingTraces,
    /// The state episodes start from, `(h_0, z_0)` ([`crate::Rssm::initial_state`] of the
    /// loaded weights).
    zero: (Vec<f32>, Vec<f32>),
    /// The posterior state `(h, z)`.
    state: (Vec<f32>, Vec<f32>),
    prev_action: [f32; ACT_DIM],
    /// Equal Gumbel noise (the sample is the most likely class), `[Z]`.
    uniform_mode: Vec<f32>,
    rng: ChaCha8Rng,
}

impl DreamerPolicy {
    /// A policy of the architecture `cfg` for observations of `obs_dim`, with the bytes of
    /// the learner's policy weights; `seed` seeds its sampling noise.
    pub fn new(cfg: &DreamerConfig, obs_dim: usize, weights: &[u8], seed: u64) -> Result<Self> {
        cfg.validate()?;
        let nets = read_nets(cfg, obs_dim, weights)?;
        let mut policy = Self {
            cfg: cfg.clone(),
            obs_dim,
            nets,
            traces: ActingTraces::default(),
            zero: (Vec::new(), Vec::new()),
            state: (Vec::new(), Vec::new()),
            prev_action: [0.0; ACT_DIM],
            uniform_mode: vec![0.5; cfg.stoch * cfg.classes],
            rng: ChaCha8Rng::seed_from_u64(seed),
        };
        policy.start_from_loaded();
        policy.reset();
        Ok(policy)
    }

    /// The initial state of the loaded weights, and the traces sized for them.
    fn start_from_loaded(&mut self) {
        let (nets, tr) = (&self.nets, &mut self.traces);
        let (h, z) = nets.rssm.initial_state(&mut tr.rssm);
        self.zero = (h.to_vec(), z.to_vec());
        tr.encoder = nets.encoder.trace(1);
        tr.actor = nets.actor.trace(1);
        if let Some(mask) = &nets.mask {
            tr.mask = mask.trace(1);
        }
    }

    /// Replaces the weights (same architecture) without resetting the state (the next
    /// episode starts from the new weights' initial state).
    pub fn load(&mut self, weights: &[u8]) -> Result<()> {
        self.nets = read_nets(&self.cfg, self.obs_dim, weights)?;
        self.start_from_loaded();
        Ok(())
    }

    /// Restarts the sampling noise from `seed`.
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// Starts a new episode: the initial state and a zero previous action.
    pub fn reset(&mut self) {
        self.state = self.zero.clone();
        self.prev_action = [0.0; ACT_DIM];
    }

    /// cMask's mask for observation `obs` (`None` for the other agents): the mask of `tanh μ`
    /// if `deterministic`, else of a sample (the oracle's `mask_sample`).
    fn mask(&mut self, obs: &[f32], deterministic: bool) -> Option<[f32; CONTEXT_DIM]> {
        let net = self.nets.mask.as_ref()?;
        let trace = &mut self.traces.mask;
        net.forward(obs, trace, 0..1);
        let out = net.output(trace, 0..1);
        let mut a = [0f32; CONTEXT_DIM];
        if deterministic {
            a.iter_mut()
                .zip(out)
                .for_each(|(a, &mean)| *a = mean.tanh());
        } else {
            let noise: [f32; CONTEXT_DIM] =
                std::array::from_fn(|_| self.rng.sample(StandardNormal));
            let clamp = self.cfg.mask.log_std_clamp.map(|b| b as f32);
            squash_rows(out, &noise, clamp, &mut a, &mut [0.0]);
        }
        Some(a.map(|a| mask_value(a, self.cfg.mask.mask_space)))
    }

    /// The action in `[−1, 1]²` for observation `obs` and raw context `[c_v, c_θ]`, and (cMask) the
    /// mask used. Deterministic: the mean action, the most likely latent and the mask of
    /// `tanh μ` (the oracle's `mask_of`); otherwise samples.
    pub fn act(
        &mut self,
        obs: &[f32],
        context: [f32; 2],
        deterministic: bool,
    ) -> Result<([f32; 2], Option<[f32; 2]>)> {
        if obs.len() != self.obs_dim {
            return Err(PolicyError::Observation {
                found: obs.len(),
                want: self.obs_dim,
            });
        }
        let mask = self.mask(obs, deterministic);
        // the model's context: the raw one scaled (and masked), or none
        let scale = (1.0 / self.cfg.context_divisor()) as f32;
        let ctx: [f32; CONTEXT_DIM] =
            std::array::from_fn(|i| context[i] * scale * mask.map_or(1.0, |m| m[i]));
        let ctx = &ctx[..self.nets.rssm.config().context_dim];
        let z = self.cfg.stoch * self.cfg.classes;
        let (uniform, noise) = if deterministic {
            (None, None)
        } else {
            let u = uniform_rows(std::slice::from_mut(&mut self.rng), 1, z);
            let n: [f32; ACT_DIM] = std::array::from_fn(|_| self.rng.sample(StandardNormal));
            (Some(u), Some(n))
        };
        let (nets, tr) = (&self.nets, &mut self.traces);
        // the embedding of symlog o (symlog [o, a_{t−1}] as the paper's code acts)
        tr.input.clear();
        tr.input.extend(obs.iter().map(|&v| symlog_value(v)));
        if self.cfg.step_alignment == StepAlignment::PaperCode {
            tr.input
                .extend(self.prev_action.iter().map(|&v| symlog_value(v)));
        }
        nets.encoder
            .forward(tr.input.as_slice(), &mut tr.encoder, 0..1);
        let embed = match nets.encoder.outputs() {
            0 => &tr.input[..],
            _ => nets.encoder.output(&tr.encoder, 0..1),
        };
        let (h, zs) = (&self.state.0[..], &self.state.1[..]);
        let uniform = uniform.as_deref().unwrap_or(&self.uniform_mode);
        let inputs = (&self.prev_action[..], ctx, embed);
        nets.rssm
            .posterior_step((h, zs), inputs, uniform, &mut tr.rssm);
        let (h, zs, _) = tr.rssm.states();
        self.state.0.copy_from_slice(h);
        self.state.1.copy_from_slice(zs);
        tr.head_input.clear();
        for part in [h, zs, ctx] {
            tr.head_input.extend_from_slice(part);
        }
        nets.actor
            .forward(tr.head_input.as_slice(), &mut tr.actor, 0..1);
        let out = nets.actor.output(&tr.actor, 0..1);
        let (lo, span) = (
            self.cfg.min_std as f32,
            (self.cfg.max_std - self.cfg.min_std) as f32,
        );
        let action: [f32; ACT_DIM] = std::array::from_fn(|j| {
            let mean = out[j].tanh();
            match noise {
                None => mean,
                Some(n) => {
                    let a = mean + (sigmoid(out[ACT_DIM + j] + 2.0) * span + lo) * n[j];
                    a * (1.0 / a.abs().max(1.0))
                }
            }
        });
        self.prev_action = action;
        Ok((action, mask))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::oracle::dreamer::{mask_of, mask_sample, normals, uniforms};
    use crate::oracle::{symlog, DreamerNets, ParamStore, RssmState};
    use candle_core::{DType, Device, Module, Tensor};
    use ctxrace_config::agents::{ContextMode, ContextScale, MaskConfig, MaskSpace};

    /// A DreamerV3 configuration small enough for a test, with the context mode `context`.
    fn tiny(context: ContextMode) -> DreamerConfig {
        DreamerConfig {
            context,
            units: 16,
            layers: 1,
            deter: 16,
            hidden: 16,
            stoch: 4,
            classes: 4,
            head_units: 16,
            head_layers: 1,
            mask: MaskConfig {
                units: 16,
                ..MaskConfig::default()
            },
            ..DreamerConfig::default()
        }
    }
    /// The acting policy feeds the context as `context_scale` says: raw, the network sees `c`
    /// where, normalised, it sees `c / 0.15` (so a raw policy at `c` acts as a normalised one
    /// at `0.15 c`), the mask of cMask multiplying the scaled context.
    #[test]
    fn acting_feeds_the_context_at_its_scale() {
        for context in [ContextMode::Crssm, ContextMode::Cmask] {
            let cfg = |scale| DreamerConfig {
                context_scale: scale,
                ..tiny(context)
            };
            let (raw, normalised) = (cfg(ContextScale::Raw), cfg(ContextScale::Normalised));
            let store = ParamStore::new();
            let nets = DreamerNets::new(&raw, 3, ACT_DIM, store.builder()).unwrap();
            let c = Tensor::new(&[[0.1f32, -0.3]], &Device::Cpu).unwrap();
            let fed: Vec<Vec<f32>> = nets.context(&c, None).unwrap().unwrap().to_vec2().unwrap();
            assert_eq!(fed, [[0.1, -0.3]]);
            let weights = store.to_bytes().unwrap();
            let act = |cfg: &DreamerConfig, c: [f32; 2]| {
                let mut policy = DreamerPolicy::new(cfg, 3, &weights, 1).unwrap();
                (0..3)
                    .map(|_| policy.act(&[0.5, 0.2, 0.1], c, true).unwrap().0)
                    .collect::<Vec<_>>()
            };
            let (a, b) = (act(&raw, [0.06, -0.09]), act(&normalised, [0.009, -0.0135]));
            for (x, y) in a.iter().flatten().zip(b.iter().flatten()) {
                assert!((x - y).abs() < 1e-5, "{a:?} vs {b:?}");
            }
            let other = act(&normalised, [0.06, -0.09]);
            assert!(
                a.iter()
                    .flatten()
                    .zip(other.iter().flatten())
                    .any(|(x, y)| (x - y).abs() > 1e-4),
                "the context scale changes nothing: {a:?} vs {other:?}"
            );
        }
    }

    /// The acting masks of each [`MaskSpace`]: `(1 + tanh u)/2` over `(0, 1)`, the paper's code's
    /// `sigmoid(tanh u)` inside `(σ(−1), σ(1)) ≈ (0.269, 0.731)`; the deterministic mask is the
    /// space's map of `tanh μ`.
    #[test]
    fn the_policy_acts_with_the_mask_of_its_space() {
        let unit = MaskConfig {
            units: 16,
            ..MaskConfig::default()
        };
        for mask in [unit.clone(), unit.with_paper_code_mask()] {
            let cfg = DreamerConfig {
                mask,
                ..tiny(ContextMode::Cmask)
            };
            let store = ParamStore::new();
            let nets = DreamerNets::new(&cfg, 3, ACT_DIM, store.builder()).unwrap();
            let mut policy = DreamerPolicy::new(&cfg, 3, &store.to_bytes().unwrap(), 1).unwrap();
            let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
            let (lo, hi) = match cfg.mask.mask_space {
                MaskSpace::Unit => (0.0, 1.0),
                MaskSpace::PaperCode => (sigmoid(-1.0), sigmoid(1.0)),
            };
            let (mut least, mut most) = (1f32, 0f32);
            for k in 0..200 {
                let obs = [0.5, 0.2, (k as f32 * 0.37).sin() * 3.0];
                let (_, m) = policy.act(&obs, [0.1, -0.1], false).unwrap();
                for v in m.unwrap() {
                    assert!(lo <= v && v <= hi, "{:?}: {v}", cfg.mask.mask_space);
                    (least, most) = (least.min(v), most.max(v));
                }
            }
            // the samples spread over the range (an untrained actor's σ is about 1)
            assert!(most - least > 0.5 * (hi - lo), "{least}..{most}");
            let obs = [0.5, 0.2, 0.1];
            let (_, m) = policy.act(&obs, [0.1, -0.1], true).unwrap();
            let o = Tensor::from_slice(&obs, (1, 3), &Device::Cpu).unwrap();
            let mode = nets.mask.as_ref().unwrap().mean_action(&o).unwrap();
            let want: Vec<f32> = mask_of(&mode, cfg.mask.mask_space)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            // the acting pass and the candle composition may round differently (one ulp)
            let got = m.unwrap();
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-6, "{got:?} vs {want:?}");
            }
        }
    }

    /// The candle composition the policy acted with before it ran the networks (the
    /// oracle): the networks on the learner's parameters, the state and the previous action.
    struct CandleActor {
        nets: DreamerNets,
        paper_code: bool,
        state: RssmState,
        prev: Tensor,
        rng: ChaCha8Rng,
    }

    impl CandleActor {
        /// One step as `DreamerNets::observe` and the candle policy computed it.
        fn act(
            &mut self,
            obs: &[f32],
            context: [f32; 2],
            deterministic: bool,
        ) -> (Vec<f32>, Option<Vec<f32>>) {
            let dev = &Device::Cpu;
            let nets = &self.nets;
            let o = Tensor::from_slice(obs, (1, obs.len()), dev).unwrap();
            let space = nets.mask_space;
            let mask = nets.mask.as_ref().map(|actor| match deterministic {
                true => mask_of(&actor.mean_action(&o).unwrap(), space).unwrap(),
                false => {
                    let noise = normals(&mut self.rng, (1, CONTEXT_DIM)).unwrap();
                    mask_sample(actor, &o, &noise, space).unwrap().0
                }
            });
            let raw = Tensor::from_slice(&context, (1, CONTEXT_DIM), dev).unwrap();
            let ctx = nets.context(&raw, mask.as_ref()).unwrap();
            let (s, c) = {
                let rc = nets.rssm.config();
                (rc.stoch, rc.classes)
            };
            let (uniform, noise) = match deterministic {
                true => (Tensor::full(0.5f32, (1, s, c), dev).unwrap(), None),
                false => {
                    let u = uniforms(&mut self.rng, (1, s, c)).unwrap();
                    (u, Some(normals(&mut self.rng, (1, ACT_DIM)).unwrap()))
                }
            };
            let input = match self.paper_code {
                true => Tensor::cat(&[&o, &self.prev], 1).unwrap(),
                false => o,
            };
            let embed = nets.encoder.forward(&symlog(&input).unwrap()).unwrap();
            let (next, _) = nets
                .rssm
                .obs_step(&self.state, &self.prev, ctx.as_ref(), &embed, &uniform)
                .unwrap();
            let (mean, std) = nets
                .actor_dist(&next.head_input(ctx.as_ref()).unwrap())
                .unwrap();
            let action = match noise {
                Some(n) => DreamerNets::sample_action(&mean, &std, &n).unwrap(),
                None => mean,
            };
            let values = |t: &Tensor| -> Vec<f32> { t.flatten_all().unwrap().to_vec1().unwrap() };
            let decision = (values(&action), mask.as_ref().map(values));
            (self.state, self.prev) = (next, action);
            decision
        }
    }

    /// The policy on the networks acts as the candle networks it was read from did, on
    /// random weights (a random learned initial state too), for each context mode and both step
    /// alignments, deterministic and sampled, step after step: actions, masks and the state.
    #[test]
    fn acts_as_the_candle_networks_did() {
        let close = |got: &[f32], want: &[f32], what: &str| {
            assert_eq!(got.len(), want.len(), "{what}");
            for (g, w) in got.iter().zip(want) {
                assert!((g - w).abs() <= 1e-5, "{what}: {got:?} vs {want:?}");
            }
        };
        for context in [ContextMode::None, ContextMode::Crssm, ContextMode::Cmask] {
            for paper_code in [false, true] {
                let cfg = match paper_code {
                    true => tiny(context).with_paper_code_world_model(),
                    false => tiny(context),
                };
                let store = ParamStore::new();
                let nets = DreamerNets::new(&cfg, 3, ACT_DIM, store.builder()).unwrap();
                store.init(4).unwrap();
                for (name, v) in store.named() {
                    if name == "rssm.initial_state.w" {
                        v.set(&Tensor::randn(0f32, 1.0, v.shape(), &Device::Cpu).unwrap())
                            .unwrap();
                    }
                }
                let mut policy =
                    DreamerPolicy::new(&cfg, 3, &store.to_bytes().unwrap(), 0).unwrap();
                for deterministic in [true, false] {
                    policy.reset();
                    policy.reseed(5);
                    let mut oracle = CandleActor {
                        state: nets.rssm.initial(1).unwrap(),
                        prev: Tensor::zeros((1, ACT_DIM), DType::F32, &Device::Cpu).unwrap(),
                        nets: nets.clone(),
                        paper_code,
                        rng: ChaCha8Rng::seed_from_u64(5),
                    };
                    for t in 0..4 {
                        let what =
                            format!("{context:?} paper code {paper_code} {deterministic} {t}");
                        let obs = [0.5, (t as f32 * 0.9).sin() * 2.0, 0.1 * t as f32];
                        let ctx = [0.1, -0.05 * t as f32];
                        let (action, mask) = policy.act(&obs, ctx, deterministic).unwrap();
                        let (want_action, want_mask) = oracle.act(&obs, ctx, deterministic);
                        close(&action, &want_action, &what);
                        assert_eq!(mask.is_some(), want_mask.is_some(), "{what}");
                        if let (Some(m), Some(w)) = (mask, want_mask) {
                            close(&m, &w, &what);
                        }
                        let h: Vec<f32> =
                            oracle.state.deter.flatten_all().unwrap().to_vec1().unwrap();
                        let z: Vec<f32> =
                            oracle.state.stoch.flatten_all().unwrap().to_vec1().unwrap();
                        close(&policy.state.0, &h, &what);
                        close(&policy.state.1, &z, &what);
                    }
                }
            }
        }
    }

    /// Weights of another architecture are refused, naming the tensor.
    #[test]
    fn weights_of_another_architecture_are_refused() {
        let store = ParamStore::new();
        DreamerNets::new(&tiny(ContextMode::Crssm), 3, ACT_DIM, store.builder()).unwrap();
        let weights = store.to_bytes().unwrap();
        let err = DreamerPolicy::new(&tiny(ContextMode::Cmask), 3, &weights, 0)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("mask.l0.fc.weight"), "{err}");
        let err = DreamerPolicy::new(&tiny(ContextMode::None), 3, &weights, 0)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("rssm.img_in.fc.weight"), "{err}");
    }
}
