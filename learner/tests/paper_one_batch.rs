//! One batch through ctxrace's DreamerV3 and cMask and through the paper's own torch models
//! (c0fd903: `Utils/dreamerv3`, and `Utils/cbdreamer` for cMask) from the same weights, with the
//! same noise: the loss terms, gradient norms, the mask SAC's losses and temperature, and every
//! parameter's step agree, over two steps (issue 37's one-batch comparison).
//!
//! `testdata/paper_one_batch/{dreamerv3,cmask}.safetensors` were written by
//! `deploy/paper_one_batch.py` (see docs/parity/one_batch.md for the commands): the paper's agent
//! at 16 units and a 4 x 4 latent (cbDreamer's mask networks at 16 units), its weights under
//! ctxrace's names, one batch of 4 sequences of 16 steps from a paper run's replay, the noise
//! its samples used (ctxrace's own streams, computed in Python) and torch's loss terms, gradient
//! norms and gradients.

use candle_core::{Device, Tensor};
use ctxrace_config::agents::{AgentConfig, AlgoKind, DreamerConfig, CONTEXT_DIM};
use ctxrace_config::SequenceBatch;
use ctxrace_learner::{Algorithm, Batch, Dreamer, Metrics};
use ctxrace_nn::dreamer::{normal_rows, uniform_rows};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

const OBS: usize = 108;
const ACT: usize = 2;

/// The paper code's model a file holds.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Model {
    /// `Utils/dreamerv3`: ctxrace's DreamerV3.
    Dreamerv3,
    /// `Utils/cbdreamer` (cbDreamer): ctxrace's cMask.
    Cmask,
}

use Model::{Cmask, Dreamerv3};

impl Model {
    /// The file `deploy/paper_one_batch.py --model <name>` wrote.
    fn file(self) -> PathBuf {
        let name = match self {
            Dreamerv3 => "dreamerv3",
            Cmask => "cmask",
        };
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../testdata/paper_one_batch")
            .join(format!("{name}.safetensors"))
    }

    /// The parameter stores of the model's checkpoint the file fills.
    fn stores(self) -> &'static [&'static str] {
        match self {
            Dreamerv3 => &["policy", "heads", "critic", "slow_critic"],
            Cmask => &[
                "policy",
                "heads",
                "critic",
                "slow_critic",
                "mask_critic",
                "mask_target",
                "mask_alpha",
            ],
        }
    }
}

