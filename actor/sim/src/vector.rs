//! Many races stepped together ([`RaceVector`]): `n` environments of one track and scenario,
//! stepped on worker threads, their observations and outcomes written into buffers the caller
//! owns. An env whose episode ended resets itself on the next step, ignoring that step's action
//! (Gymnasium's next-step autoreset), or, with [`Autoreset::SameStep`], in the step that ended it.
//!
//! **Agents.** [`RaceVector::with_agents`] makes each race drive several cars from outside
//! ([`RaceEnv::set_agents`]): the vector's lanes are then the races' agents, race-major (lane
//! `r × agents + i` is agent `i` of race `r`), each with its own observation, action and outcome.
//! An agent whose episode ended before the race did reports zeros, reward 0 and no flag until
//! the race ends (black death); at the race's end every lane reports it ended (terminated, or
//! truncated at the time limit), so that a lane's next observation always starts an episode.
//!
//! **Seeds and contexts.** [`RaceVector::reset`] with `seed` starts env `i`'s episode from the
//! reset seed `seed + i` (what `ctxrace race --seed` passes to [`RaceEnv::reset`]); a stream of
//! that env seeded by the same number draws its later episodes' reset seeds and every
//! episode's context, uniform in `±context_range` as the training actors draw them, unless a
//! context is pinned for the env.

use crate::race::{RaceEnv, RaceError, StepInfo};
use ctxrace_config::context::CONTEXT_LIMIT;
use ctxrace_config::{Context, RaceConfig};
use ctxrace_tracks::Track;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use std::sync::Arc;

/// Why a vector of races refused a call; nothing was stepped.
#[derive(Debug, thiserror::Error)]
pub enum VectorError {
    /// A race could not be built or stepped.
    #[error(transparent)]
    Race(#[from] RaceError),
    /// No env was asked for.
    #[error("a race vector needs at least one env")]
    Empty,
    /// The training context range is no number in `[0, CONTEXT_LIMIT]`.
    #[error("context_range {0} must lie in [0, {CONTEXT_LIMIT}] (the paper trains on 0.15)")]
    ContextRange(f64),
    /// A buffer or argument does not hold one entry per env.
    #[error("{what} holds {got} values where {envs} envs need {want}")]
    Shape {
        /// Which argument.
        what: &'static str,
        /// Its length.
        got: usize,
        /// The length needed.
        want: usize,
        /// Envs in the vector.
        envs: usize,
    },
    /// An action is NaN or infinite.
    #[error(
        "env {env}'s action {action:?} is not finite; policies must output numbers in [-1, 1]"
    )]
    BadAction {
        /// The env.
        env: usize,
        /// Its action.
        action: [f64; 2],
    },
    /// `step` was called before the first `reset`.
    #[error("step called before reset; call reset first")]
    NotReset,
    /// The worker threads could not be started.
    #[error("starting the worker threads")]
    Threads(#[from] rayon::ThreadPoolBuildError),
}

/// When an env whose episode ended starts its next one: Gymnasium's autoreset modes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Autoreset {
    /// On the next step, which returns the new episode's first observation with reward 0 and
    /// ignores its action (Gymnasium's `NEXT_STEP`).
    #[default]
    NextStep,
    /// In the step that ended it: the step returns the new episode's first observation, and
    /// the ended episode's last one is kept apart ([`RaceVector::final_obs`]; Gymnasium's
    /// `SAME_STEP`, which Stable-Baselines3's vector envs follow).
    SameStep,
}

/// What one env reports after a reset or a step: Gymnasium's reward and flags, and its info.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EnvOutcome {
    /// The reward (0 after a reset).
    pub reward: f64,
    /// The episode ended (lap, crash or collision).
    pub terminated: bool,
    /// The episode hit the time limit.
    pub truncated: bool,
    /// The context of the env's episode: after a reset the new one's, after a step the stepped
    /// one's (under [`Autoreset::SameStep`] the ended episode's; [`RaceVector::contexts`] tells
    /// the one that started).
    pub context: Context,
    /// PG of the episode so far.
    pub progress: f64,
    /// The ego's rank change this step (+ passes, − being passed).
    pub overtakes: i32,
    /// The ego collided with a rival this step.
    pub a2a: bool,
    /// The ego hit a wall this step.
    pub wall_crash: bool,
}

impl EnvOutcome {
    /// The outcome of a step of the episode in `context` that earned `reward`, ended as
    /// `(terminated, truncated)`, with its details `info`.
    pub fn of_step(
        context: Context,
        reward: f64,
        (terminated, truncated): (bool, bool),
        info: &StepInfo,
    ) -> Self {
        Self {
            reward,
            terminated,
            truncated,
            context,
            progress: info.progress,
            overtakes: info.overtakes,
            a2a: info.a2a,
            wall_crash: info.wall_crash,
        }
    }
}

