//! What a single-process trainer runs on, as two small traits every crate can see: an
//! [`ExperienceSource`] that runs episodes one decision at a time (the actor's collector) and a
//! [`SampleStore`] that keeps the steps and draws training batches (the replay buffer). The
//! learner trains over them without depending on the crates that implement them; whoever
//! composes a run builds both and passes them in.

use crate::results::TrainingEpisode;
use crate::steps::TrajectoryStep;
use ctxrace_config::{Batch, BatchSpec, Sampler};
use rand_chacha::ChaCha8Rng;
use std::path::Path;

/// A training episode as its source reports it when it ends.
#[derive(Clone, Debug, PartialEq)]
pub struct EndedEpisode {
    /// Its row of the training curves, but for the run's counters (`env_steps`, `grad_steps`,
    /// `actor`: zero until [`EndedEpisode::row`] sets them).
    pub record: TrainingEpisode,
    /// The policy chose every action of the episode (no random prefill action).
    pub by_policy: bool,
    /// cMask's mean context mask `[m_v, m_θ]` over the decisions its policy masked, and their
    /// count (`None` where no decision was masked).
    pub mean_mask: Option<([f64; 2], u64)>,
}

impl EndedEpisode {
    /// Its row of the training curves (`episodes.csv`), run by `actor` and ended when the run
    /// had taken `env_steps` environment steps and `grad_steps` gradient steps.
    pub fn row(&self, actor: u32, env_steps: u64, grad_steps: u64) -> TrainingEpisode {
        TrainingEpisode {
            env_steps,
            grad_steps,
            actor,
            ..self.record.clone()
        }
    }
}

/// Where an experience source stands between two episodes: all it needs to go on exactly as it
/// would have (its counters and the position of its random stream), for a resumed run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SourcePosition {
    /// Decisions taken.
    pub decisions: u64,
    /// Episodes started.
    pub episodes: u64,
    /// Words its random stream has given (ChaCha's word position).
    pub rng_words: u128,
}

/// Why a store's contents could not be saved or restored (its own error, boxed).
pub type StoreError = Box<dyn std::error::Error + Send + Sync>;

/// Runs training episodes one decision at a time and reports every step in the replay's
/// convention ([`TrajectoryStep`]).
pub trait ExperienceSource {
    /// The acting policy it runs (the networks' `Policy` in ctxrace's processes).
    type Policy;

    /// Why a decision could not be taken (the policy's or the simulator's error).
    type Error: std::error::Error + Send + Sync + 'static;

    /// Length of one observation frame.
    fn obs_dim(&self) -> usize;

    /// Decisions taken so far.
    fn decisions(&self) -> u64;

    /// Episodes started so far.
    fn episodes(&self) -> u64;

    /// Whether the next [`ExperienceSource::step`] starts a new episode.
    fn at_episode_boundary(&self) -> bool;

    /// Takes one decision with `policy` (uniform random actions when `None`), starting an
    /// episode first if none is running; passes the steps to `sink` and returns the episode
    /// if it ended.
    fn step(
        &mut self,
        policy: Option<&mut Self::Policy>,
        sink: &mut dyn FnMut(&TrajectoryStep),
    ) -> Result<Option<EndedEpisode>, Self::Error>;

    /// Where it stands, at an episode boundary only (`None` within an episode).
    fn position(&self) -> Option<SourcePosition>;

    /// Continues from `at`, a [`ExperienceSource::position`] of a source built as this one
    /// was: its next step starts the episode that source's next step would have started.
    fn restore(&mut self, at: &SourcePosition);
}

/// Keeps the steps of a run's streams and draws training batches from them.
pub trait SampleStore {
    /// Length of the observation frame of a stored step.
    fn obs_dim(&self) -> usize;

    /// Length of the action of a stored step.
    fn act_dim(&self) -> usize;

    /// Steps held.
    fn len(&self) -> usize;

    /// Whether it holds no step.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Steps it can hold.
    fn capacity(&self) -> usize;

    /// Appends a chunk payload (steps encoded by [`TrajectoryStep::encode`]) to stream
    /// `actor`; `after_gap` starts a new segment.
    fn insert_chunk(&mut self, actor: usize, payload: &[f32], after_gap: bool);

    /// One batch of `spec`: sequences drawn by `sampler`, transitions uniformly; `None` if the
    /// store cannot serve it yet.
    fn sample(&self, spec: BatchSpec, sampler: Sampler, rng: &mut ChaCha8Rng) -> Option<Batch>;

    /// Writes everything it holds to `path`, so that [`SampleStore::restore`] gives a store
    /// that draws the same batches.
    fn save(&self, path: &Path) -> Result<(), StoreError>;

    /// Replaces its contents by what [`SampleStore::save`] wrote to `path` from a store of the
    /// same shape; a damaged file or another shape is an error naming the file.
    fn restore(&mut self, path: &Path) -> Result<(), StoreError>;
}
