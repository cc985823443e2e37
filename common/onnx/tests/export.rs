//! The written models decoded back: their interface (names, shapes, opset), their weights
//! (every initializer the policy's tensor of that shape and value) and their graph (every node
//! reads values computed before it), for each agent and the configurations that change the
//! graph; and the refusals.

use ctxrace_config::agents::{AlgoKind, InitialState, MaskSpace, StepAlignment};
use ctxrace_config::{AgentConfig, ExperimentConfig};
use ctxrace_nn::dreamer::PolicyNets;
use ctxrace_nn::parameters::{init, to_safetensors};
use ctxrace_nn::{Activation, Mlp, MlpShape, Parameters, Policy, Weights};
use ctxrace_onnx::proto::{DimensionValue, ModelProto, TensorProto};
use ctxrace_onnx::{export_path, export_trained, ExportError, IR_VERSION, OPSET};
use ctxrace_run::trained::{CheckpointChoice, TrainedAgent};
use prost::Message as _;
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

/// The repository's folder of recorded weights.
fn testdata() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../testdata/d6b5c40")
}

/// The small agent of `algo` recorded in testdata (16-unit networks), out of any run.
fn recorded(algo: &str) -> TrainedAgent {
    let dir = testdata().join(algo);
    let text = std::fs::read_to_string(dir.join("agent.toml")).expect("agent.toml");
    let agent =
        AgentConfig::from_saved_table(toml::from_str(&text).expect("toml")).expect("agent config");
    TrainedAgent {
        checkpoint: dir.clone(),
        agent,
        weights: std::fs::read(dir.join("policy.safetensors")).expect("weights"),
        experiment: None,
    }
}

/// An agent of `algo` with small networks changed by `tweak`, freshly initialised, for scans of
/// `beams` values (its run's race).
fn fresh(algo: AlgoKind, beams: usize, tweak: impl FnOnce(&mut AgentConfig)) -> TrainedAgent {
    let mut agent = AgentConfig {
        algo,
        ..AgentConfig::default()
    };
    let d = &mut agent.dreamer;
    (d.units, d.deter, d.hidden, d.stoch, d.classes) = (8, 12, 10, 3, 5);
    (d.head_units, d.mask.units, d.bins) = (9, 7, 15);
    agent.sac.hidden = 11;
    tweak(&mut agent);
    let weights = match algo {
        AlgoKind::Sac => {
            let shape = MlpShape {
                input: beams * agent.sac.frames,
                units: agent.sac.hidden,
                layers: agent.sac.layers,
                out: Some(4),
                act: Activation::Relu,
            };
            let mut actor = Mlp::from_weights(&mut Weights::initial(), "", &shape).expect("mlp");
            init(&mut actor, 3);
            to_safetensors(&actor)
        }
        _ => {
            let mut nets = PolicyNets::initial(&agent.dreamer(), beams, 2).expect("nets");
            // a learned initial state starts at zeros; one away from them shows it in use
            let names: Vec<String> = nets.tensors().iter().map(|t| t.name.to_string()).collect();
            nets.update(&mut |i, values| {
                if names[i] == "rssm.initial_state.w" {
                    values
                        .iter_mut()
                        .enumerate()
                        .for_each(|(j, v)| *v = j as f32 - 5.0);
                }
            });
            to_safetensors(&nets)
        }
    }
    .expect("safetensors");
    let mut experiment = ExperimentConfig::default();
    experiment.race.lidar.beams = beams;
    TrainedAgent {
        checkpoint: PathBuf::from("fresh"),
        agent,
        weights,
        experiment: Some(experiment),
    }
}

/// The model of `agent`, written and decoded back.
fn decoded(agent: &TrainedAgent) -> ModelProto {
    let bytes = export_trained(agent).expect("export").to_bytes();
    ModelProto::decode(bytes.as_slice()).expect("decode")
}