/// The context an env draws first after a reset from `seed` (uniform in `±range`): a race of
/// one env started from `seed` races as the vector's first env started from it.
pub fn first_context(seed: u64, range: f64) -> Context {
    draw_context(&mut ChaCha8Rng::seed_from_u64(seed), range)
}

/// A context uniform in `±range` (speed, then steering) from `stream`, as the training actors
/// draw them.
fn draw_context(stream: &mut ChaCha8Rng, range: f64) -> Context {
    Context {
        speed: stream.random_range(-range..=range),
        steer: stream.random_range(-range..=range),
    }
}

/// One env of the vector with its stream of episodes.
struct Slot {
    env: RaceEnv,
    /// Draws the env's contexts and later reset seeds.
    stream: ChaCha8Rng,
    /// The context every episode takes instead of a drawn one.
    pinned: Option<Context>,
    /// Its episode ended: the next step resets it.
    ended: bool,
    /// Each agent's episode ended before the race did (with several agents).
    agent_ended: Vec<bool>,
    /// Under [`Autoreset::SameStep`], the state ([`RaceEnv::state_into`]) its last ended episode
    /// ended in.
    final_state: Vec<f32>,
}

impl Slot {
    /// Starts an episode from `seed` (drawn from the stream when `None`), writing every
    /// agent's first observation into its row of `obs`; returns its context.
    fn start(&mut self, seed: Option<u64>, range: f64, obs: &mut [f32]) -> Context {
        let context = self
            .pinned
            .unwrap_or_else(|| draw_context(&mut self.stream, range));
        let seed = seed.unwrap_or_else(|| self.stream.random());
        let dim = self.env.obs_dim();
        obs[..dim].copy_from_slice(&self.env.reset(seed, context));
        for (i, row) in obs.chunks_exact_mut(dim).enumerate().skip(1) {
            row.copy_from_slice(&self.env.observe_agent(i));
        }
        self.ended = false;
        self.agent_ended.fill(false);
        context
    }

    /// [`Slot::start`] with each agent's outcome (reward 0, the new context) in `out`.
    fn restart(&mut self, seed: Option<u64>, range: f64, obs: &mut [f32], out: &mut [EnvOutcome]) {
        let context = self.start(seed, range, obs);
        out.fill(EnvOutcome {
            context,
            ..EnvOutcome::default()
        });
    }

    /// Steps the race with each agent's action (one per row of `obs` and entry of `out`), or
    /// resets it if its episode ended. Under [`Autoreset::SameStep`] a step that ends the
    /// race writes its observations into `final_obs` and starts the next episode at once, its
    /// first observations into `obs`.
    fn advance(
        &mut self,
        actions: &[[f64; 2]],
        (range, autoreset): (f64, Autoreset),
        (obs, final_obs): (&mut [f32], &mut [f32]),
        out: &mut [EnvOutcome],
    ) -> Result<(), RaceError> {
        if self.ended {
            self.restart(None, range, obs, out);
            return Ok(());
        }
        let context = self.env.context();
        if let [action] = actions {
            let step = self.env.step(*action)?;
            let flags = (step.terminated, step.truncated);
            self.ended = step.terminated || step.truncated;
            obs.copy_from_slice(&step.obs);
            out[0] = EnvOutcome::of_step(context, step.reward, flags, &step.info);
        } else {
            let steps = self.env.step_agents(actions)?;
            self.ended = self.env.is_finished();
            self.agent_ended.resize(actions.len(), false);
            let lanes = steps.iter().zip(obs.chunks_exact_mut(self.env.obs_dim()));
            for (((step, row), o), was_done) in lanes.zip(out.iter_mut()).zip(&mut self.agent_ended)
            {
                row.copy_from_slice(&step.obs);
                // black death until the race ends, when every lane ends again
                let flags = match (*was_done, self.ended) {
                    (true, false) => (false, false),
                    (true, true) => (true, false),
                    (false, _) => (step.terminated, step.truncated),
                };
                *was_done |= step.terminated;
                *o = EnvOutcome::of_step(context, step.reward, flags, &step.info);
            }
        }
        if self.ended && autoreset == Autoreset::SameStep {
            final_obs.copy_from_slice(obs);
            let dim = self.env.state_dim();
            self.final_state.resize(dim * actions.len(), 0.0);
            for (i, row) in self.final_state.chunks_exact_mut(dim.max(1)).enumerate() {
                self.env.state_of(i, row);
            }
            self.start(None, range, obs);
        }
        Ok(())
    }
}

