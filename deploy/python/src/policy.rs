//! A trained agent's acting policy for Python: read from a run folder or a checkpoint as
//! `ctxrace eval` reads it ([`TrainedAgent`]), one acting [`Policy`] per row of a batch (each
//! with its own recurrent state and noise, as one actor process drives one), acting with the
//! GIL released.

use crate::{bytes_of, pairs, BindError, Result};
use ctxrace_config::LidarConfig;
use ctxrace_nn::policy::mlp::{Linear, MlpPolicy, ACTIVATIONS, INPUTS, OUTPUTS};
use ctxrace_nn::policy::PolicyError;
use ctxrace_nn::Policy;
use ctxrace_run::trained::TrainedAgent;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use rayon::prelude::*;
use std::path::PathBuf;

/// A trained agent's acting policy over batches of episodes.
#[pyclass(name = "Policy", module = "ctxrace._ctxrace")]
pub struct PyPolicy {
    agent: TrainedAgent,
    /// Values in one observation.
    obs_dim: usize,
    /// One policy per batch row, made as rows are first used.
    rows: Vec<Policy>,
    /// The run's race scenario as JSON (the default scenario's when the run is unknown).
    race: String,
}

impl PyPolicy {
    /// The experiment of the agent's run, when the run is known.
    pub(crate) fn experiment(&self) -> Option<&ctxrace_config::ExperimentConfig> {
        self.agent.experiment.as_ref()
    }

    /// Makes policies up to `n` rows, row `i` seeded by `i` until reset with a seed.
    fn grow(&mut self, n: usize) -> Result<()> {
        while self.rows.len() < n {
            let seed = self.rows.len() as u64;
            let policy = Policy::new(&self.agent.agent, self.obs_dim, &self.agent.weights, seed)?;
            self.rows.push(policy);
        }
        Ok(())
    }
}

#[pymethods]
impl PyPolicy {
    /// The policy of the checkpoint `path`, or of the checkpoint `checkpoint` (`best`,
    /// `latest`, `step-N`; none: [`CheckpointChoice::default`]) of the run folder `path`.
    #[new]
    #[pyo3(signature = (path, checkpoint=None))]
    fn new(path: PathBuf, checkpoint: Option<&str>) -> PyResult<Self> {
        let choice = crate::checkpoint_choice(checkpoint)?;
        let agent =
            TrainedAgent::load(&path, choice).map_err(|e| BindError::Trained(Box::new(e)))?;
        let mut p = Self {
            obs_dim: agent.obs_dim(),
            race: crate::race_json(&agent.race())?,
            rows: Vec::new(),
            agent,
        };
        // a checkpoint that does not fit its race is refused now, not at the first action
        p.grow(1)?;
        Ok(p)
    }