/// The shape of a graph input or output: `None` for the batch `B`.
fn shapes(values: &[ctxrace_onnx::proto::ValueInfoProto]) -> Vec<(String, Vec<Option<i64>>)> {
    values
        .iter()
        .map(|v| {
            let t = v.r#type.as_ref().and_then(|t| t.tensor_type.as_ref());
            assert_eq!(t.and_then(|t| t.elem_type), Some(1), "{} is float", v.name);
            let dims = t.and_then(|t| t.shape.as_ref()).expect("shape").dim.iter();
            let dims = dims.map(|d| match d.value.as_ref() {
                Some(DimensionValue::DimValue(n)) => Some(*n),
                Some(DimensionValue::DimParam(p)) => {
                    assert_eq!(p, "B");
                    None
                }
                None => panic!("{}: an axis of no size", v.name),
            });
            (v.name.clone(), dims.collect())
        })
        .collect()
}

/// The model's interface is the issue's, for scans of `o` values, a state of `s` and (cMask)
/// the mask; every node reads graph inputs, initializers or earlier nodes' outputs, and the
/// outputs are computed.
fn check_interface(m: &ModelProto, o: i64, s: i64, mask: bool) {
    assert_eq!(m.ir_version, IR_VERSION);
    assert_eq!(m.opset_import.len(), 1);
    assert_eq!(
        (m.opset_import[0].domain.as_str(), m.opset_import[0].version),
        ("", OPSET)
    );
    let g = m.graph.as_ref().expect("graph");
    let b = None;
    let want_in = [
        ("obs", vec![b, Some(o)]),
        ("context", vec![b, Some(2)]),
        ("is_first", vec![b]),
        ("state", vec![b, Some(s)]),
    ];
    let mut want_out = vec![
        ("action", vec![b, Some(2)]),
        ("state_out", vec![b, Some(s)]),
    ];
    if mask {
        want_out.push(("mask", vec![b, Some(2)]));
    }
    let named = |w: &[(&str, Vec<Option<i64>>)]| -> Vec<(String, Vec<Option<i64>>)> {
        w.iter().map(|(n, d)| (n.to_string(), d.clone())).collect()
    };
    assert_eq!(shapes(&g.input), named(&want_in));
    assert_eq!(shapes(&g.output), named(&want_out));
    let mut known: HashSet<&str> = g.input.iter().map(|v| v.name.as_str()).collect();
    let inits: HashSet<&str> = g.initializer.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(
        inits.len(),
        g.initializer.len(),
        "initializer names are unique"
    );
    known.extend(&inits);
    for node in &g.node {
        for input in &node.input {
            assert!(
                known.contains(input.as_str()),
                "{} reads {input} first",
                node.op_type
            );
        }
        for output in &node.output {
            assert!(known.insert(output), "{output} written twice");
        }
    }
    for out in &g.output {
        assert!(
            known.contains(out.name.as_str()),
            "{} is computed",
            out.name
        );
    }
}

/// The model's initializers by name.
fn initializers(m: &ModelProto) -> HashMap<&str, &TensorProto> {
    let g = m.graph.as_ref().expect("graph");
    g.initializer.iter().map(|t| (t.name.as_str(), t)).collect()
}

/// The prefixes of the networks' initializers.
const NETS: [&str; 4] = ["encoder.", "rssm.", "actor.", "mask."];

/// The number of initializers named `{prefix}…`.
fn count_under(m: &ModelProto, prefix: &str) -> usize {
    let g = m.graph.as_ref().expect("graph");
    g.initializer
        .iter()
        .filter(|t| t.name.starts_with(prefix))
        .count()
}

/// The operator of the node that computes graph output `name` (through its `Identity`).
fn op_of_output(m: &ModelProto, name: &str) -> String {
    let g = m.graph.as_ref().expect("graph");
    let writer = |v: &str| g.node.iter().find(|n| n.output.iter().any(|o| o == v));
    let identity = writer(name).expect("an output node");
    writer(&identity.input[0])
        .expect("its input's node")
        .op_type
        .clone()
}

/// Whether a node reads graph input `name`.
fn reads(m: &ModelProto, name: &str) -> bool {
    let g = m.graph.as_ref().expect("graph");
    g.node.iter().any(|n| n.input.iter().any(|i| i == name))
}

/// The dims of initializer `name`.
fn dims(m: &ModelProto, name: &str) -> Vec<i64> {
    initializers(m)
        .get(name)
        .unwrap_or_else(|| panic!("no initializer {name}"))
        .dims
        .clone()
}

