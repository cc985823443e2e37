//! The paper's evaluation protocol for Python: every context of the grid raced `laps` times
//! from the seeds `ctxrace eval` uses ([`episode_seed`]), each episode recorded as `ctxrace
//! eval` records it. A reference policy drives in Rust ([`evaluate_reference`]); a Python
//! policy drives a batch of episodes at a time through [`PyEvaluation`].

use crate::policy::PyPolicy;
use crate::{bytes_of, keys_table, load_track, pairs, BindError, Result};
use ctxrace_config::config_file::read_config_table;
use ctxrace_config::{Context, RaceConfig};
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::BaselineEgo;
use ctxrace_sim::eval_dir::{GRID, LAPS, RANGE};
use ctxrace_sim::evaluation::{episode_seed, run_episode, summarise, EvalEpisode, SplitMeans};
use ctxrace_sim::scenario::{EvalScenario, ScenarioChoice};
use ctxrace_sim::vector::VectorError;
use ctxrace_sim::RaceEnv;
use ctxrace_tracks::Track;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use rayon::prelude::*;
use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::Arc;

/// Episodes each worker thread races between two checks of Python's signals (Ctrl-C): a few
/// tenths of a second of racing.
const SIGNAL_CHECK_EPISODES_PER_THREAD: usize = 4;

/// The grid and the episodes of one evaluation.
struct Protocol {
    track: Arc<Track>,
    race: RaceConfig,
    /// Half-width of the training contexts, which splits the grid in and out of distribution.
    train_range: f64,
    grid: Vec<Context>,
    seed: u64,
    /// `(context index, lap)` of every episode, in order.
    todo: Vec<(usize, usize)>,
    pool: rayon::ThreadPool,
}

impl Protocol {
    /// Resolves where the policy races (`ScenarioChoice`'s rules, over `run`'s scenario when
    /// it is a trained agent's), reads the track and lays out the `grid × grid` contexts over
    /// `±range`, `laps` each.
    fn new(
        scenario: ScenarioArgs,
        grid: usize,
        range: f64,
        laps: usize,
        seed: u64,
        threads: usize,
    ) -> Result<Self> {
        if grid == 0 || laps == 0 {
            return Err(BindError::Argument(format!(
                "grid {grid} and laps {laps} must be positive (the paper's: 7 and 50)"
            )));
        }
        let EvalScenario {
            track,
            race,
            train_range,
        } = scenario.resolve()?;
        let track = load_track(&track, scenario.tracks_dir, &race)?;
        // the environment checks the race against the track once, here
        RaceEnv::new(track.clone(), race.clone()).map_err(VectorError::from)?;
        Context::new(range, range)?;
        let grid = Context::grid(grid, range);
        let todo = (0..grid.len())
            .flat_map(|i| (0..laps).map(move |lap| (i, lap)))
            .collect();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(VectorError::from)?;
        Ok(Self {
            track,
            race,
            train_range,
            grid,
            seed,
            todo,
            pool,
        })
    }

    /// A fresh environment of the race.
    fn env(&self) -> RaceEnv {
        RaceEnv::new(self.track.clone(), self.race.clone()).expect("checked in Protocol::new")
    }

    /// The episodes in `(context, lap)` order, their per-context summary and its split means
    /// (`null` for a split without contexts) as JSON.
    fn result(&self, mut episodes: Vec<(usize, EvalEpisode)>) -> String {
        episodes.sort_by_key(|(i, e)| (*i, e.lap));
        let episodes: Vec<EvalEpisode> = episodes.into_iter().map(|(_, e)| e).collect();
        let contexts = summarise(&episodes, self.train_range);
        let means = serde_json::json!({
            "in": SplitMeans::split(&contexts, true),
            "out": SplitMeans::split(&contexts, false),
        });
        serde_json::json!({ "episodes": episodes, "contexts": contexts, "means": means })
            .to_string()
    }
}

/// Where an evaluation races, as Python gave it: each `None` (and each key not given) is
/// decided by [`EvalScenario::resolve`] over the trained agent `run`'s scenario.
struct ScenarioArgs {
    track: Option<String>,
    rivals: Option<usize>,
    train_range: Option<f64>,
    /// Race keys, a JSON object.
    race_keys: String,
    /// A race config file in place of the run's race.
    config: Option<PathBuf>,
    tracks_dir: Option<PathBuf>,
    /// The trained agent's run (its recorded experiment), when it is known.
    run: Option<ctxrace_config::ExperimentConfig>,
}

impl ScenarioArgs {
    /// The scenario the arguments choose.
    fn resolve(&self) -> Result<EvalScenario> {
        let choice = ScenarioChoice {
            track: self.track.clone(),
            rivals: self.rivals,
            train_range: self.train_range,
            race: self.config.as_deref().map(read_config_table).transpose()?,
            race_keys: keys_table(&self.race_keys)?,
        };
        Ok(EvalScenario::resolve(self.run.as_ref(), choice)?)
    }
}

