//! ctxrace's trained agents as ONNX models, so that a trained agent acts outside ctxrace (on a
//! car's computer, under onnxruntime): one deterministic decision a call, for a batch of `B`
//! episodes.
//!
//! | input | shape | |
//! |---|---|---|
//! | `obs` | `(B, O)` | the LiDAR scan (`O` the run's `[race.lidar] beams`, 108 by default) |
//! | `context` | `(B, 2)` | the episode's raw context `(c_v, c_θ)` (read by cRSSM and cMask) |
//! | `is_first` | `(B,)` | non-zero where the decision starts an episode; its `state` is then ignored |
//! | `state` | `(B, S)` | the previous decision's `state_out` |
//!
//! | output | shape | |
//! |---|---|---|
//! | `action` | `(B, 2)` | the deterministic action (steering, speed) in `[−1, 1]` |
//! | `state_out` | `(B, S)` | the state for the next decision |
//! | `mask` | `(B, 2)` | cMask only: its context mask `m` |
//!
//! Stepped from `is_first = 1` with each call's `state_out` passed on, a model's actions are
//! the acting policy's ([`ctxrace_nn::Policy::act`] with `deterministic`) after
//! [`ctxrace_nn::Policy::reset`], up to the rounding of floating-point arithmetic. The state
//! is, for the DreamerV3 family, `[h, z, a_{t−1}]` ([`dreamer`]); for SAC, the previous scans
//! of its frame stack ([`sac`]); the model's doc string and metadata (`ctxrace.state`) name its
//! parts.
//!
//! - [`proto`]: the ONNX messages (prost); [`graph`]: a graph under construction;
//!   [`nets`]: layers and MLPs as nodes; [`model`]: the interface and the model around a graph.
//! - [`dreamer`], [`sac`]: each family's decision.

pub mod dreamer;
pub mod graph;
pub mod model;
pub mod nets;
pub mod proto;
pub mod sac;

use ctxrace_nn::policy::{Policy, PolicyError};
use ctxrace_run::trained::{CheckpointChoice, TrainedAgent, TrainedAgentError};
use model::{Interface, StateLayout};
use prost::Message as _;
use std::path::{Path, PathBuf};

pub use model::{IR_VERSION, OPSET};

/// Why an agent could not be exported, or its model not written; each names the way out.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The path is an MLP policy file, a network trained elsewhere.
    #[error(
        "{} is an MLP policy file (a policy trained outside ctxrace); export a ctxrace run or \
         checkpoint folder, and the MLP from the framework that trained it (e.g. \
         torch.onnx.export)",
        .0.display()
    )]
    MlpFile(PathBuf),
    /// The trained agent could not be read back.
    #[error(transparent)]
    Trained(Box<TrainedAgentError>),
    /// Its policy refused its weights.
    #[error(transparent)]
    Policy(#[from] PolicyError),
    /// A SAC agent that adds noise to every action, deterministic ones too.
    #[error(
        "this SAC agent adds exploration noise (agent.sac.explore_noise = {0}) to every action, \
         deterministic ones too, so no deterministic model acts as it does; export an agent \
         trained with explore_noise = 0"
    )]
    ExploreNoise(f32),
    /// A SAC agent that carries its frame stack from one episode into the next.
    #[error(
        "this SAC agent carries its frame stack into the next episode \
         (agent.sac.reset_frame_stack = false), which a model whose is_first restarts the stack \
         does not do; export an agent trained with reset_frame_stack = true"
    )]
    CarriedFrameStack,
    /// The model could not be written.
    #[error("writing {}", .path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
}

impl From<TrainedAgentError> for ExportError {
    fn from(e: TrainedAgentError) -> Self {
        Self::Trained(Box::new(e))
    }
}

/// The outcome of an export.
pub type Result<T> = std::result::Result<T, ExportError>;

/// A trained agent's ONNX model and what a caller needs to drive it.
#[derive(Clone, Debug)]
pub struct OnnxPolicy {
    /// The model.
    pub model: proto::ModelProto,
    /// The algorithm (`sac`, `dreamerv3`, `crssm`, `cmask`).
    pub algo: &'static str,
    /// `O`, values in one observation.
    pub obs_dim: usize,
    /// The state's parts, in order (`S` their widths' sum).
    pub state: StateLayout,
    /// Whether it gives cMask's `mask`.
    pub mask: bool,
}