#[test]
fn the_recorded_agents_export_with_the_issues_interface_and_their_weights() {
    for (algo, s, mask) in [
        ("sac", 108, false),
        ("dreamerv3", 16 + 16 + 2, false),
        ("crssm", 16 + 16 + 2, false),
        ("cmask", 16 + 16 + 2, true),
    ] {
        let agent = recorded(algo);
        let model = decoded(&agent);
        check_interface(&model, 108, s, mask);
        let meta: HashMap<_, _> = model
            .metadata_props
            .iter()
            .map(|e| (e.key.as_str(), e.value.as_str()))
            .collect();
        assert_eq!(meta["ctxrace.algo"], algo);
        assert_eq!(meta["ctxrace.obs_dim"], "108");
        // every weight the acting networks read, once (SAC: the actor's; the DreamerV3
        // family: all but the prior's, which a posterior step does not run)
        let policy = Policy::new(&agent.agent, 108, &agent.weights, 0).expect("policy");
        let acting: Vec<(String, Vec<usize>, usize)> = match &policy {
            Policy::Sac(p) => tensors(p.actor()),
            Policy::Dreamer(p) => {
                let nets = p.nets();
                let [img_in, gates, _, _, post, post_out] = nets.rssm.layers();
                let mut v = tensors(&nets.encoder);
                for l in [img_in, gates, post, post_out] {
                    v.extend(layer_tensors(l));
                }
                v.extend(tensors(&nets.actor));
                v.extend(nets.mask.iter().flat_map(tensors));
                v
            }
            Policy::Mlp(_) => unreachable!("a trained agent"),
        };
        let g = model.graph.as_ref().expect("graph");
        let mut written: Vec<(Vec<usize>, usize)> = g
            .initializer
            .iter()
            .filter(|t| NETS.iter().any(|net| t.name.starts_with(net)))
            .map(|t| {
                (
                    t.dims.iter().map(|&d| d as usize).collect(),
                    t.float_data.len(),
                )
            })
            .collect();
        let mut want: Vec<(Vec<usize>, usize)> =
            acting.into_iter().map(|(_, d, n)| (d, n)).collect();
        written.sort();
        want.sort();
        assert_eq!(written, want, "{algo}: one initializer per acting tensor");
    }
}

/// `(name, shape, values)` of an MLP's tensors (as [`ctxrace_nn::Parameters`] lists them).
fn tensors(mlp: &Mlp) -> Vec<(String, Vec<usize>, usize)> {
    mlp.layers().iter().flat_map(layer_tensors).collect()
}

/// `(name, shape, values)` of a layer's tensors.
fn layer_tensors(l: &ctxrace_nn::Layer) -> Vec<(String, Vec<usize>, usize)> {
    l.tensors()
        .into_iter()
        .map(|t| (t.name.to_string(), t.shape, t.values.len()))
        .collect()
}

#[test]
fn the_obs_width_is_the_runs_and_the_context_is_read_where_the_agent_reads_it() {
    for (algo, reads_context) in [
        (AlgoKind::Sac, false),
        (AlgoKind::Dreamerv3, false),
        (AlgoKind::Crssm, true),
        (AlgoKind::Cmask, true),
    ] {
        let model = decoded(&fresh(algo, 64, |_| {}));
        let (s, mask) = match algo {
            AlgoKind::Sac => (64, false),
            _ => (12 + 15 + 2, algo == AlgoKind::Cmask),
        };
        check_interface(&model, 64, s, mask);
        assert_eq!(reads(&model, "context"), reads_context, "{algo:?}");
        assert!(reads(&model, "is_first") && reads(&model, "obs"));
    }
}

