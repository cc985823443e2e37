//! What a training run shows and logs as it goes: progress bars, the training episodes (CSV and
//! TensorBoard) and the run's rates.

use crate::results::TrainingEpisode;
use anyhow::{Context as _, Result};
use ctxrace_common::run_dir::TRAINING_EPISODES;
use ctxrace_learner::tensorboard::EventWriter;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::Path;
use std::time::Instant;

/// A progress bar over `len` `unit`s with their rate and, in its message, live figures.
pub fn progress_bar(len: u64, unit: &str) -> ProgressBar {
    let template =
        format!("{{elapsed_precise}} [{{bar:30}}] {{pos}}/{{len}} {unit} ({{per_sec}}) {{msg}}");
    let bar = ProgressBar::new(len);
    match ProgressStyle::with_template(&template) {
        Ok(style) => bar.with_style(style),
        Err(_) => bar,
    }
}

/// Appends training episodes to `episodes.csv` and, with the run's rates, to a TensorBoard
/// event file (scalars `episode/*` and `rate/*`, `replay/*` at the run's env steps).
pub struct EpisodeLog {
    writer: csv::Writer<std::fs::File>,
    events: EventWriter,
}

impl EpisodeLog {
    /// Opens (appending) `<run_dir>/episodes.csv`, with a new event file for `role`.
    pub fn open(run_dir: &Path, role: &str) -> Result<Self> {
        let path = run_dir.join(TRAINING_EPISODES);
        let fresh = std::fs::metadata(&path).map_or(true, |m| m.len() == 0);
        let file = ctxrace_common::run_dir::open_append(&path)
            .with_context(|| format!("opening {}", path.display()))?;
        Ok(Self {
            writer: csv::WriterBuilder::new()
                .has_headers(fresh)
                .from_writer(file),
            events: EventWriter::create(run_dir, role)?,
        })
    }

    /// Appends one episode.
    pub fn write(&mut self, episode: &TrainingEpisode) -> Result<()> {
        self.writer.serialize(episode)?;
        self.writer.flush()?;
        let flag = |b: bool| f64::from(u8::from(b));
        self.events.scalars(
            episode.env_steps,
            [
                ("episode/progress", episode.progress),
                ("episode/overtakes", f64::from(episode.overtakes)),
                ("episode/a2a", flag(episode.a2a)),
                ("episode/wall_crash", flag(episode.wall_crash)),
                ("episode/return", episode.episode_return),
                ("episode/steps", episode.steps as f64),
            ],
        )?;
        self.events.flush()
    }

    /// Records the run's rates and replay fill at `env_steps`.
    pub fn rates(&mut self, env_steps: u64, rates: &Rates) -> Result<()> {
        self.events.scalars(
            env_steps,
            [
                ("rate/env_steps_per_second", rates.env_steps_per_second),
                ("rate/grad_steps_per_second", rates.grad_steps_per_second),
                ("replay/steps", rates.replay_steps as f64),
                ("replay/fill", rates.replay_fill),
            ],
        )?;
        self.events.flush()
    }
}

/// What [`EpisodeLog::rates`] records.
#[derive(Clone, Copy, Debug, Default)]
pub struct Rates {
    /// Environment steps per second since the last record.
    pub env_steps_per_second: f64,
    /// Gradient steps per second since the last record.
    pub grad_steps_per_second: f64,
    /// Steps the replay holds.
    pub replay_steps: u64,
    /// Its fill, `[0, 1]`.
    pub replay_fill: f64,
}

/// Seconds between two [`Rates`] records.
pub const RATES_EVERY: std::time::Duration = std::time::Duration::from_secs(5);

/// Turns counters into [`Rates`] over the time since the previous reading; the first reading
/// only sets the baseline (a resumed run's counters do not start at zero).
#[derive(Clone, Debug, Default)]
pub struct RateMeter {
    last: Option<(Instant, u64, u64)>,
}

impl RateMeter {
    /// The rates since the last reading when [`RATES_EVERY`] has passed since it, else `None`.
    pub fn read(&mut self, env_steps: u64, grad_steps: u64, replay: (u64, u64)) -> Option<Rates> {
        let Some((at, env_before, grad_before)) = self.last else {
            self.last = Some((Instant::now(), env_steps, grad_steps));
            return None;
        };
        let secs = at.elapsed().as_secs_f64();
        if secs < RATES_EVERY.as_secs_f64() {
            return None;
        }
        let per_second = |now: u64, before: u64| now.saturating_sub(before) as f64 / secs;
        let rates = Rates {
            env_steps_per_second: per_second(env_steps, env_before),
            grad_steps_per_second: per_second(grad_steps, grad_before),
            replay_steps: replay.0,
            replay_fill: replay.0 as f64 / replay.1.max(1) as f64,
        };
        self.last = Some((Instant::now(), env_steps, grad_steps));
        Some(rates)
    }
}
