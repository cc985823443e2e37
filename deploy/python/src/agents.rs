//! `RaceAgents` for Python: one multi-agent race ([`RaceEnv::set_agents`]) for the package's
//! PettingZoo `ParallelEnv`. The race keys' `rivals` count the scripted rivals; the agents'
//! cars (the ego and the `agents - 1` cars ahead of it on the grid) come on top. Each call
//! hands back every agent's observation and a row of the vector env's outcome table
//! ([`crate::vector::OUTCOME_COLUMNS`]) per agent, as bytes.

use crate::vector::row;
use crate::{bytes_of, load_track, pairs, race_config, with_agents, BindError};
use ctxrace_config::Context;
use ctxrace_render::race::{moment_rgb, race_title, Frame};
use ctxrace_sim::vector::{first_context, EnvOutcome, VectorError};
use ctxrace_sim::{AgentStep, RaceEnv};
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use std::path::PathBuf;

/// A race of several agents and its scripted rivals.
#[pyclass(name = "RaceAgents", module = "ctxrace._ctxrace")]
pub struct PyRaceAgents {
    env: RaceEnv,
    context_range: f64,
    /// The race scenario as JSON (`rivals`: every car but the ego).
    race: String,
    /// The track's name.
    track: String,
    /// The race so far, frame by frame (the ego's action and scan), when made to record.
    frames: Option<Vec<Frame>>,
}

impl PyRaceAgents {
    /// Records the race's state after a reset (no action) or a step (the ego's `action`), when
    /// made to record.
    fn record(&mut self, action: [f64; 2], ego: &AgentStep) {
        if let Some(frames) = &mut self.frames {
            if self.env.metrics().steps == 0 {
                frames.clear();
            }
            frames.push(Frame::capture(&self.env, action, ego.reward, &ego.obs));
        }
    }

    /// Every agent's observation (zeros for one whose episode ended) and outcome row as bytes.
    fn arrays<'py>(
        &self,
        py: Python<'py>,
        steps: &[AgentStep],
    ) -> (Bound<'py, PyBytes>, Bound<'py, PyBytes>) {
        let context = self.env.context();
        let obs: Vec<f32> = steps.iter().flat_map(|s| s.obs.iter().copied()).collect();
        let table: Vec<f64> = steps
            .iter()
            .flat_map(|s| {
                let flags = (s.terminated, s.truncated);
                row(&EnvOutcome::of_step(context, s.reward, flags, &s.info))
            })
            .collect();
        (
            bytes_of(py, &obs, f32::to_ne_bytes),
            bytes_of(py, &table, f64::to_ne_bytes),
        )
    }
}

#[pymethods]
impl PyRaceAgents {
    /// A race on `track` of the race config file `config` (none: the default scenario) with
    /// the race keys `race_keys` (a JSON object) laid over it, `agents` of its cars driven from
    /// Python and the keys' `rivals` scripted ones; contexts drawn from `±context_range`;
    /// recording the race for [`PyRaceAgents::render`] if `record`.
    #[new]
    #[pyo3(signature = (track, agents, race_keys="{}", config=None, tracks_dir=None, context_range=0.15, record=false))]
    fn new(
        track: &str,
        agents: usize,
        race_keys: &str,
        config: Option<PathBuf>,
        tracks_dir: Option<PathBuf>,
        context_range: f64,
        record: bool,
    ) -> PyResult<Self> {
        let cfg = with_agents(race_config(config, race_keys)?, agents)?;
        if !(0.0..=ctxrace_config::context::CONTEXT_LIMIT).contains(&context_range) {
            return Err(BindError::from(VectorError::ContextRange(context_range)).into());
        }
        let track = load_track(track, tracks_dir, &cfg)?;
        let mut env = RaceEnv::new(track.clone(), cfg.clone()).map_err(BindError::from)?;
        env.set_agents(agents).map_err(BindError::from)?;
        Ok(Self {
            env,
            context_range,
            race: crate::race_json(&cfg)?,
            track: track.name.clone(),
            frames: record.then(Vec::new),
        })
    }