    /// The algorithm (`sac`, `dreamerv3`, `crssm`, `cmask`).
    #[getter]
    fn algo(&self) -> &'static str {
        self.agent.agent.algo.name()
    }

    /// The checkpoint folder read.
    #[getter]
    fn checkpoint(&self) -> PathBuf {
        self.agent.checkpoint.clone()
    }

    /// Values in one observation.
    #[getter]
    fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// The run's race scenario as JSON (the default scenario's when the run is unknown).
    #[getter]
    fn race_config(&self) -> &str {
        &self.race
    }

    /// The run's track, when the run is known.
    #[getter]
    fn track(&self) -> Option<String> {
        self.agent.experiment.as_ref().map(|e| e.track.clone())
    }

    /// The run's training context range, when the run is known.
    #[getter]
    fn context_range(&self) -> Option<f64> {
        self.agent
            .experiment
            .as_ref()
            .map(|e| e.train.context_range)
    }

    /// Starts new episodes in `rows` (every row made so far when `None`), restarting their noise
    /// from `seeds` (one per row) when given, as an evaluation reseeds each episode.
    #[pyo3(signature = (rows=None, seeds=None))]
    fn reset(&mut self, rows: Option<Vec<usize>>, seeds: Option<Vec<u64>>) -> PyResult<()> {
        let rows = rows.unwrap_or_else(|| (0..self.rows.len()).collect());
        if seeds.as_ref().is_some_and(|s| s.len() != rows.len()) {
            return Err(BindError::Argument("give one seed per row reset".into()).into());
        }
        self.grow(rows.iter().max().map_or(0, |&m| m + 1))?;
        for (k, &row) in rows.iter().enumerate() {
            self.rows[row].reset();
            if let Some(seeds) = &seeds {
                self.rows[row].reseed(seeds[k]);
            }
        }
        Ok(())
    }

    /// Acts on `obs` (`f32`, one observation per row) under `contexts` (`f64` pairs) for the
    /// batch rows `rows` (`0..k` when `None`), sampling unless `deterministic`, with the GIL
    /// released; returns the actions as `f64` pairs (bytes) and, for cMask, the masks it
    /// chose (`f64` pairs; `None` for the other agents).
    #[pyo3(signature = (obs, contexts, deterministic=false, rows=None))]
    fn act<'py>(
        &mut self,
        py: Python<'py>,
        obs: &[u8],
        contexts: &[u8],
        deterministic: bool,
        rows: Option<Vec<usize>>,
    ) -> PyResult<(Bound<'py, PyBytes>, Option<Bound<'py, PyBytes>>)> {
        let contexts = pairs("contexts", contexts)?;
        let k = contexts.len();
        if obs.len() != k * self.obs_dim * 4 {
            return Err(BindError::Argument(format!(
                "obs holds {} bytes where {k} observations of {} float32 need {}",
                obs.len(),
                self.obs_dim,
                k * self.obs_dim * 4
            ))
            .into());
        }
        let obs = crate::f32s("obs", obs)?;
        let rows = rows.unwrap_or_else(|| (0..k).collect());
        let mut seen = vec![false; rows.iter().max().map_or(0, |&m| m + 1)];
        if rows.len() != k || rows.iter().any(|&r| std::mem::replace(&mut seen[r], true)) {
            return Err(BindError::Argument(format!(
                "rows must name {k} distinct batch rows, one per observation"
            ))
            .into());
        }
        self.grow(seen.len())?;
        let dim = self.obs_dim;
        let mut by_row: Vec<Option<&mut Policy>> = self.rows.iter_mut().map(Some).collect();
        let mut work: Vec<(&mut Policy, &[f32], [f32; 2])> = Vec::with_capacity(k);
        for (i, &row) in rows.iter().enumerate() {
            let policy = by_row[row].take().expect("distinct rows");
            let c = contexts[i];
            work.push((
                policy,
                &obs[i * dim..(i + 1) * dim],
                [c[0] as f32, c[1] as f32],
            ));
        }
        let decisions = py
            .detach(|| {
                work.into_par_iter()
                    .map(|(policy, obs, context)| policy.act(obs, context, deterministic))
                    .collect::<std::result::Result<Vec<_>, PolicyError>>()
            })
            .map_err(BindError::from)?;
        let actions: Vec<f64> = decisions
            .iter()
            .flat_map(|d| d.action.map(f64::from))
            .collect();
        let masks: Option<Vec<f64>> = decisions
            .iter()
            .map(|d| d.mask.map(|m| m.map(f64::from)))
            .collect::<Option<Vec<_>>>()
            .map(|m| m.concat());
        Ok((
            bytes_of(py, &actions, f64::to_ne_bytes),
            masks.map(|m| bytes_of(py, &m, f64::to_ne_bytes)),
        ))
    }
}

/// Writes an MLP policy file (`ctxrace_nn::policy::mlp`'s format) to `path`: `layers` as
/// `(weight bytes, out, in, bias bytes)` of native-endian `f32`, `activation`, `inputs` and
/// `output` named as the file's metadata names them (none: the first of each list, the
/// format's default), for observations of `obs_dim` beams (none: the race's default LiDAR); the
/// policy is checked (shapes chained, 2 actions) before anything is written.
#[pyfunction]
#[pyo3(signature = (path, layers, activation=None, inputs=None, output=None, obs_dim=None))]
pub fn save_mlp_policy(
    path: PathBuf,
    layers: Vec<(Vec<u8>, usize, usize, Vec<u8>)>,
    activation: Option<&str>,
    inputs: Option<&str>,
    output: Option<&str>,
    obs_dim: Option<usize>,
) -> PyResult<()> {
    let activation = activation.unwrap_or(ACTIVATIONS[0].0);
    let inputs = inputs.unwrap_or(INPUTS[0].0);
    let output = output.unwrap_or(OUTPUTS[0].0);
    let obs_dim = obs_dim.unwrap_or_else(|| LidarConfig::default().beams);
    let layers = layers
        .into_iter()
        .map(|(weight, out, input, bias)| {
            let weight = crate::f32s("weight", &weight)?;
            let bias = crate::f32s("bias", &bias)?;
            if weight.len() != out * input || bias.len() != out {
                return Err(BindError::Argument(format!(
                    "a layer of shape ({out}, {input}) holds {} weights and {} biases",
                    weight.len(),
                    bias.len()
                )));
            }
            Ok(Linear { weight, bias })
        })
        .collect::<Result<Vec<_>>>()?;
    let policy =
        MlpPolicy::named(layers, activation, inputs, output, obs_dim).map_err(BindError::from)?;
    let bytes = policy.to_safetensors().map_err(BindError::from)?;
    std::fs::write(&path, bytes)
        .map_err(|e| BindError::Argument(format!("writing {}: {e}", path.display())))?;
    Ok(())
}