/// Evaluates the reference policy `policy` (`pure-pursuit`, `follow-the-gap`, `random`,
/// `still`) as `ctxrace eval POLICY` does, on worker threads with the GIL released; returns
/// `{"episodes": [...], "contexts": [...], "means": {"in": ..., "out": ...}}` as JSON.
#[pyfunction]
#[pyo3(signature = (policy, track=None, rivals=None, train_range=None, race_keys="{}", config=None, tracks_dir=None, grid=GRID, range=RANGE, laps=LAPS, seed=0, threads=0))]
#[allow(clippy::too_many_arguments)]
pub fn evaluate_reference(
    py: Python<'_>,
    policy: &str,
    track: Option<String>,
    rivals: Option<usize>,
    train_range: Option<f64>,
    race_keys: &str,
    config: Option<PathBuf>,
    tracks_dir: Option<PathBuf>,
    grid: usize,
    range: f64,
    laps: usize,
    seed: u64,
    threads: usize,
) -> PyResult<String> {
    let kind: BaselineKind = policy.parse().map_err(BindError::Argument)?;
    let scenario = ScenarioArgs {
        track,
        rivals,
        train_range,
        race_keys: race_keys.into(),
        config,
        tracks_dir,
        run: None,
    };
    let p = Protocol::new(scenario, grid, range, laps, seed, threads)?;
    // a chunk of episodes at a time with the GIL released, Python's signals checked between
    // chunks, so that Ctrl-C stops an evaluation within a chunk (each episode's own seed makes
    // the chunking change nothing)
    let chunk = SIGNAL_CHECK_EPISODES_PER_THREAD * p.pool.current_num_threads();
    let mut episodes = Vec::with_capacity(p.todo.len());
    for part in p.todo.chunks(chunk) {
        episodes.extend(py.detach(|| {
            p.pool.install(|| {
                part.par_iter()
                    .map_init(
                        || {
                            let env = p.env();
                            let ego = BaselineEgo::new(kind, &env);
                            (env, ego)
                        },
                        |(env, ego), &(index, lap)| {
                            let seed = episode_seed(p.seed, index, lap);
                            let e = run_episode(env, ego, p.grid[index], seed, lap, |_, _| {})
                                .expect("a reference policy's actions are finite");
                            (index, e)
                        },
                    )
                    .collect::<Vec<_>>()
            })
        }));
        py.check_signals()?;
    }
    Ok(p.result(episodes))
}

/// An episode of the grid being raced.
struct Racing {
    index: usize,
    lap: usize,
    seed: u64,
}

/// One environment of a [`PyEvaluation`] with the episode it races.
struct Lane {
    env: RaceEnv,
    racing: Option<Racing>,
    obs: Vec<f32>,
    /// Its episode started since [`PyEvaluation::started`] last looked.
    fresh: bool,
}

/// The protocol driven by a Python policy: up to `batch` episodes race at once; the policy
/// acts on the observations and contexts of those still running.
#[pyclass(name = "Evaluation", module = "ctxrace._ctxrace")]
pub struct PyEvaluation {
    protocol: Protocol,
    lanes: Vec<Lane>,
    /// Episodes not started yet.
    queue: VecDeque<(usize, usize)>,
    done: Vec<(usize, EvalEpisode)>,
}

impl PyEvaluation {
    /// Starts the next queued episodes in idle lanes.
    fn refill(&mut self) {
        let p = &self.protocol;
        for lane in self.lanes.iter_mut().filter(|l| l.racing.is_none()) {
            let Some((index, lap)) = self.queue.pop_front() else {
                return;
            };
            let seed = episode_seed(p.seed, index, lap);
            lane.obs = lane.env.reset(seed, p.grid[index]);
            lane.racing = Some(Racing { index, lap, seed });
            lane.fresh = true;
        }
    }

    /// The lanes racing an episode.
    fn racing(&self) -> impl Iterator<Item = &Lane> {
        self.lanes.iter().filter(|l| l.racing.is_some())
    }
}