    /// The race so far as a picture `width` pixels wide, as `ctxrace race --render race.gif`
    /// draws a moment (car 0 drawn as the ego, every other car as a rival): (RGB bytes row by
    /// row, height, width). Needs a race made to record, reset since.
    #[pyo3(signature = (width=ctxrace_render::race::MOMENT_WIDTH_PX))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        width: u32,
    ) -> PyResult<(Bound<'py, PyBytes>, u32, u32)> {
        let Some(frames) = &self.frames else {
            return Err(BindError::Argument(
                "this race records nothing to draw: make it with record=True".into(),
            )
            .into());
        };
        let title = race_title(&self.track, "agents", &self.env);
        let track = self.env.track();
        let picture = py
            .detach(|| moment_rgb(track, frames, &title, width))
            .map_err(|e| BindError::Render(e.into()))?;
        Ok((
            PyBytes::new(py, &picture.rgb),
            picture.height,
            picture.width,
        ))
    }

    /// Number of agents.
    #[getter]
    fn agents(&self) -> usize {
        self.env.agents()
    }

    /// Values of an observation (the LiDAR beams).
    #[getter]
    fn obs_dim(&self) -> usize {
        self.env.obs_dim()
    }

    /// The race scenario as JSON, every key resolved (`rivals` counts every car but the ego).
    #[getter]
    fn race_config(&self) -> &str {
        &self.race
    }

    /// The track's name.
    #[getter]
    fn track(&self) -> &str {
        &self.track
    }

    /// Values of one agent's state (its pose, speed and yaw rate, then every other car relative
    /// to it).
    #[getter]
    fn state_dim(&self) -> usize {
        self.env.state_dim()
    }

    /// The bounds `(low, high)` of each state value.
    #[getter]
    fn state_bounds(&self) -> (Vec<f32>, Vec<f32>) {
        self.env.state_bounds()
    }

    /// Race time between two decisions (s).
    #[getter]
    fn decision_period(&self) -> f64 {
        self.env.decision_period()
    }

    /// Whether the race has ended.
    #[getter]
    fn finished(&self) -> bool {
        self.env.is_finished()
    }

    /// The race's context `(c_v, c_θ)`.
    #[getter]
    fn context(&self) -> (f64, f64) {
        let c = self.env.context();
        (c.speed, c.steer)
    }

    /// Every agent's state as native-endian `f32` bytes (`agents × state_dim`).
    fn states<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        let dim = self.env.state_dim();
        let mut out = vec![0.0f32; dim * self.env.agents()];
        for (i, o) in out.chunks_exact_mut(dim).enumerate() {
            self.env.state_of(i, o);
        }
        bytes_of(py, &out, f32::to_ne_bytes)
    }

    /// Starts a race from `seed` in `context` (none: drawn from `±context_range` by a stream
    /// seeded with `seed`, as the vector env's first env draws it). Returns (observations,
    /// outcome table) as bytes.
    #[pyo3(signature = (seed, context=None))]
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seed: u64,
        context: Option<(f64, f64)>,
    ) -> PyResult<(Bound<'py, PyBytes>, Bound<'py, PyBytes>)> {
        let context = match context {
            Some((speed, steer)) => Context::new(speed, steer).map_err(BindError::from)?,
            None => first_context(seed, self.context_range),
        };
        let first = self.env.reset(seed, context);
        let steps: Vec<AgentStep> = (0..self.env.agents())
            .map(|i| AgentStep {
                obs: if i == 0 {
                    first.clone()
                } else {
                    self.env.observe_agent(i)
                },
                reward: 0.0,
                terminated: false,
                truncated: false,
                info: Default::default(),
            })
            .collect();
        self.record([0.0; 2], &steps[0]);
        Ok(self.arrays(py, &steps))
    }

    /// Steps the race with every agent's action (native-endian `f64` pairs, one per agent; an
    /// ended agent's is ignored), with the GIL released. Returns (observations, outcome table).
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: &[u8],
    ) -> PyResult<(Bound<'py, PyBytes>, Bound<'py, PyBytes>)> {
        let actions = pairs("actions", actions)?;
        let env = &mut self.env;
        let steps = py
            .detach(|| env.step_agents(&actions))
            .map_err(BindError::from)?;
        self.record(actions[0], &steps[0]);
        Ok(self.arrays(py, &steps))
    }
}
