use crate::dreamer::{mask_of, mask_sample, normals, uniforms};
use crate::{symlog, DreamerNets, ParamStore, RssmState};
use candle_core::{DType, Device, Module, Tensor};
use ctxrace_config::agents::{
    ContextMode, ContextScale, DreamerConfig, MaskConfig, MaskSpace, CONTEXT_DIM,
};
use ctxrace_nn::policy::{DreamerPolicy, ACT_DIM};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

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

/// A fixed mask is the one cMask acts with, the noise streams untouched: masked to (0, 0) it acts
/// exactly as told the zero context, and an agent without a mask refuses one.
#[test]
fn a_fixed_mask_replaces_the_chosen_one() {
    let cfg = tiny(ContextMode::Cmask);
    let store = ParamStore::new();
    DreamerNets::new(&cfg, 3, ACT_DIM, store.builder()).unwrap();
    let weights = store.to_bytes().unwrap();
    let run = |mask: Option<[f32; 2]>, context: [f32; 2]| {
        let mut policy = DreamerPolicy::new(&cfg, 3, &weights, 7).unwrap();
        policy.fix_mask(mask).unwrap();
        (0..20)
            .map(|k| {
                let obs = [0.5, 0.2, (k as f32 * 0.37).sin()];
                policy.act(&obs, context, false).unwrap()
            })
            .collect::<Vec<_>>()
    };
    let masked = run(Some([0.0, 0.0]), [0.2, -0.1]);
    let zero = run(None, [0.0, 0.0]);
    assert!(masked.iter().all(|(_, m)| *m == Some([0.0, 0.0])));
    let actions = |d: &[([f32; 2], Option<[f32; 2]>)]| d.iter().map(|x| x.0).collect::<Vec<_>>();
    assert_eq!(actions(&masked), actions(&zero));
    let told = run(None, [0.2, -0.1]);
    assert_ne!(
        actions(&told),
        actions(&zero),
        "the context changes nothing"
    );
    let half = run(Some([1.0, 0.5]), [0.2, -0.1]);
    assert!(half.iter().all(|(_, m)| *m == Some([1.0, 0.5])));

    let crssm = tiny(ContextMode::Crssm);
    let store = ParamStore::new();
    DreamerNets::new(&crssm, 3, ACT_DIM, store.builder()).unwrap();
    let mut policy = DreamerPolicy::new(&crssm, 3, &store.to_bytes().unwrap(), 0).unwrap();
    assert!(policy.fix_mask(None).is_ok());
    let err = policy.fix_mask(Some([1.0, 1.0])).unwrap_err();
    assert!(err.to_string().contains("only a cMask agent"), "{err}");
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
            let mut policy = DreamerPolicy::new(&cfg, 3, &store.to_bytes().unwrap(), 0).unwrap();
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
                    let what = format!("{context:?} paper code {paper_code} {deterministic} {t}");
                    let obs = [0.5, (t as f32 * 0.9).sin() * 2.0, 0.1 * t as f32];
                    let ctx = [0.1, -0.05 * t as f32];
                    let (action, mask) = policy.act(&obs, ctx, deterministic).unwrap();
                    let (want_action, want_mask) = oracle.act(&obs, ctx, deterministic);
                    close(&action, &want_action, &what);
                    assert_eq!(mask.is_some(), want_mask.is_some(), "{what}");
                    if let (Some(m), Some(w)) = (mask, want_mask) {
                        close(&m, &w, &what);
                    }
                    let h: Vec<f32> = oracle.state.deter.flatten_all().unwrap().to_vec1().unwrap();
                    let z: Vec<f32> = oracle.state.stoch.flatten_all().unwrap().to_vec1().unwrap();
                    close(policy.state().0, &h, &what);
                    close(policy.state().1, &z, &what);
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