#[test]
fn configurations_that_change_the_decision_change_the_graph() {
    let dreamer = |tweak: fn(&mut AgentConfig)| decoded(&fresh(AlgoKind::Cmask, 20, tweak));
    // the paper's step alignment: the encoder reads [o, a_{t-1}]
    let plain = dreamer(|_| {});
    let paper = dreamer(|a| a.dreamer.step_alignment = StepAlignment::PaperCode);
    assert_eq!(dims(&plain, "encoder.l0.weight"), [8, 20]);
    assert_eq!(dims(&paper, "encoder.l0.weight"), [8, 22]);
    // an encoder of depth 0: the posterior reads [h, symlog o]
    let shallow = dreamer(|a| a.dreamer.layers = 0);
    assert_eq!(count_under(&shallow, "encoder."), 0);
    assert_eq!(dims(&shallow, "rssm.post.weight"), [10, 12 + 20]);
    // the mask of tanh μ: (a + 1)/2 or σ(a)
    let sigmoid = dreamer(|a| a.dreamer.mask.mask_space = MaskSpace::PaperCode);
    assert_eq!(op_of_output(&plain, "mask"), "Add");
    assert_eq!(op_of_output(&sigmoid, "mask"), "Sigmoid");
    // deeper heads, more layers; SAC's stack of 3 frames keeps 2
    let deep = dreamer(|a| (a.dreamer.head_layers, a.dreamer.mask.layers) = (3, 1));
    assert_eq!(count_under(&deep, "actor."), 3 * 3 + 2);
    assert_eq!(count_under(&deep, "mask."), 2 + 2);
    let sac = decoded(&fresh(AlgoKind::Sac, 20, |a| a.sac.frames = 3));
    check_interface(&sac, 20, 40, false);
    assert_eq!(dims(&sac, "actor.l0.weight"), [11, 60]);
}

#[test]
fn episodes_start_from_the_policys_initial_state() {
    for initial in [InitialState::Zeros, InitialState::Learned] {
        let agent = fresh(AlgoKind::Crssm, 16, |a| a.dreamer.initial_state = initial);
        let model = decoded(&agent);
        let Policy::Dreamer(p) = Policy::new(&agent.agent, 16, &agent.weights, 0).expect("policy")
        else {
            unreachable!("a DreamerV3 agent")
        };
        let (h0, z0) = p.initial_state();
        let want = [h0, z0, &[0.0, 0.0]].concat();
        let start = initializers(&model)["initial_state"];
        assert_eq!(start.dims, [1, want.len() as i64]);
        assert_eq!(start.float_data, want);
        // the learned state's h_0 = tanh(w) and one class per variable
        let ones = z0.iter().filter(|&&v| v == 1.0).count();
        match initial {
            InitialState::Zeros => assert!(want.iter().all(|&v| v == 0.0)),
            InitialState::Learned => assert!(h0.iter().any(|&v| v != 0.0) && ones == 3),
        }
    }
}

#[test]
fn agents_without_a_deterministic_model_and_bad_paths_are_refused() {
    let noisy = fresh(AlgoKind::Sac, 16, |a| a.sac.explore_noise = 0.1);
    let err = export_trained(&noisy).expect_err("noise");
    assert!(matches!(err, ExportError::ExploreNoise(_)), "{err}");
    assert!(err.to_string().contains("explore_noise = 0"), "{err}");
    let carried = fresh(AlgoKind::Sac, 16, |a| a.sac.reset_frame_stack = false);
    let err = export_trained(&carried).expect_err("stack");
    assert!(
        err.to_string().contains("reset_frame_stack = true"),
        "{err}"
    );
    // weights of another architecture
    let mut other = fresh(AlgoKind::Crssm, 16, |_| {});
    other.agent.dreamer.deter = 13;
    let err = export_trained(&other).expect_err("shapes");
    assert!(matches!(err, ExportError::Policy(_)), "{err}");
    // an MLP policy file, and a folder that is no run
    let dir = tempfile::tempdir().expect("tempdir");
    let mlp = dir.path().join("mlp.safetensors");
    std::fs::write(&mlp, b"weights").expect("write");
    let err = export_path(&mlp, CheckpointChoice::Best).expect_err("mlp");
    assert!(err.to_string().contains("MLP policy file"), "{err}");
    let err = export_path(dir.path(), CheckpointChoice::Best).expect_err("no run");
    assert!(err.to_string().contains("neither a checkpoint"), "{err}");
    // and a model that cannot be written names its file
    let model = export_trained(&recorded("sac")).expect("export");
    let err = model
        .write(&dir.path().join("no/such/dir.onnx"))
        .expect_err("write");
    assert!(err.to_string().contains("no/such/dir.onnx"), "{err}");
    let out = dir.path().join("sac.onnx");
    assert_eq!(model.write(&out).expect("write"), model.to_bytes().len());
    assert_eq!(std::fs::read(&out).expect("read"), model.to_bytes());
}