#[pymethods]
impl PyEvaluation {
    /// The protocol over the `grid × grid` contexts of `±range`, `laps` each from `seed`,
    /// `batch` episodes at a time, stepped on `threads` worker threads (0: one per core), where
    /// the arguments and the trained agent `run` (if any) say ([`EvalScenario::resolve`]).
    #[new]
    #[pyo3(signature = (track=None, rivals=None, train_range=None, race_keys="{}", config=None, tracks_dir=None, run=None, grid=GRID, range=RANGE, laps=LAPS, seed=0, batch=64, threads=0))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        track: Option<String>,
        rivals: Option<usize>,
        train_range: Option<f64>,
        race_keys: &str,
        config: Option<PathBuf>,
        tracks_dir: Option<PathBuf>,
        run: Option<PyRef<'_, PyPolicy>>,
        grid: usize,
        range: f64,
        laps: usize,
        seed: u64,
        batch: usize,
        threads: usize,
    ) -> PyResult<Self> {
        let scenario = ScenarioArgs {
            track,
            rivals,
            train_range,
            race_keys: race_keys.into(),
            config,
            tracks_dir,
            run: run.and_then(|r| r.experiment().cloned()),
        };
        let protocol = Protocol::new(scenario, grid, range, laps, seed, threads)?;
        let lanes = (0..batch.clamp(1, protocol.todo.len().max(1)))
            .map(|_| Lane {
                env: protocol.env(),
                racing: None,
                obs: Vec::new(),
                fresh: false,
            })
            .collect();
        let mut e = Self {
            queue: protocol.todo.iter().copied().collect(),
            protocol,
            lanes,
            done: Vec::new(),
        };
        e.refill();
        Ok(e)
    }

    /// Episodes racing now.
    #[getter]
    fn racing_now(&self) -> usize {
        self.racing().count()
    }

    /// Values in one observation.
    #[getter]
    fn obs_dim(&self) -> usize {
        self.lanes[0].env.obs_dim()
    }

    /// The lanes (batch rows) of the episodes racing now, in the order of
    /// [`PyEvaluation::observe`].
    fn lanes(&self) -> Vec<usize> {
        (0..self.lanes.len())
            .filter(|&i| self.lanes[i].racing.is_some())
            .collect()
    }

    /// `(lane, reset seed)` of the episodes started since the last call: a stateful policy
    /// starts them afresh (a trained agent reseeds its noise with the seed, as `ctxrace eval`).
    fn started(&mut self) -> Vec<(usize, u64)> {
        let mut started = Vec::new();
        for (i, lane) in self.lanes.iter_mut().enumerate() {
            if let (true, Some(r)) = (std::mem::take(&mut lane.fresh), &lane.racing) {
                started.push((i, r.seed));
            }
        }
        started
    }

    /// The observations (`f32`) and contexts (`f64` pairs) of the episodes racing now, as bytes.
    fn observe<'py>(&self, py: Python<'py>) -> (Bound<'py, PyBytes>, Bound<'py, PyBytes>) {
        let obs: Vec<f32> = self.racing().flat_map(|l| l.obs.iter().copied()).collect();
        let contexts: Vec<f64> = self
            .racing()
            .flat_map(|l| l.env.context().to_array())
            .collect();
        (
            bytes_of(py, &obs, f32::to_ne_bytes),
            bytes_of(py, &contexts, f64::to_ne_bytes),
        )
    }

    /// Steps the episodes racing now with `actions` (`f64` pairs, one per episode, in the order
    /// of [`PyEvaluation::observe`]) with the GIL released; records the episodes that ended and
    /// starts queued ones in their place.
    fn act(&mut self, py: Python<'_>, actions: &[u8]) -> PyResult<()> {
        let actions = pairs("actions", actions)?;
        let racing = self.racing_now();
        if actions.len() != racing {
            return Err(BindError::from(VectorError::Shape {
                what: "actions",
                got: actions.len(),
                want: racing,
                envs: racing,
            })
            .into());
        }
        if let Some(env) = actions
            .iter()
            .position(|a| !a.iter().all(|v| v.is_finite()))
        {
            let action = actions[env];
            return Err(BindError::from(VectorError::BadAction { env, action }).into());
        }
        let mut given = actions.into_iter();
        let lanes: Vec<(&mut Lane, [f64; 2])> = self
            .lanes
            .iter_mut()
            .filter(|l| l.racing.is_some())
            .map(|l| (l, given.next().expect("one action per racing lane")))
            .collect();
        let grid = &self.protocol.grid;
        let pool = &self.protocol.pool;
        let ended: Vec<(usize, EvalEpisode)> = py.detach(|| {
            pool.install(|| {
                lanes
                    .into_par_iter()
                    .filter_map(|(lane, action)| {
                        let step = lane.env.step(action).expect("a finite action of a race");
                        lane.obs = step.obs;
                        if !(step.terminated || step.truncated) {
                            return None;
                        }
                        let r = lane.racing.take().expect("racing");
                        let metrics = lane.env.metrics();
                        let e = EvalEpisode::new(
                            grid[r.index],
                            r.lap,
                            r.seed,
                            metrics,
                            step.info.lap_complete,
                        );
                        Some((r.index, e))
                    })
                    .collect()
            })
        });
        self.done.extend(ended);
        self.refill();
        Ok(())
    }

    /// `{"episodes": [...], "contexts": [...], "means": {"in": ..., "out": ...}}` as JSON,
    /// contexts in or out of distribution by the scenario's training range; an error while
    /// episodes remain.
    fn result(&self) -> PyResult<String> {
        if self.racing_now() > 0 {
            return Err(pyo3::exceptions::PyRuntimeError::new_err(
                "episodes are still racing: call act until racing_now is 0",
            ));
        }
        Ok(self.protocol.result(self.done.clone()))
    }
}
