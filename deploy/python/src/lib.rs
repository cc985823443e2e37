//! The extension module `ctxrace._ctxrace` of the `ctxrace` Python package: races stepped in
//! Rust for the package's Gymnasium envs ([`vector::PyRaceVector`]) and the paper's evaluation
//! protocol ([`evaluate`]), trained agents' acting policies ([`policy`]) and their ONNX models
//! ([`export`]). It links the
//! simulator library (`ctxrace-sim`, its tracks and configuration), the run's files
//! (`ctxrace-run`) and the networks (`ctxrace-nn`), never the transport. Arrays cross as native-endian bytes that
//! the Python side views with numpy; errors become Python exceptions naming what to fix.

mod agents;
mod evaluate;
mod export;
mod policy;
mod tracks;
mod vector;

use ctxrace_config::config_file::{read_config_table, ConfigFileError};
use ctxrace_config::preset::merge_tables;
use ctxrace_config::validate::Causes;
use ctxrace_config::{ContextError, RaceConfig, RaceConfigError};
use ctxrace_nn::policy::PolicyError;
use ctxrace_run::trained::{CheckpointChoice, TrainedAgentError, UnknownCheckpointChoice};
use ctxrace_sim::vector::VectorError;
use ctxrace_tracks::{Track, TrackError, TrackOptions};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

