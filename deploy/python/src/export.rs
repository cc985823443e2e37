//! A trained agent exported for use outside ctxrace: its ONNX model ([`ctxrace_onnx`]), read
//! from a run folder or a checkpoint as `ctxrace export onnx` reads it.

use crate::Result;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// Writes the ONNX model of the trained agent at `path` (a checkpoint folder, or the checkpoint
/// `checkpoint` of a run folder) to `out`; returns what was written: `algo`, `obs_dim`,
/// `state_dim`, `state` (the state's parts as `(name, start, stop)`), `outputs`, `opset` and
/// `bytes`.
#[pyfunction]
#[pyo3(signature = (path, out, checkpoint=None))]
pub fn export_onnx<'py>(
    py: Python<'py>,
    path: PathBuf,
    out: PathBuf,
    checkpoint: Option<&str>,
) -> PyResult<Bound<'py, PyDict>> {
    let choice = crate::checkpoint_choice(checkpoint)?;
    let (model, bytes) = py.detach(|| -> Result<_> {
        let model = ctxrace_onnx::export_path(&path, choice)?;
        let bytes = model.write(&out)?;
        Ok((model, bytes))
    })?;
    let mut start = 0;
    let state: Vec<(String, usize, usize)> = model
        .state
        .0
        .iter()
        .map(|(name, w)| {
            start += w;
            (name.clone(), start - w, start)
        })
        .collect();
    let mut outputs = vec![ctxrace_onnx::model::ACTION, ctxrace_onnx::model::STATE_OUT];
    if model.mask {
        outputs.push(ctxrace_onnx::model::MASK);
    }
    let d = PyDict::new(py);
    d.set_item("algo", model.algo)?;
    d.set_item("obs_dim", model.obs_dim)?;
    d.set_item("state_dim", model.state_dim())?;
    d.set_item("state", state)?;
    d.set_item("outputs", outputs)?;
    d.set_item("opset", ctxrace_onnx::OPSET)?;
    d.set_item("bytes", bytes)?;
    Ok(d)
}
