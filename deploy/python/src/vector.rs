//! `RaceVector` for Python: the simulator's [`RaceVector`] with the buffers it writes into,
//! stepped with the GIL released; each call hands back the observations and a table of
//! outcomes as bytes. Made to record, it keeps every env's episode so far and draws it as
//! `ctxrace race --render race.gif` draws a moment ([`moment_rgb`]).

use crate::{bytes_of, load_track, pairs, race_config, with_agents, BindError, Result};
use ctxrace_config::Context;
use ctxrace_render::race::{moment_rgb, race_title, render_race, Frame};
use ctxrace_sim::vector::{Autoreset, EnvOutcome, RaceVector};
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use std::path::PathBuf;

/// The columns of the outcome table, one `f64` each per env (flags as 0 or 1).
pub const OUTCOME_COLUMNS: [&str; 9] = [
    "reward",
    "terminated",
    "truncated",
    "context_speed",
    "context_steer",
    "progress",
    "overtakes",
    "a2a",
    "wall_crash",
];

/// One env's outcome as a row of the table ([`OUTCOME_COLUMNS`]).
pub fn row(o: &EnvOutcome) -> [f64; 9] {
    [
        o.reward,
        f64::from(u8::from(o.terminated)),
        f64::from(u8::from(o.truncated)),
        o.context.speed,
        o.context.steer,
        o.progress,
        f64::from(o.overtakes),
        f64::from(u8::from(o.a2a)),
        f64::from(u8::from(o.wall_crash)),
    ]
}

/// `num_envs` races of one track and scenario, stepped on worker threads (the package's
/// `gymnasium.make`, `ctxrace.make_vec` and `ctxrace.make_agents_vec` wrap it); with several
/// agents a race, its rows (observations, actions, outcomes, states) are the races' agents,
/// race-major.
#[pyclass(name = "RaceVector", module = "ctxrace._ctxrace")]
pub struct PyRaceVector {
    inner: RaceVector,
    obs: Vec<f32>,
    outcomes: Vec<EnvOutcome>,
    /// The race scenario as JSON.
    race: String,
    /// The track's name.
    track: String,
    /// Each race's episode so far, frame by frame, when made to record (else empty).
    frames: Vec<Vec<Frame>>,
}

impl PyRaceVector {
    /// Records each race's state after a reset or a step (`actions` taken, none after a
    /// reset; the ego's drawn), when made to record; a race whose episode (re)started begins a
    /// new record.
    fn record(&mut self, actions: Option<&[[f64; 2]]>) {
        if self.frames.is_empty() {
            return;
        }
        let (dim, k) = (self.inner.obs_dim(), self.inner.agents());
        for (i, (env, frames)) in self.inner.envs().zip(&mut self.frames).enumerate() {
            let started = env.metrics().steps == 0;
            if started {
                frames.clear();
            }
            let ego = i * k;
            let action = match actions {
                Some(a) if !started => a[ego],
                _ => [0.0; 2],
            };
            let obs = &self.obs[ego * dim..(ego + 1) * dim];
            frames.push(Frame::capture(env, action, self.outcomes[ego].reward, obs));
        }
    }

    /// The race of row `env` and the frames it recorded; an error naming the fix where the
    /// vector does not record or has no such row.
    fn recorded(&self, env: usize) -> Result<(&ctxrace_sim::RaceEnv, &[Frame])> {
        let race = env / self.inner.agents();
        match (self.frames.get(race), self.inner.envs().nth(race)) {
            (Some(frames), Some(race)) if env < self.inner.lanes() => Ok((race, frames)),
            _ if self.frames.is_empty() => Err(BindError::Argument(
                "this vector records nothing to draw: make it with record=True".into(),
            )),
            _ => Err(BindError::Argument(format!(
                "env {env} is no env of {}",
                self.inner.lanes()
            ))),
        }
    }

    /// The observations and the outcome table as bytes.
    fn arrays<'py>(&self, py: Python<'py>) -> (Bound<'py, PyBytes>, Bound<'py, PyBytes>) {
        let table: Vec<f64> = self.outcomes.iter().flat_map(row).collect();
        (
            bytes_of(py, &self.obs, f32::to_ne_bytes),
            bytes_of(py, &table, f64::to_ne_bytes),
        )
    }
}

