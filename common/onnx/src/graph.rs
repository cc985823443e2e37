//! A graph under construction: nodes appended in the order they compute, each output a fresh
//! name, and the constants (weights, shapes, scalars) kept as initializers.

use crate::proto::{AttributeProto, AttributeType, DataType, NodeProto, TensorProto};

/// The nodes and initializers of a graph being built.
#[derive(Debug, Default)]
pub struct Graph {
    /// The nodes, in the order they compute.
    pub nodes: Vec<NodeProto>,
    /// The constant tensors.
    pub initializers: Vec<TensorProto>,
    /// Values named so far (the next fresh name's number).
    count: usize,
}

/// An attribute of a node: its name and value.
pub enum Attr {
    /// An integer.
    Int(&'static str, i64),
    /// A float.
    Float(&'static str, f32),
}

impl Attr {
    /// The attribute's message.
    fn proto(self) -> AttributeProto {
        let base = |name: &str, ty: AttributeType| AttributeProto {
            name: name.into(),
            r#type: Some(ty as i32),
            ..Default::default()
        };
        match self {
            Attr::Int(name, i) => AttributeProto {
                i: Some(i),
                ..base(name, AttributeType::Int)
            },
            Attr::Float(name, f) => AttributeProto {
                f: Some(f),
                ..base(name, AttributeType::Float)
            },
        }
    }
}

/// A `float` tensor `name` of shape `dims` holding `values` (row-major).
fn f32_tensor(name: &str, dims: &[usize], values: &[f32]) -> TensorProto {
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: DataType::Float as i32,
        float_data: values.to_vec(),
        name: name.into(),
        ..Default::default()
    }
}

/// An `int64` tensor `name` of shape `dims` holding `values`.
fn i64_tensor(name: &str, dims: &[usize], values: &[i64]) -> TensorProto {
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: DataType::Int64 as i32,
        int64_data: values.to_vec(),
        name: name.into(),
        ..Default::default()
    }
}

impl Graph {
    /// A fresh value name starting with `hint`.
    fn fresh(&mut self, hint: &str) -> String {
        self.count += 1;
        format!("{hint}_{}", self.count)
    }

    /// Appends the node `op` on `inputs` with `attrs`, writing `N` new values (named after
    /// `hint`), and returns their names.
    pub fn node_n<const N: usize>(
        &mut self,
        op: &str,
        inputs: &[&str],
        attrs: Vec<Attr>,
        hint: &str,
    ) -> [String; N] {
        let output: [String; N] = std::array::from_fn(|_| self.fresh(hint));
        self.nodes.push(NodeProto {
            input: inputs.iter().map(|s| s.to_string()).collect(),
            output: output.to_vec(),
            name: format!("{op}_{}", self.nodes.len()),
            op_type: op.into(),
            attribute: attrs.into_iter().map(Attr::proto).collect(),
        });
        output
    }

    /// [`Graph::node_n`] with one output.
    pub fn node(&mut self, op: &str, inputs: &[&str], attrs: Vec<Attr>, hint: &str) -> String {
        let [out] = self.node_n(op, inputs, attrs, hint);
        out
    }

    /// Exposes `value` as the graph output `name` (an `Identity` node writing it).
    pub fn output(&mut self, value: &str, name: &str) {
        self.nodes.push(NodeProto {
            input: vec![value.into()],
            output: vec![name.into()],
            name: format!("Identity_{}", self.nodes.len()),
            op_type: "Identity".into(),
            attribute: Vec::new(),
        });
    }

    /// A `float` initializer `name` of shape `dims` (names must be unique: callers prefix them
    /// by the network they belong to).
    pub fn weight(&mut self, name: &str, dims: &[usize], values: &[f32]) -> String {
        self.initializers.push(f32_tensor(name, dims, values));
        name.into()
    }

    /// A fresh `float` scalar initializer of value `v`.
    pub fn scalar(&mut self, v: f32) -> String {
        let name = self.fresh("const");
        self.weight(&name, &[], &[v])
    }

    /// A fresh `int64` initializer of shape `[values.len()]` (a shape, split sizes, axes).
    pub fn ints(&mut self, values: &[i64]) -> String {
        let name = self.fresh("ints");
        self.initializers
            .push(i64_tensor(&name, &[values.len()], values));
        name
    }

    /// `x` split along axis 1 into parts of the widths `widths`.
    pub fn split<const N: usize>(
        &mut self,
        x: &str,
        widths: [usize; N],
        hint: &str,
    ) -> [String; N] {
        let sizes = self.ints(&widths.map(|w| w as i64));
        self.node_n("Split", &[x, &sizes], vec![Attr::Int("axis", 1)], hint)
    }

    /// `parts` joined along axis 1 (the one part itself if there is one).
    pub fn concat(&mut self, parts: &[&str], hint: &str) -> String {
        match parts {
            [one] => one.to_string(),
            _ => self.node("Concat", parts, vec![Attr::Int("axis", 1)], hint),
        }
    }

    /// `x σ(x)`, ONNX (opset 17) having no SiLU operator.
    pub fn silu(&mut self, x: &str) -> String {
        let s = self.node("Sigmoid", &[x], vec![], "sigmoid");
        self.node("Mul", &[x, &s], vec![], "silu")
    }

    /// `symlog x = sign(x) ln(1 + |x|)` ([`ctxrace_nn::symlog_value`]).
    pub fn symlog(&mut self, x: &str) -> String {
        let one = self.scalar(1.0);
        let abs = self.node("Abs", &[x], vec![], "abs");
        let plus = self.node("Add", &[&abs, &one], vec![], "one_plus");
        let log = self.node("Log", &[&plus], vec![], "log");
        let sign = self.node("Sign", &[x], vec![], "sign");
        self.node("Mul", &[&sign, &log], vec![], "symlog")
    }
}
