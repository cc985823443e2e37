//! Many races stepped together ([`RaceVector`]): `n` environments of one track and scenario,
//! stepped on worker threads, their observations and outcomes written into buffers the caller
//! owns. An env whose episode ended resets itself on the next step, ignoring that step's action
//! (Gymnasium's next-step autoreset), or, with [`Autoreset::SameStep`], in the step that ended it.
//!
//! **Seeds and contexts.** [`RaceVector::reset`] with `seed` starts env `i`'s episode from the
//! reset seed `seed + i` (what `ctxrace race --seed` passes to [`RaceEnv::reset`]); a stream of
//! that env seeded by the same number draws its later episodes' reset seeds and every
//! episode's context, uniform in `±context_range` as the training actors draw them, unless a
//! context is pinned for the env.

use crate::race::{RaceEnv, RaceError};
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
    /// Under [`Autoreset::SameStep`], the state ([`RaceEnv::state_into`]) its last ended episode
    /// ended in.
    final_state: Vec<f32>,
}

impl Slot {
    /// Starts an episode from `seed` (drawn from the stream when `None`), writing its first
    /// observation into `obs`.
    fn start(&mut self, seed: Option<u64>, range: f64, obs: &mut [f32]) -> EnvOutcome {
        let context = self
            .pinned
            .unwrap_or_else(|| draw_context(&mut self.stream, range));
        let seed = seed.unwrap_or_else(|| self.stream.random());
        obs.copy_from_slice(&self.env.reset(seed, context));
        self.ended = false;
        EnvOutcome {
            context,
            ..EnvOutcome::default()
        }
    }

    /// Steps the env with `action`, or resets it if its episode ended. Under
    /// [`Autoreset::SameStep`] a step that ends the episode writes its observation into
    /// `final_obs` and starts the next episode at once, its first observation into `obs`.
    fn advance(
        &mut self,
        action: [f64; 2],
        (range, autoreset): (f64, Autoreset),
        obs: &mut [f32],
        final_obs: &mut [f32],
    ) -> Result<EnvOutcome, RaceError> {
        if self.ended {
            return Ok(self.start(None, range, obs));
        }
        let step = self.env.step(action)?;
        self.ended = step.terminated || step.truncated;
        let context = self.env.context();
        if self.ended && autoreset == Autoreset::SameStep {
            final_obs.copy_from_slice(&step.obs);
            self.final_state.resize(self.env.state_dim(), 0.0);
            self.env.state_into(&mut self.final_state);
            self.start(None, range, obs);
        } else {
            obs.copy_from_slice(&step.obs);
        }
        Ok(EnvOutcome {
            reward: step.reward,
            terminated: step.terminated,
            truncated: step.truncated,
            context,
            progress: step.info.progress,
            overtakes: step.info.overtakes,
            a2a: step.info.a2a,
            wall_crash: step.info.wall_crash,
        })
    }
}

/// `n` races of one track and scenario, stepped together on worker threads.
pub struct RaceVector {
    slots: Vec<Slot>,
    context_range: f64,
    autoreset: Autoreset,
    obs_dim: usize,
    /// The ended episodes' last observations under [`Autoreset::SameStep`].
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

    /// Under [`Autoreset::SameStep`], the last observations of the episodes that ended at the
    /// last step (`len × obs_dim`; the rows of envs that did not end are stale).
    pub fn final_obs(&self) -> &[f32] {
        &self.final_obs
    }

    /// Each env's current episode's context.
    pub fn contexts(&self) -> impl Iterator<Item = Context> + '_ {
        self.slots.iter().map(|s| s.env.context())
    }

    /// Number of envs.
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

    /// Checks that a buffer holds `per_env` values per env.
    fn check(&self, what: &'static str, got: usize, per_env: usize) -> Result<(), VectorError> {
        let want = per_env * self.len();
        match got == want {
            true => Ok(()),
            false => Err(VectorError::Shape {
                what,
                got,
                want,
                envs: self.len(),
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

    /// Every env's current state ([`RaceEnv::state_into`]) into `out` (`len × state_dim`), or,
    /// with `ended`, under [`Autoreset::SameStep`] the state the episode that ended at the last
    /// step ended in (the rows of the other envs are stale).
    pub fn states_into(&self, ended: bool, out: &mut [f32]) -> Result<(), VectorError> {
        let dim = self.state_dim();
        self.check("states", out.len(), dim)?;
        for (slot, row) in self.slots.iter().zip(out.chunks_exact_mut(dim.max(1))) {
            if !ended {
                slot.env.state_into(row);
            } else if slot.final_state.len() == dim {
                row.copy_from_slice(&slot.final_state);
            }
        }
        Ok(())
    }

    /// Starts a new episode in every env (see the module's seeds and contexts), writing the
    /// first observations into `obs` (`len × obs_dim`) and each env's context into `out`;
    /// `contexts` pins env `i`'s context to `contexts[i]` for this and its later episodes,
    /// `None` unpins them all.
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
            self.check("contexts", c.len(), 1)?;
        }
        let range = self.context_range;
        for (i, ((slot, obs), out)) in self
            .slots
            .iter_mut()
            .zip(obs.chunks_mut(self.obs_dim))
            .zip(out.iter_mut())
            .enumerate()
        {
            let env_seed = seed.wrapping_add(i as u64);
            slot.stream = ChaCha8Rng::seed_from_u64(env_seed);
            slot.pinned = contexts.map(|c| c[i]);
            *out = slot.start(Some(env_seed), range, obs);
        }
        self.started = true;
        Ok(())
    }

    /// Steps every env with its action (`actions[i]`), on the worker threads; an env whose
    /// episode ended at the previous step is reset instead (see [`Autoreset`]). Observations go to `obs`
    /// (`len × obs_dim`), the rest to `out`. Refuses, stepping nothing, a non-finite action
    /// or a call before [`RaceVector::reset`].
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
        let (mode, dim) = ((self.context_range, self.autoreset), self.obs_dim);
        let (slots, finals) = (&mut self.slots, &mut self.final_obs);
        if slots.len() == 1 || self.pool.current_num_threads() == 1 {
            // on the caller's thread: a hop to one worker costs more than a lone race's step
            let lanes = slots.iter_mut().zip(actions).zip(obs.chunks_mut(dim));
            let lanes = lanes.zip(finals.chunks_mut(dim)).zip(out.iter_mut());
            for ((((slot, &action), obs), final_obs), out) in lanes {
                *out = slot.advance(action, mode, obs, final_obs)?;
            }
            return Ok(());
        }
        self.pool.install(|| {
            slots
                .par_iter_mut()
                .zip(actions.par_iter())
                .zip(obs.par_chunks_mut(dim))
                .zip(finals.par_chunks_mut(dim))
                .zip(out.par_iter_mut())
                .try_for_each(|((((slot, &action), obs), final_obs), out)| {
                    *out = slot.advance(action, mode, obs, final_obs)?;
                    Ok::<_, RaceError>(())
                })
        })?;
        Ok(())
    }
}