#[pymethods]
impl PyRaceVector {
    /// `num_envs` races on `track` of the race config file `config` (none: the default
    /// scenario) with the race keys `race_keys` (a JSON object) laid over it; contexts drawn from `±context_range`; `threads` worker threads (0:
    /// one per core); an ended episode's env resets in the step that ended it when
    /// `same_step`, else on the next step; recording each env's episode for
    /// [`PyRaceVector::render`] if `record`; each race driving `agents` cars from Python (the
    /// ego and the `agents - 1` cars ahead of it, on top of the keys' scripted `rivals`).
    #[new]
    #[pyo3(signature = (track, num_envs, race_keys="{}", config=None, tracks_dir=None, context_range=0.15, threads=0, same_step=false, record=false, agents=1))]
    #[allow(clippy::too_many_arguments)] // Python's keyword arguments
    fn new(
        track: &str,
        num_envs: usize,
        race_keys: &str,
        config: Option<PathBuf>,
        tracks_dir: Option<PathBuf>,
        context_range: f64,
        threads: usize,
        same_step: bool,
        record: bool,
        agents: usize,
    ) -> PyResult<Self> {
        let cfg = with_agents(race_config(config, race_keys)?, agents)?;
        let track = load_track(track, tracks_dir, &cfg)?;
        let autoreset = match same_step {
            true => Autoreset::SameStep,
            false => Autoreset::NextStep,
        };
        let inner = RaceVector::new(track.clone(), &cfg, num_envs, context_range, threads)
            .map_err(BindError::from)?
            .with_autoreset(autoreset)
            .with_agents(agents)
            .map_err(BindError::from)?;
        Ok(Self {
            obs: vec![0.0; inner.lanes() * inner.obs_dim()],
            outcomes: vec![EnvOutcome::default(); inner.lanes()],
            race: crate::race_json(&cfg)?,
            track: track.name.clone(),
            frames: if record {
                vec![Vec::new(); num_envs]
            } else {
                Vec::new()
            },
            inner,
        })
    }

    /// Rows of observations, actions and outcomes: races × agents.
    #[getter]
    fn num_envs(&self) -> usize {
        self.inner.lanes()
    }

    /// Number of races.
    #[getter]
    fn races(&self) -> usize {
        self.inner.len()
    }

    /// Cars each race drives from Python.
    #[getter]
    fn agents(&self) -> usize {
        self.inner.agents()
    }