/// Why a call from Python was refused.
#[derive(Debug, thiserror::Error)]
pub enum BindError {
    /// A race config file could not be read (a folder, too large, not text).
    #[error("race config")]
    Read(#[from] ConfigFileError),
    /// The race keyword arguments are no TOML table.
    #[error(
        "race keys (give numbers, strings, booleans and dicts of them, as the TOML configs do)"
    )]
    Keys(#[source] Box<dyn std::error::Error + Send + Sync>),
    /// The race configuration is refused.
    #[error(transparent)]
    Race(#[from] RaceConfigError),
    /// The track could not be loaded.
    #[error("loading track '{spec}'")]
    Track {
        /// The track as given.
        spec: String,
        /// Why.
        #[source]
        source: Box<TrackError>,
    },
    /// A context is out of range.
    #[error(transparent)]
    Context(#[from] ContextError),
    /// The vector of races refused the call.
    #[error(transparent)]
    Vector(#[from] VectorError),
    /// The race refused an argument or could not go on.
    #[error(transparent)]
    Sim(#[from] ctxrace_sim::RaceError),
    /// An array's bytes do not hold whole values.
    #[error("{what} holds {bytes} bytes, no whole number of {size}-byte values")]
    Bytes {
        /// Which argument.
        what: &'static str,
        /// Its length in bytes.
        bytes: usize,
        /// The size of one value.
        size: usize,
    },
    /// A trained agent could not be read back.
    #[error(transparent)]
    Trained(Box<TrainedAgentError>),
    /// A trained agent could not be exported, or its model not written.
    #[error(transparent)]
    Export(#[from] ctxrace_onnx::ExportError),
    /// A trained agent's policy refused its weights or an observation.
    #[error(transparent)]
    Policy(#[from] PolicyError),
    /// An argument out of its range (a reference policy's name, the grid's size).
    #[error("{0}")]
    Argument(String),
    /// The race could not be drawn.
    #[error("drawing the race")]
    Render(#[source] Box<dyn std::error::Error + Send + Sync>),
}

impl From<BindError> for PyErr {
    fn from(e: BindError) -> PyErr {
        let message = Causes(&e).to_string();
        match e {
            BindError::Vector(VectorError::NotReset) => PyRuntimeError::new_err(message),
            _ => PyValueError::new_err(message),
        }
    }
}

/// The outcome of a call from Python.
type Result<T> = std::result::Result<T, BindError>;

/// The race of a TOML config file (none: an empty table) with `keys_json` laid over it: a JSON
/// object of race keys (tables as objects, `null` as a key not given); each key replaces the
/// file's, tables merged key by key; keys neither gives take the values of the preset named.
fn race_config(config: Option<PathBuf>, keys_json: &str) -> Result<RaceConfig> {
    let table = config
        .as_deref()
        .map(read_config_table)
        .transpose()?
        .unwrap_or_default();
    Ok(RaceConfig::from_table(merge_tables(
        table,
        keys_table(keys_json)?,
    ))?)
}

/// `cfg` with `agents` cars driven from Python besides its scripted rivals (the ego and the
/// `agents - 1` cars ahead of it on the grid: its `rivals` then count every car but the ego),
/// or the error naming both counts where the grid has too few places.
fn with_agents(mut cfg: RaceConfig, agents: usize) -> Result<RaceConfig> {
    let most = ctxrace_config::MAX_RIVALS + 1;
    if agents == 0 {
        return Err(BindError::Argument(
            "agents must be at least 1, not 0".into(),
        ));
    }
    if agents + cfg.rivals > most {
        return Err(BindError::Argument(format!(
            "agents = {agents} and rivals = {} make {} cars where a race holds {most}: \
             agents + rivals must be at most {most}",
            cfg.rivals,
            agents + cfg.rivals
        )));
    }
    cfg.rivals += agents - 1;
    Ok(cfg)
}

/// A JSON object of race keys (`null`s: keys not given, left out) as a TOML table.
fn keys_table(keys_json: &str) -> Result<toml::Table> {
    let json: serde_json::Value =
        serde_json::from_str(keys_json).map_err(|e| BindError::Keys(e.into()))?;
    match toml::Value::try_from(without_nulls(json)).map_err(|e| BindError::Keys(e.into()))? {
        toml::Value::Table(keys) => Ok(keys),
        other => Err(BindError::Keys(format!("{other} is no table").into())),
    }
}

/// `json` without the object entries whose value is `null`, at every depth.
fn without_nulls(json: serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match json {
        Value::Object(map) => Value::Object(
            map.into_iter()
                .filter(|(_, v)| !v.is_null())
                .map(|(k, v)| (k, without_nulls(v)))
                .collect(),
        ),
        Value::Array(items) => Value::Array(items.into_iter().map(without_nulls).collect()),
        other => other,
    }
}

/// Tracks loaded so far, by what identifies them (the raceline's optimisation takes a while).
static TRACKS: OnceLock<Mutex<HashMap<String, Arc<Track>>>> = OnceLock::new();

/// Loads `spec` (a name in `tracks_dir`, else `$CTXRACE_TRACKS_DIR`, else `../shared/tracks`,
/// then in the per-user folder; a map yaml; `generated:SEED`) with `race`'s raceline choice,
/// once per process.
fn load_track(spec: &str, tracks_dir: Option<PathBuf>, race: &RaceConfig) -> Result<Arc<Track>> {
    let opts = TrackOptions::for_race(tracks_dir, race.shipped_raceline);
    let key = format!(
        "{spec}\0{}\0{}",
        opts.tracks_dir.display(),
        race.shipped_raceline
    );
    let cache = TRACKS.get_or_init(Mutex::default);
    if let Some(track) = cache.lock().unwrap_or_else(|p| p.into_inner()).get(&key) {
        return Ok(track.clone());
    }
    let track = Arc::new(Track::load(spec, &opts).map_err(|source| BindError::Track {
        spec: spec.to_string(),
        source: Box::new(source),
    })?);
    let mut cache = cache.lock().unwrap_or_else(|p| p.into_inner());
    Ok(cache.entry(key).or_insert(track).clone())
}

/// `bytes` as native-endian values of `N` bytes each (`from` reads one), or an error naming
/// `what` when they hold no whole number of them.
fn values<T, const N: usize>(
    what: &'static str,
    bytes: &[u8],
    from: fn([u8; N]) -> T,
) -> Result<Vec<T>> {
    if !bytes.len().is_multiple_of(N) {
        return Err(BindError::Bytes {
            what,
            bytes: bytes.len(),
            size: N,
        });
    }
    let (whole, _) = bytes.as_chunks::<N>();
    Ok(whole.iter().map(|&b| from(b)).collect())
}

/// The race scenario as the package hands it to Python (JSON), or an error saying it could not
/// be written.
/// The checkpoint `name` names (`best`, `latest`, `step-N`, `best-at-N`; none: the
/// evaluation's, [`CheckpointChoice::default`]).
fn checkpoint_choice(name: Option<&str>) -> Result<CheckpointChoice> {
    Ok(name
        .map(str::parse)
        .transpose()
        .map_err(|e: UnknownCheckpointChoice| BindError::Argument(e.to_string()))?
        .unwrap_or_default())
}

fn race_json(cfg: &RaceConfig) -> Result<String> {
    serde_json::to_string(cfg)
        .map_err(|e| BindError::Argument(format!("the race scenario does not serialise: {e}")))
}

/// `bytes` as native-endian `f64` values, or an error naming `what`.
fn f64s(what: &'static str, bytes: &[u8]) -> Result<Vec<f64>> {
    values(what, bytes, f64::from_ne_bytes)
}

/// `bytes` as native-endian `f32` values, or an error naming `what`.
fn f32s(what: &'static str, bytes: &[u8]) -> Result<Vec<f32>> {
    values(what, bytes, f32::from_ne_bytes)
}

/// Pairs of values (actions, contexts) from native-endian `f64` bytes.
fn pairs(what: &'static str, bytes: &[u8]) -> Result<Vec<[f64; 2]>> {
    if !bytes.len().is_multiple_of(16) {
        return Err(BindError::Bytes {
            what,
            bytes: bytes.len(),
            size: 16,
        });
    }
    Ok(f64s(what, bytes)?
        .chunks_exact(2)
        .map(|p| [p[0], p[1]])
        .collect())
}

/// Native-endian bytes of `values`, as a Python `bytes`.
fn bytes_of<'py, T: Copy, const N: usize>(
    py: Python<'py>,
    values: &[T],
    to_bytes: fn(T) -> [u8; N],
) -> Bound<'py, pyo3::types::PyBytes> {
    pyo3::types::PyBytes::new_with(py, values.len() * N, |buf| {
        for (b, &v) in buf.chunks_exact_mut(N).zip(values) {
            b.copy_from_slice(&to_bytes(v));
        }
        Ok(())
    })
    .expect("filling bytes cannot fail")
}

/// The extension module.
#[pymodule]
fn _ctxrace(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<vector::PyRaceVector>()?;
    m.add_class::<agents::PyRaceAgents>()?;
    m.add_class::<evaluate::PyEvaluation>()?;
    m.add_class::<policy::PyPolicy>()?;
    m.add_function(wrap_pyfunction!(evaluate::evaluate_reference, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::list_tracks, m)?)?;
    m.add_function(wrap_pyfunction!(policy::save_mlp_policy, m)?)?;
    m.add_function(wrap_pyfunction!(export::export_onnx, m)?)?;
    m.add_function(wrap_pyfunction!(tracks::download_track, m)?)?;
    m.add("OUTCOME_COLUMNS", vector::OUTCOME_COLUMNS.to_vec())?;
    let references = ctxrace_sim::baseline::BaselineKind::ALL.map(|k| k.name());
    m.add("REFERENCE_POLICIES", references.to_vec())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    // the evaluation protocol's defaults, decided once (ctxrace_sim::eval_dir) for ctxrace eval
    // and Python (where it races: ctxrace_sim::scenario, behind Evaluation)
    use ctxrace_sim::eval_dir;
    m.add("EVAL_GRID", eval_dir::GRID)?;
    m.add("EVAL_RANGE", eval_dir::RANGE)?;
    m.add("EVAL_LAPS", eval_dir::LAPS)?;
    m.add("CONTEXT_LIMIT", ctxrace_config::context::CONTEXT_LIMIT)?;
    // an MLP policy file's choices, named once (ctxrace_nn::policy::mlp)
    use ctxrace_nn::policy::mlp::{ACTIVATIONS, INPUTS, OUTPUTS};
    m.add(
        "MLP_ACTIVATIONS",
        ACTIVATIONS.map(|(name, _)| name).to_vec(),
    )?;
    m.add("MLP_INPUTS", INPUTS.map(|(name, _)| name).to_vec())?;
    m.add("MLP_OUTPUTS", OUTPUTS.map(|(name, _)| name).to_vec())?;
    // a frame per decision of the default race: the envs' metadata before one is made
    m.add(
        "DEFAULT_RENDER_FPS",
        1.0 / RaceConfig::default().decision_period(),
    )?;
    m.add(
        "TRAIN_CONTEXT_RANGE",
        ctxrace_config::TrainConfig::default().context_range,
    )?;
    Ok(())
}