/// The model's file's tensors by name; a missing file fails the test, saying how to write it.
fn read(model: Model) -> HashMap<String, Tensor> {
    let path = model.file();
    assert!(
        path.exists(),
        "{}: missing; write it with deploy/paper_one_batch.py (the commands are in \
         docs/parity/one_batch.md)",
        path.display()
    );
    candle_core::safetensors::load(&path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

fn scalar(file: &HashMap<String, Tensor>, name: &str) -> f64 {
    values(&file[name])[0] as f64
}

/// The configuration the file was written for: the paper-code preset of the model's algorithm
/// (its world model, mask SAC and raw context as the code's) at the file's sizes: 16 units, a
/// 4 x 4 latent, 3 encoder and decoder layers, 2 head layers, batches of 4 x 16, the code's
/// learning rates and imagination horizon, and (cMask) the harness's mask width and rate.
fn config(model: Model, file: &HashMap<String, Tensor>) -> DreamerConfig {
    let c = values(&file["config"]);
    let (units, stoch, classes) = (c[0] as usize, c[1] as usize, c[2] as usize);
    let algo = match model {
        Dreamerv3 => AlgoKind::Dreamerv3,
        Cmask => AlgoKind::Cmask,
    };
    let preset = AgentConfig {
        algo,
        ..AgentConfig::paper_code()
    }
    .dreamer();
    let mut cfg = DreamerConfig {
        units,
        layers: 3,
        deter: units,
        hidden: units,
        stoch,
        classes,
        head_units: units,
        head_layers: 2,
        batch: c[3] as usize,
        length: c[4] as usize,
        seed: c[5] as u64,
        model_lr: c[6] as f64,
        ac_lr: c[7] as f64,
        horizon: c[8] as usize,
        ..preset
    };
    if model == Cmask {
        cfg.mask.units = c[9] as usize;
        cfg.mask.lr = c[10] as f64;
    }
    cfg
}

/// The stores' weights in `dir` (a checkpoint), by `store/name`.
fn stored(model: Model, dir: &Path) -> HashMap<String, Vec<f32>> {
    let mut out = HashMap::new();
    for store in model.stores() {
        let path = dir.join(format!("{store}.safetensors"));
        for (name, t) in candle_core::safetensors::load(&path, &Device::Cpu).unwrap() {
            out.insert(format!("{store}/{name}"), values(&t));
        }
    }
    out
}

/// The agent of `cfg` with the file's weights, through a checkpoint: a fresh agent's own
/// (optimisers at zero, step 0) with its stores replaced by the file's tensors. The mask SAC's
/// targets start as its critics (the code's `load_state_dict`; the file holds them once).
fn agent_with_file_weights(
    model: Model,
    cfg: &DreamerConfig,
    file: &HashMap<String, Tensor>,
    dir: &Path,
) -> Dreamer {
    let mut agent = Dreamer::new(cfg.clone(), OBS, ACT).unwrap();
    agent.save(dir).unwrap();
    for &store in model.stores() {
        let source = if store == "mask_target" {
            "mask_critic"
        } else {
            store
        };
        let prefix = format!("{source}/");
        let tensors: HashMap<String, Tensor> = file
            .iter()
            .filter_map(|(k, v)| Some((k.strip_prefix(&prefix)?.to_string(), v.clone())))
            .collect();
        let path = dir.join(format!("{store}.safetensors"));
        candle_core::safetensors::save(&tensors, &path).unwrap();
    }
    agent
        .load(dir)
        .expect("the torch weights fill every store of ctxrace's agent, name by name");
    agent
}

/// The file's batch; cbDreamer's with its raw contexts and the masks that acted (every row's
/// action chose through a mask in the paper's run), DreamerV3's without.
fn batch(file: &HashMap<String, Tensor>, cfg: &DreamerConfig) -> SequenceBatch {
    let n = cfg.batch * cfg.length;
    let or_zeros = |name: &str| {
        file.get(name)
            .map_or_else(|| vec![0.0; n * CONTEXT_DIM], values)
    };
    SequenceBatch {
        batch: cfg.batch,
        length: cfg.length,
        obs_dim: OBS,
        act_dim: ACT,
        obs: values(&file["batch/obs"]),
        action: values(&file["batch/action"]),
        reward: values(&file["batch/reward"]),
        is_first: values(&file["batch/is_first"]),
        is_terminal: values(&file["batch/is_terminal"]),
        context: or_zeros("batch/context"),
        mask: or_zeros("batch/mask"),
        has_mask: vec![f32::from(u8::from(file.contains_key("batch/mask"))); n],
    }
}

/// Sequence `b`'s noise stream at step 0 as ctxrace's DreamerV3 seeds it: ChaCha8 from
/// `seed ^ (b + 1)·φ` (φ = 0x9e37_79b9_7f4a_7c15), stream number 0.
fn streams(cfg: &DreamerConfig) -> Vec<ChaCha8Rng> {
    (0..cfg.batch as u64)
        .map(|b| {
            let mut rng =
                ChaCha8Rng::seed_from_u64(cfg.seed ^ (b + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15));
            rng.set_stream(0);
            rng
        })
        .collect()
}

fn assert_bits(name: &str, got: &[f32], want: &[f32]) {
    assert_eq!(got.len(), want.len(), "{name}");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert_eq!(g.to_bits(), w.to_bits(), "{name}[{i}]: {g} vs {w}");
    }
}

/// The noise the file's torch samples used is the noise ctxrace's step 0 draws, bit for bit, in
/// its order: (cMask) `T·2` normals of each stream for the batch's masks; per sequence step,
/// `S·C` posterior uniforms of each stream; per imagined step (`H − 1` of them) the actions'
/// normals and the priors' uniforms of each stream's `T` starts; (cMask) the mask SAC's
/// critic and actor passes, `(T − 1)·2` normals of each stream each. So both sides sample the
/// same masks, latents and actions.
fn the_torch_samples_used_ctxraces_noise(model: Model) {
    let file = read(model);
    let cfg = config(model, &file);
    let (z, n) = (cfg.stoch * cfg.classes, cfg.batch * cfg.length);
    let mut rngs = streams(&cfg);
    let mut want = Vec::new();
    if model == Cmask {
        want.push((
            "mask_normal",
            normal_rows(&mut rngs, cfg.length, CONTEXT_DIM),
        ));
    }
    let mut posterior = Vec::new();
    for _ in 0..cfg.length {
        posterior.extend(uniform_rows(&mut rngs, 1, z));
    }
    want.push(("model_uniform", posterior));
    let (mut normals, mut uniforms) = (Vec::new(), Vec::new());
    for _ in 1..cfg.horizon {
        normals.extend(normal_rows(&mut rngs, cfg.length, ACT));
        uniforms.extend(uniform_rows(&mut rngs, cfg.length, z));
    }
    assert_eq!(uniforms.len(), (cfg.horizon - 1) * n * z);
    want.extend([("imag_normal", normals), ("imag_uniform", uniforms)]);
    if model == Cmask {
        for pass in ["sac_critic_normal", "sac_actor_normal"] {
            want.push((pass, normal_rows(&mut rngs, cfg.length - 1, CONTEXT_DIM)));
        }
    }
    for (name, noise) in want {
        assert_bits(name, &values(&file[&format!("noise/{name}")]), &noise);
    }
}

#[test]
fn the_torch_dreamerv3_samples_used_ctxraces_noise() {
    the_torch_samples_used_ctxraces_noise(Dreamerv3);
}

#[test]
fn the_torch_cmask_samples_used_ctxraces_noise() {
    the_torch_samples_used_ctxraces_noise(Cmask);
}

/// One training step of ctxrace's agent with the file's weights on its batch.
struct OneStep {
    /// The file's tensors.
    file: HashMap<String, Tensor>,
    /// The step's metrics.
    metrics: Metrics,
    /// The stores' weights before and after the step, by `store/name`.
    before: HashMap<String, Vec<f32>>,
    after: HashMap<String, Vec<f32>>,
}

fn step_once(model: Model) -> OneStep {
    let file = read(model);
    let cfg = config(model, &file);
    let dir = tempfile::tempdir().unwrap();
    let mut agent = agent_with_file_weights(model, &cfg, &file, &dir.path().join("before"));
    let before = stored(model, &dir.path().join("before"));
    let metrics = agent
        .train_step(&Batch::Sequence(batch(&file, &cfg)))
        .unwrap();
    agent.save(&dir.path().join("after")).unwrap();
    let after = stored(model, &dir.path().join("after"));
    OneStep {
        file,
        metrics,
        before,
        after,
    }
}

/// ctxrace's world-model metrics and torch's names for them.
const WORLD_MODEL: [(&str, &str); 6] = [
    ("model/loss", "model_loss"),
    ("model/recon", "recon"),
    ("model/reward", "reward"),
    ("model/cont", "cont"),
    ("model/kl", "kl"),
    ("model/grad_norm", "model_grad_norm"),
];

/// ctxrace's behaviour-learning metrics and torch's names for them.
const BEHAVIOUR: [(&str, &str); 6] = [
    ("imag/return", "return"),
    ("imag/return_scale", "return_scale"),
    ("actor/loss", "actor_loss"),
    ("critic/loss", "critic_loss"),
    ("actor/grad_norm", "actor_grad_norm"),
    ("critic/grad_norm", "critic_grad_norm"),
];

/// ctxrace's mask-SAC metrics and torch's names for them: the mean of the batch's masks, the
/// step's `α`, the critics' and actor's losses, the entropy of the actor's sample.
const MASK: [(&str, &str); 5] = [
    ("mask/mean", "mask_mean"),
    ("mask/alpha", "mask_alpha"),
    ("mask/q_loss", "mask_q_loss"),
    ("mask/actor_loss", "mask_actor_loss"),
    ("mask/entropy", "mask_entropy"),
];

/// `(ctxrace's metric, the file's tensor of torch's name under group/, tolerance)` for each
/// pair.
fn torch<'a>(
    group: &str,
    pairs: &[(&'a str, &str)],
    tolerance: f64,
) -> Vec<(&'a str, String, f64)> {
    pairs
        .iter()
        .map(|&(ours, theirs)| (ours, format!("{group}/{theirs}"), tolerance))
        .collect()
}

/// Each of ctxrace's metrics `ours` is torch's `theirs` to `tolerance`, relative to
/// `max(1, |torch|)`.
fn agrees(metrics: &Metrics, file: &HashMap<String, Tensor>, pairs: &[(&str, String, f64)]) {
    for (ours, theirs, tolerance) in pairs {
        let (got, want) = (metrics[*ours], scalar(file, theirs));
        let err = (got - want).abs() / want.abs().max(1.0);
        println!("{ours}: ctxrace {got:.7}, torch {want:.7} (relative {err:.1e})");
        assert!(err < *tolerance, "{ours}: ctxrace {got} vs torch {want}");
    }
}

/// From the torch model's weights, on its batch and noise, ctxrace's world-model step (the
/// paper-code alignment and learned initial state; cMask's masked context in the sequence
/// model and every head) computes torch's loss terms and gradient norm to 1e-5 relative:
/// float32 on both sides, sums in different orders over 64 rows of up to 255 terms and a
/// 16-step recurrence (measured: 6e-8 or less). cbDreamer's gradient norm here is its world
/// model's own (the code's logged norm also counts its mask SAC's stale gradients:
/// docs/parity/one_batch.md).
#[test]
fn the_world_model_step_agrees_with_the_papers_torch_model() {
    for model in [Dreamerv3, Cmask] {
        let step = step_once(model);
        agrees(
            &step.metrics,
            &step.file,
            &torch("torch", &WORLD_MODEL, 1e-5),
        );
    }
}

/// Behaviour learning after that step, imagining from the same posterior states with the same
/// action noise and prior samples (cMask: with the raw context, as the code's behaviour step
/// reads it), computes torch's λ-returns, return scale, actor and critic losses and gradient
/// norms, to 1e-4 relative (the world model both sides stepped differs in the last bits, and 9
/// imagined steps through it compound them).
#[test]
fn behaviour_learning_agrees_with_the_papers_torch_model() {
    for model in [Dreamerv3, Cmask] {
        let step = step_once(model);
        agrees(&step.metrics, &step.file, &torch("torch", &BEHAVIOUR, 1e-4));
    }
}

/// cMask's mask SAC step (the paper-code form: the code's mask spaces, its reward one row late,
/// bootstrapping at terminals) computes torch's `CtxMask._train`: the masks' mean, `α`, the
/// critics' and actor's losses and the actor sample's entropy, to 1e-5 relative.
#[test]
fn the_mask_sac_step_agrees_with_the_papers_torch_model() {
    let step = step_once(Cmask);
    agrees(&step.metrics, &step.file, &torch("torch", &MASK, 1e-5));
}

/// After that step the mask actor, critics and `log α` hold torch's stepped values wherever
/// torch's gradient is not negligible (Adam's first step is `−lr·g/(|g| + ε)`, so a gradient
/// near zero may step either way), and the target critics torch's Polyak average everywhere
/// (moved on the first step, as the code's `it % 2 == 0`), to 1e-6.
#[test]
fn the_mask_sac_steps_its_weights_as_torch() {
    let step = step_once(Cmask);
    let mut compared = 0;
    for (name, want) in &step.file {
        let Some(param) = name.strip_prefix("after/") else {
            continue;
        };
        let (want, got) = (values(want), &step.after[param]);
        assert_eq!(want.len(), got.len(), "{param}");
        let grad = step.file.get(&format!("grad/{param}")).map(values);
        let largest = grad
            .as_ref()
            .map_or(0.0, |g| g.iter().fold(0f32, |m, v| m.max(v.abs())));
        for (i, (&w, &g)) in want.iter().zip(got).enumerate() {
            let significant = grad.as_ref().is_none_or(|d| d[i].abs() > 1e-3 * largest);
            if significant {
                assert!((w - g).abs() < 1e-6, "{param}[{i}]: torch {w}, ctxrace {g}");
                compared += 1;
            }
        }
    }
    println!("{compared} mask-SAC weights compared after the step");
    assert!(compared > 1000, "only {compared} weights compared");
}

/// A second step on the same batch (the noise of ctxrace's step 1), after the first step's
/// updates: Adam's moments and bias corrections, the slow critic's average, the return
/// normaliser's second update and (cMask) the mask SAC's updated actor, critics, targets and
/// `α` agree with torch's too, to 1e-4 (the first update's last-bit differences carried
/// through the second).
#[test]
fn a_second_step_agrees_with_the_papers_torch_model() {
    for model in [Dreamerv3, Cmask] {
        let file = read(model);
        let cfg = config(model, &file);
        let dir = tempfile::tempdir().unwrap();
        let mut agent = agent_with_file_weights(model, &cfg, &file, dir.path());
        let seq = Batch::Sequence(batch(&file, &cfg));
        agent.train_step(&seq).unwrap();
        let second = agent.train_step(&seq).unwrap();
        let mut terms = [WORLD_MODEL, BEHAVIOUR].concat();
        if model == Cmask {
            terms.extend(MASK);
        }
        agrees(&second, &file, &torch("torch2", &terms, 1e-4));
    }
}

/// Every parameter the step trains (world model, actor, critic; cMask's mask actor, critics
/// and `log α`) moves against the sign of torch's gradient wherever that gradient is not
/// negligible (above 1e-3 of its tensor's largest): Adam's first step is `−lr·g/(|g| + ε)`, so
/// the move's sign is the gradient's, and the gradients agree part by part, not only in norm.
/// Nine in ten of the parameters with a gradient are compared (the others' are below the
/// threshold; exact zeros, such as the dead ReLU units of the mask networks, are not counted).
#[test]
fn every_parameter_moves_against_torchs_gradient() {
    for model in [Dreamerv3, Cmask] {
        let step = step_once(model);
        let (mut checked, mut total) = (0, 0);
        for (name, g) in &step.file {
            let Some(param) = name.strip_prefix("grad/") else {
                continue;
            };
            let g = values(g);
            let (w0, w1) = (&step.before[param], &step.after[param]);
            assert_eq!(g.len(), w0.len(), "{param}");
            let largest = g.iter().fold(0f32, |m, v| m.max(v.abs()));
            total += g.iter().filter(|&&v| v != 0.0).count();
            for (i, ((&gi, &a), &b)) in g.iter().zip(w0).zip(w1).enumerate() {
                if gi.abs() > 1e-3 * largest {
                    assert!(
                        (b - a) * gi < 0.0,
                        "{param}[{i}]: torch's gradient {gi}, ctxrace moved {a} -> {b}"
                    );
                    checked += 1;
                }
            }
        }
        println!("{model:?}: {checked} of {total} parameters compared");
        assert!(
            checked * 10 > total * 9,
            "{model:?}: only {checked} of {total} compared"
        );
    }
}