    /// Values in one env's observation (LiDAR beams).
    #[getter]
    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }

    /// Worker threads stepping the envs.
    #[getter]
    fn threads(&self) -> usize {
        self.inner.threads()
    }

    /// The race scenario, every key resolved, as JSON.
    #[getter]
    fn race_config(&self) -> &str {
        &self.race
    }

    /// The track's name.
    #[getter]
    fn track(&self) -> &str {
        &self.track
    }

    /// Under same-step autoreset, the last observations of the episodes that ended at the last
    /// step (native-endian `f32`, one row per env; other rows are stale), as bytes.
    fn final_obs<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        bytes_of(py, self.inner.final_obs(), f32::to_ne_bytes)
    }

    /// Values in one env's state (`RaceEnv::state_into`: the ego's pose, speed and yaw rate, each
    /// rival's pose relative to the ego and its speed).
    #[getter]
    fn state_dim(&self) -> usize {
        self.inner.state_dim()
    }

    /// Bounds `(low, high)` of each value of one env's state.
    #[getter]
    fn state_bounds(&self) -> (Vec<f32>, Vec<f32>) {
        self.inner.state_bounds()
    }

    /// Every env's current state (native-endian `f32`, one row per env), or with `ended`, under
    /// same-step autoreset, the state the episodes that ended at the last step ended in (other
    /// rows stale), as bytes.
    #[pyo3(signature = (ended=false))]
    fn states<'py>(&self, py: Python<'py>, ended: bool) -> PyResult<Bound<'py, PyBytes>> {
        let mut out = vec![0.0f32; self.inner.lanes() * self.inner.state_dim()];
        self.inner
            .states_into(ended, &mut out)
            .map_err(BindError::from)?;
        Ok(bytes_of(py, &out, f32::to_ne_bytes))
    }

    /// Each race's current episode's context (native-endian `f64` pairs), as bytes.
    fn contexts<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        let pairs: Vec<f64> = self
            .inner
            .contexts()
            .flat_map(|c| [c.speed, c.steer])
            .collect();
        bytes_of(py, &pairs, f64::to_ne_bytes)
    }

    /// Race time between two decisions (s).
    #[getter]
    fn decision_period(&self) -> f64 {
        self.inner
            .envs()
            .next()
            .map_or(0.0, |env| env.decision_period())
    }

    /// Env `env`'s episode so far as a picture `width` pixels wide (a moment of `ctxrace race
    /// --render race.gif`, as wide by default): (RGB bytes row by row, height, width). Needs a
    /// vector made to record, reset since.
    #[pyo3(signature = (env, width=ctxrace_render::race::MOMENT_WIDTH_PX))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        env: usize,
        width: u32,
    ) -> PyResult<(Bound<'py, PyBytes>, u32, u32)> {
        let (race, frames) = self.recorded(env)?;
        let title = race_title(&self.track, "agent", race);
        let picture = py
            .detach(|| moment_rgb(race.track(), frames, &title, width))
            .map_err(|e| BindError::Render(e.into()))?;
        Ok((
            PyBytes::new(py, &picture.rgb),
            picture.height,
            picture.width,
        ))
    }

    /// Race `env`'s episode so far: its metrics as `ctxrace race --json` reports them (progress,
    /// overtakes, collisions, lap time, return, ...: the ego's) and what ended it, as JSON.
    fn metrics(&self, env: usize) -> PyResult<String> {
        let race = self.inner.envs().nth(env).ok_or_else(|| {
            BindError::Argument(format!("race {env} is no race of {}", self.inner.len()))
        })?;
        let mut json = serde_json::to_value(race.metrics()).map_err(|e| {
            BindError::Argument(format!("the episode's metrics do not serialise: {e}"))
        })?;
        json["ended_by"] = race.metrics().ended_by().into();
        Ok(json.to_string())
    }

    /// Draws env `env`'s recorded episode as `ctxrace race --render` does (a `.gif` animation,
    /// else a picture of its last moment by the extension: `.png` or `.svg`) into `path`, titled
    /// with the ego's name `ego`. Needs a vector made to record.
    fn save_render(&self, py: Python<'_>, env: usize, path: PathBuf, ego: &str) -> PyResult<()> {
        let (race, frames) = self.recorded(env)?;
        let title = race_title(&self.track, ego, race);
        py.detach(|| render_race(&path, race.track(), frames, &title))
            .map_err(|e| BindError::Render(e.into()))?;
        Ok(())
    }

    /// Starts every race's next episode from `seed` (race `i`: reset seed `seed + i`);
    /// `contexts` (native-endian `f64` pairs, one per race) pins each race's context, none
    /// draws them. Returns (observations, outcome table) as bytes.
    #[pyo3(signature = (seed, contexts=None))]
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seed: u64,
        contexts: Option<&[u8]>,
    ) -> PyResult<(Bound<'py, PyBytes>, Bound<'py, PyBytes>)> {
        let contexts = contexts
            .map(|bytes| {
                pairs("contexts", bytes)?
                    .into_iter()
                    .map(|[speed, steer]| Ok(Context::new(speed, steer)?))
                    .collect::<Result<Vec<_>>>()
            })
            .transpose()?;
        let (inner, obs, out) = (&mut self.inner, &mut self.obs, &mut self.outcomes);
        py.detach(|| inner.reset(seed, contexts.as_deref(), obs, out))
            .map_err(BindError::from)?;
        self.record(None);
        Ok(self.arrays(py))
    }

    /// Steps every row with its action (native-endian `f64` pairs, one per row), with the GIL
    /// released; a race whose episode ended resets instead. Returns (observations, outcome
    /// table) as bytes.
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: &[u8],
    ) -> PyResult<(Bound<'py, PyBytes>, Bound<'py, PyBytes>)> {
        let actions = pairs("actions", actions)?;
        let (inner, obs, out) = (&mut self.inner, &mut self.obs, &mut self.outcomes);
        py.detach(|| inner.step(&actions, obs, out))
            .map_err(BindError::from)?;
        self.record(Some(&actions));
        Ok(self.arrays(py))
    }
}
