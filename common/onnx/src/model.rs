//! The model's interface, the same for every agent: its inputs and outputs, how a decision
//! starts an episode, the layout of its state, and the `ModelProto` around a decision's graph.

use crate::graph::{Attr, Graph};
use crate::proto::{
    DataType, Dimension, DimensionValue, GraphProto, ModelProto, OperatorSetIdProto,
    StringStringEntryProto, TensorShapeProto, TensorTypeProto, TypeProto, ValueInfoProto,
};
use ctxrace_config::agents::CONTEXT_DIM;
use ctxrace_nn::policy::ACT_DIM;

/// The ONNX operator set the models use (17: the first with `LayerNormalization`).
pub const OPSET: i64 = 17;

/// The IR version the models are written in (8: ONNX 1.12, the one of opset 17).
pub const IR_VERSION: i64 = 8;

/// Input: the LiDAR scans, `(B, obs_dim)`.
pub const OBS: &str = "obs";
/// Input: the episodes' raw contexts `(c_v, c_θ)`, `(B, 2)` (read by cRSSM and cMask only).
pub const CONTEXT: &str = "context";
/// Input: `(B,)`, non-zero where a decision starts an episode (its `state` is then ignored).
pub const IS_FIRST: &str = "is_first";
/// Input: the state the previous decision returned, `(B, S)`.
pub const STATE: &str = "state";
/// Output: the deterministic actions `(steering, speed)` in `[−1, 1]`, `(B, 2)`.
pub const ACTION: &str = "action";
/// Output: the state to pass to the next decision, `(B, S)`.
pub const STATE_OUT: &str = "state_out";
/// Output (cMask only): the context mask `m`, `(B, 2)`.
pub const MASK: &str = "mask";

/// The parts of a model's state, in order: each a name and a width.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StateLayout(pub Vec<(String, usize)>);

impl StateLayout {
    /// `S`, the state's width.
    pub fn width(&self) -> usize {
        self.0.iter().map(|(_, w)| w).sum()
    }
}

impl std::fmt::Display for StateLayout {
    /// `h [0, 64), z [64, 128), prev_action [128, 130)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut start = 0;
        for (i, (name, w)) in self.0.iter().enumerate() {
            let sep = if i == 0 { "" } else { ", " };
            write!(f, "{sep}{name} [{start}, {})", start + w)?;
            start += w;
        }
        Ok(())
    }
}

/// The state a decision continues from: `start` (`(1, S)` or `(B, S)`) where [`IS_FIRST`] is
/// non-zero, else [`STATE`] (a `Where`, so that a first decision's `state` is not read at all,
/// whatever it holds).
pub fn state_in(g: &mut Graph, start: &str) -> String {
    let column = g.ints(&[-1, 1]);
    let first = g.node("Reshape", &[IS_FIRST, &column], vec![], "is_first");
    let to_bool = vec![Attr::Int("to", DataType::Bool as i64)];
    let first = g.node("Cast", &[&first], to_bool, "starts");
    g.node("Where", &[&first, start, STATE], vec![], "state_in")
}

/// A float tensor's type of shape `dims` (`None`: the batch `B`).
fn tensor_type(dims: &[Option<usize>]) -> TypeProto {
    let dim = dims
        .iter()
        .map(|d| Dimension {
            value: Some(match d {
                Some(n) => DimensionValue::DimValue(*n as i64),
                None => DimensionValue::DimParam("B".into()),
            }),
        })
        .collect();
    TypeProto {
        tensor_type: Some(TensorTypeProto {
            elem_type: Some(DataType::Float as i32),
            shape: Some(TensorShapeProto { dim }),
        }),
    }
}

/// A graph input or output: `name`, a float tensor of shape `dims`, and what it is.
fn value(name: &str, dims: &[Option<usize>], doc: &str) -> ValueInfoProto {
    ValueInfoProto {
        name: name.into(),
        r#type: Some(tensor_type(dims)),
        doc_string: doc.into(),
    }
}

/// What a model takes and gives besides its graph.
pub struct Interface<'a> {
    /// Values in one observation.
    pub obs_dim: usize,
    /// The state's parts.
    pub state: &'a StateLayout,
    /// Whether it gives cMask's mask ([`MASK`]).
    pub mask: bool,
    /// What it is, for people (the model's doc string).
    pub doc: String,
    /// Named strings about it (`ctxrace.algo`, ...).
    pub metadata: Vec<(String, String)>,
}

/// Graph inputs or outputs as `(name, shape)`, `None` in a shape for the batch `B`.
pub type Values = Vec<(&'static str, Vec<Option<usize>>)>;

/// The inputs' and outputs' names and shapes.
pub fn signature(obs_dim: usize, s: usize, mask: bool) -> (Values, Values) {
    let inputs = vec![
        (OBS, vec![None, Some(obs_dim)]),
        (CONTEXT, vec![None, Some(CONTEXT_DIM)]),
        (IS_FIRST, vec![None]),
        (STATE, vec![None, Some(s)]),
    ];
    let mut outputs = vec![
        (ACTION, vec![None, Some(ACT_DIM)]),
        (STATE_OUT, vec![None, Some(s)]),
    ];
    if mask {
        outputs.push((MASK, vec![None, Some(CONTEXT_DIM)]));
    }
    (inputs, outputs)
}

/// What each input and output is (the value's doc string).
fn value_doc(name: &str, layout: &StateLayout) -> String {
    match name {
        OBS => "the LiDAR scan, as the env observes it".into(),
        CONTEXT => "the episode's raw context (c_v, c_theta)".into(),
        IS_FIRST => "1 where the decision starts an episode (state is then ignored), else 0".into(),
        STATE => format!("the previous decision's state_out: {layout}"),
        ACTION => "the deterministic action (steering, speed) in [-1, 1]".into(),
        STATE_OUT => format!("the state for the next decision: {layout}"),
        _ => "cMask's context mask m in [0, 1]".into(),
    }
}

/// The model of the decision graph `g`, whose outputs are named as the interface's.
pub fn model(g: Graph, interface: Interface) -> ModelProto {
    let layout = interface.state;
    let (inputs, outputs) = signature(interface.obs_dim, layout.width(), interface.mask);
    let values = |list: Values| {
        list.into_iter()
            .map(|(name, dims)| value(name, &dims, &value_doc(name, layout)))
            .collect()
    };
    let graph = GraphProto {
        node: g.nodes,
        name: "ctxrace_decision".into(),
        initializer: g.initializers,
        doc_string: interface.doc.clone(),
        input: values(inputs),
        output: values(outputs),
    };
    ModelProto {
        ir_version: IR_VERSION,
        opset_import: vec![OperatorSetIdProto {
            domain: String::new(),
            version: OPSET,
        }],
        producer_name: "ctxrace".into(),
        producer_version: env!("CARGO_PKG_VERSION").into(),
        doc_string: interface.doc,
        graph: Some(graph),
        metadata_props: interface
            .metadata
            .into_iter()
            .map(|(key, value)| StringStringEntryProto { key, value })
            .collect(),
    }
}
