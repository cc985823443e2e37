//! ctxrace's layers and MLPs ([`ctxrace_nn::Layer`], [`ctxrace_nn::Mlp`]) as ONNX nodes.
//!
//! A layer is `p = x Wᵀ (+ b)`, one `Gemm` with `W` `[out, in]` kept as stored (`transB = 1`),
//! then what follows it:
//!
//! ```text
//! normalised:  y = act(γ (p − μ)/√(σ² + ε) + β)   LayerNormalization (axis −1, ε), then
//!              act = SiLU: y σ(y) (Sigmoid, Mul), or the identity
//! ReLU:        y = max(p, 0)                       Relu
//! nothing:     y = p
//! ```
//!
//! with `μ`, `σ²` the mean and (biased) variance of each row, as the networks normalise. The
//! weights become initializers named `{prefix}.l{i}.weight`, `.bias`, `.ln.scale`, `.ln.bias`.

use crate::graph::{Attr, Graph};
use ctxrace_nn::layer::After;
use ctxrace_nn::{Layer, Mlp, NormAct};

/// The nodes of `layer` on `x` (rows of `layer.inputs()` values), its weights named after
/// `name`; returns its output.
pub fn layer(g: &mut Graph, name: &str, layer: &Layer, x: &str) -> String {
    let (m, k) = (layer.outputs(), layer.inputs());
    let w = g.weight(&format!("{name}.weight"), &[m, k], layer.weight());
    let mut inputs = vec![x.to_string(), w];
    if let Some(b) = layer.bias() {
        inputs.push(g.weight(&format!("{name}.bias"), &[m], b));
    }
    let inputs: Vec<&str> = inputs.iter().map(String::as_str).collect();
    let p = g.node("Gemm", &inputs, vec![Attr::Int("transB", 1)], "product");
    match layer.after() {
        After::Nothing => p,
        After::Relu => g.node("Relu", &[&p], vec![], "relu"),
        After::Norm(n) => {
            let gain = g.weight(&format!("{name}.ln.scale"), &[m], &n.gain);
            let bias = g.weight(&format!("{name}.ln.bias"), &[m], &n.bias);
            let attrs = vec![Attr::Int("axis", -1), Attr::Float("epsilon", n.eps)];
            let y = g.node("LayerNormalization", &[&p, &gain, &bias], attrs, "norm");
            match n.act {
                NormAct::Identity => y,
                NormAct::Silu => g.silu(&y),
            }
        }
    }
}

/// The nodes of `mlp` on `x`, its layers' weights named `{prefix}.l{i}`; returns its output
/// (`x` itself for a network without layers, as an encoder of depth 0 passes its input on).
pub fn mlp(g: &mut Graph, prefix: &str, mlp: &Mlp, x: &str) -> String {
    mlp.layers()
        .iter()
        .enumerate()
        .fold(x.to_string(), |x, (i, l)| {
            layer(g, &format!("{prefix}.l{i}"), l, &x)
        })
}