impl OnnxPolicy {
    /// The model's bytes (an `.onnx` file).
    pub fn to_bytes(&self) -> Vec<u8> {
        self.model.encode_to_vec()
    }

    /// Writes the model to `path`; returns its size in bytes.
    pub fn write(&self, path: &Path) -> Result<usize> {
        let bytes = self.to_bytes();
        std::fs::write(path, &bytes).map_err(|source| ExportError::Write {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(bytes.len())
    }

    /// `S`, the state's width.
    pub fn state_dim(&self) -> usize {
        self.state.width()
    }
}

impl std::fmt::Display for OnnxPolicy {
    /// Its inputs, outputs and state, one line each.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let shape = |dims: &[Option<usize>]| {
            let dims: Vec<String> = dims
                .iter()
                .map(|d| d.map_or("B".into(), |n| n.to_string()))
                .collect();
            match dims.as_slice() {
                [one] => format!("({one},)"),
                _ => format!("({})", dims.join(", ")),
            }
        };
        let list = |values: model::Values| {
            let v: Vec<String> = values
                .iter()
                .map(|(name, dims)| format!("{name} {}", shape(dims)))
                .collect();
            v.join(", ")
        };
        let (inputs, outputs) = model::signature(self.obs_dim, self.state_dim(), self.mask);
        writeln!(f, "{} agent, ONNX opset {OPSET}", self.algo)?;
        writeln!(f, "inputs:  {}", list(inputs))?;
        writeln!(f, "outputs: {}", list(outputs))?;
        write!(f, "state:   S = {}: {}", self.state_dim(), self.state)
    }
}

/// The model of the trained agent at `path`: a checkpoint folder, or the checkpoint `choice` of
/// a run folder (read and verified as `ctxrace eval` reads it); an MLP policy file is refused.
pub fn export_path(path: &Path, choice: CheckpointChoice) -> Result<OnnxPolicy> {
    if ctxrace_nn::policy::mlp::is_mlp_file(path) {
        return Err(ExportError::MlpFile(path.to_path_buf()));
    }
    export_trained(&TrainedAgent::load(path, choice)?)
}

/// The model of `agent`, for the observations of its run's race ([`TrainedAgent::obs_dim`]).
pub fn export_trained(agent: &TrainedAgent) -> Result<OnnxPolicy> {
    let obs_dim = agent.obs_dim();
    let policy = Policy::new(&agent.agent, obs_dim, &agent.weights, 0)?;
    let mut g = graph::Graph::default();
    let (state, mask) = match &policy {
        Policy::Sac(p) => (sac::decision(&mut g, p)?, false),
        Policy::Dreamer(p) => (dreamer::decision(&mut g, p), p.nets().mask.is_some()),
        // a trained agent's policy is never an MLP file's
        Policy::Mlp(_) => return Err(ExportError::MlpFile(agent.checkpoint.clone())),
    };
    let algo = agent.agent.algo.name();
    let doc = format!(
        "ctxrace {algo} agent ({}): one deterministic decision a call. Inputs obs (B, {obs_dim}), \
         context (B, 2), is_first (B,) (non-zero starts an episode and ignores state), state \
         (B, {s}); outputs action (B, 2), state_out (B, {s}){}. State: {state}.",
        agent.checkpoint.display(),
        if mask { ", mask (B, 2)" } else { "" },
        s = state.width(),
    );
    let metadata = vec![
        ("ctxrace.algo".into(), algo.into()),
        (
            "ctxrace.checkpoint".into(),
            agent.checkpoint.display().to_string(),
        ),
        ("ctxrace.obs_dim".into(), obs_dim.to_string()),
        ("ctxrace.state".into(), state.to_string()),
    ];
    let interface = Interface {
        obs_dim,
        state: &state,
        mask,
        doc,
        metadata,
    };
    let model = model::model(g, interface);
    Ok(OnnxPolicy {
        model,
        algo,
        obs_dim,
        state,
        mask,
    })
}