/// `n` races of one track and scenario, stepped together on worker threads.
pub struct RaceVector {
    slots: Vec<Slot>,
    context_range: f64,
    autoreset: Autoreset,
    /// Cars each race drives from outside (lanes per race).
    agents: usize,
    obs_dim: usize,
    /// The ended episodes' last observations under [`Autoreset::SameStep`], a row per lane.
    final_obs: Vec<f32>,
    pool: rayon::ThreadPool,
    started: bool,
}

impl RaceVector {
    /// `envs` races of `cfg` on `track` whose episodes draw their contexts from
    /// `±context_range`, stepped on `threads` worker threads (0: one per core).
    pub fn new(
        track: Arc<Track>,
        cfg: &RaceConfig,
        envs: usize,
        context_range: f64,
        threads: usize,
    ) -> Result<Self, VectorError> {
        if envs == 0 {
            return Err(VectorError::Empty);
        }
        if !(0.0..=CONTEXT_LIMIT).contains(&context_range) {
            return Err(VectorError::ContextRange(context_range));
        }
        let slots = (0..envs)
            .map(|_| {
                Ok(Slot {
                    env: RaceEnv::new(track.clone(), cfg.clone())?,
                    stream: ChaCha8Rng::seed_from_u64(0),
                    pinned: None,
                    ended: true,
                    agent_ended: Vec::new(),
                    final_state: Vec::new(),
                })
            })
            .collect::<Result<Vec<_>, RaceError>>()?;
        let obs_dim = slots[0].env.obs_dim();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()?;
        Ok(Self {
            final_obs: vec![0.0; envs * obs_dim],
            slots,
            context_range,
            autoreset: Autoreset::NextStep,
            agents: 1,
            obs_dim,
            pool,
            started: false,
        })
    }

    /// The vector with the autoreset mode `autoreset` (default: [`Autoreset::NextStep`]).
    pub fn with_autoreset(mut self, autoreset: Autoreset) -> Self {
        self.autoreset = autoreset;
        self
    }

    /// The autoreset mode.
    pub fn autoreset(&self) -> Autoreset {
        self.autoreset
    }

    /// The vector whose races each drive `agents` cars from outside (see the module's agents;
    /// default 1: the ego), or the error naming the race's cars where it has too few.
    pub fn with_agents(mut self, agents: usize) -> Result<Self, VectorError> {
        for slot in &mut self.slots {
            slot.env.set_agents(agents)?;
            slot.ended = true;
        }
        self.agents = agents;
        self.final_obs = vec![0.0; self.lanes() * self.obs_dim];
        self.started = false;
        Ok(self)
    }

    /// Cars each race drives from outside.
    pub fn agents(&self) -> usize {
        self.agents
    }

    /// Lanes: an observation, action and outcome each, `len × agents`.
    pub fn lanes(&self) -> usize {
        self.slots.len() * self.agents
    }

    /// Under [`Autoreset::SameStep`], the last observations of the episodes that ended at the
    /// last step (`lanes × obs_dim`; the rows of lanes that did not end are stale).
    pub fn final_obs(&self) -> &[f32] {
        &self.final_obs
    }

    /// Each env's current episode's context.
    pub fn contexts(&self) -> impl Iterator<Item = Context> + '_ {
        self.slots.iter().map(|s| s.env.context())
    }

    /// Number of envs (races).
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// Whether the vector holds no env (never: [`RaceVector::new`] refuses that).
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Values in one env's observation.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Worker threads stepping the envs.
    pub fn threads(&self) -> usize {
        self.pool.current_num_threads()
    }

    /// The envs, in order.
    pub fn envs(&self) -> impl Iterator<Item = &RaceEnv> {
        self.slots.iter().map(|s| &s.env)
    }

    /// Checks that a buffer holds `per_lane` values per lane.
    fn check(&self, what: &'static str, got: usize, per_lane: usize) -> Result<(), VectorError> {
        let want = per_lane * self.lanes();
        match got == want {
            true => Ok(()),
            false => Err(VectorError::Shape {
                what,
                got,
                want,
                envs: self.lanes(),
            }),
        }
    }

    /// Values of one env's state ([`RaceEnv::state_dim`]).
    pub fn state_dim(&self) -> usize {
        self.slots.first().map_or(0, |s| s.env.state_dim())
    }

    /// Bounds of one env's state ([`RaceEnv::state_bounds`]).
    pub fn state_bounds(&self) -> (Vec<f32>, Vec<f32>) {
        self.slots
            .first()
            .map_or((Vec::new(), Vec::new()), |s| s.env.state_bounds())
    }

    /// Every lane's current state ([`RaceEnv::state_of`] its agent) into `out`
    /// (`lanes × state_dim`), or, with `ended`, under [`Autoreset::SameStep`] the state the
    /// episode that ended at the last step ended in (the rows of the other lanes are stale).
    pub fn states_into(&self, ended: bool, out: &mut [f32]) -> Result<(), VectorError> {
        let dim = self.state_dim();
        self.check("states", out.len(), dim)?;
        let per_race = (dim * self.agents).max(1);
        for (slot, rows) in self.slots.iter().zip(out.chunks_exact_mut(per_race)) {
            if !ended {
                for (i, row) in rows.chunks_exact_mut(dim.max(1)).enumerate() {
                    slot.env.state_of(i, row);
                }
            } else if slot.final_state.len() == rows.len() {
                rows.copy_from_slice(&slot.final_state);
            }
        }
        Ok(())
    }

    /// Starts a new episode in every race (see the module's seeds and contexts), writing the
    /// first observations into `obs` (`lanes × obs_dim`) and each lane's context into `out`
    /// (`lanes`); `contexts` (one per race) pins race `i`'s context to `contexts[i]` for this
    /// and its later episodes, `None` unpins them all.
    pub fn reset(
        &mut self,
        seed: u64,
        contexts: Option<&[Context]>,
        obs: &mut [f32],
        out: &mut [EnvOutcome],
    ) -> Result<(), VectorError> {
        self.check("obs", obs.len(), self.obs_dim)?;
        self.check("outcomes", out.len(), 1)?;
        if let Some(c) = contexts {
            if c.len() != self.len() {
                return Err(VectorError::Shape {
                    what: "contexts",
                    got: c.len(),
                    want: self.len(),
                    envs: self.len(),
                });
            }
        }
        let (range, k) = (self.context_range, self.agents);
        let races = obs.chunks_mut(self.obs_dim * k).zip(out.chunks_mut(k));
        for (i, (slot, (obs, out))) in self.slots.iter_mut().zip(races).enumerate() {
            let env_seed = seed.wrapping_add(i as u64);
            slot.stream = ChaCha8Rng::seed_from_u64(env_seed);
            slot.pinned = contexts.map(|c| c[i]);
            slot.restart(Some(env_seed), range, obs, out);
        }
        self.started = true;
        Ok(())
    }

    /// Steps every lane with its action (`actions[i]`), each race on a worker thread; a race
    /// whose episode ended at the previous step is reset instead (see [`Autoreset`]).
    /// Observations go to `obs` (`lanes × obs_dim`), the rest to `out`. Refuses, stepping
    /// nothing, a non-finite action or a call before [`RaceVector::reset`].
    pub fn step(
        &mut self,
        actions: &[[f64; 2]],
        obs: &mut [f32],
        out: &mut [EnvOutcome],
    ) -> Result<(), VectorError> {
        if !self.started {
            return Err(VectorError::NotReset);
        }
        self.check("actions", actions.len(), 1)?;
        self.check("obs", obs.len(), self.obs_dim)?;
        self.check("outcomes", out.len(), 1)?;
        if let Some(env) = actions
            .iter()
            .position(|a| !a.iter().all(|v| v.is_finite()))
        {
            return Err(VectorError::BadAction {
                env,
                action: actions[env],
            });
        }
        let (mode, k) = ((self.context_range, self.autoreset), self.agents);
        let rows = self.obs_dim * k;
        let (slots, finals) = (&mut self.slots, &mut self.final_obs);
        if slots.len() == 1 || self.pool.current_num_threads() == 1 {
            // on the caller's thread: a hop to one worker costs more than a lone race's step
            let lanes = slots
                .iter_mut()
                .zip(actions.chunks(k))
                .zip(obs.chunks_mut(rows));
            let lanes = lanes.zip(finals.chunks_mut(rows)).zip(out.chunks_mut(k));
            for ((((slot, actions), obs), final_obs), out) in lanes {
                slot.advance(actions, mode, (obs, final_obs), out)?;
            }
            return Ok(());
        }
        self.pool.install(|| {
            slots
                .par_iter_mut()
                .zip(actions.par_chunks(k))
                .zip(obs.par_chunks_mut(rows))
                .zip(finals.par_chunks_mut(rows))
                .zip(out.par_chunks_mut(k))
                .try_for_each(|((((slot, actions), obs), final_obs), out)| {
                    slot.advance(actions, mode, (obs, final_obs), out)
                })
        })?;
        Ok(())
    }
}
