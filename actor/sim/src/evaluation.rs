//! The paper's evaluation protocol: every context of a `grid × grid` grid over `[−range, range]²`
//! (7 × 7 over ±0.3 in the paper), `laps` episodes (laps) each from seeded resets, the ego's
//! metrics per episode and their means per context, split in and out of the training
//! distribution. The grid itself is [`Context::grid`].
//!
//! **Definitions.** PG: the largest fraction of the lap the ego completed in the episode.
//! OT: +1 each time the ego passes a rival, −1 each time a rival passes it, by track progress,
//! summed over the episode. A2A: the episode ended in an ego–rival collision; per context it is
//! reported as the number of such episodes per 50 laps, as the paper does. A context is
//! in-distribution when both of its values lie inside the training range `[−r, r]`
//! ([`Context::within`]).
//!
//! **Records.** An evaluation directory holds [`EvalMeta`] (`meta.json`), one [`EvalEpisode`]
//! per episode (`episodes.csv`) and one [`ContextSummary`] per context (`contexts.csv`,
//! `contexts.json`); the file names are in `ctxrace_run::run_dir`, the readers and writers
//! in `ctxrace_run::results`. [`run_episode`] races one episode of the grid.

use crate::driver::{ActMode, Decided, DriveError, Ego};
use crate::race::{EpisodeMetrics, RaceEnv};
use ctxrace_config::Context;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Laps per context that A2A counts are scaled to (the paper's protocol).
pub const A2A_PER_LAPS: f64 = 50.0;

/// What was evaluated, and how (an evaluation directory's `meta.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalMeta {
    /// Algorithm name (`sac`, `dreamerv3`, `crssm`, `cmask`) or baseline (`random`, `pure-pursuit`).
    pub algo: String,
    /// Track name.
    pub track: String,
    /// Number of rivals.
    pub rivals: usize,
    /// Training seed of the agent (groups runs for seed averaging).
    pub train_seed: u64,
    /// Half-width of the training context range (in-distribution bound).
    pub train_range: f64,
    /// Grid points per context dimension.
    pub grid: usize,
    /// Half-width of the evaluation grid.
    pub range: f64,
    /// Laps (episodes) per context.
    pub laps: usize,
    /// Seed of the evaluation episodes.
    pub seed: u64,
    /// Checkpoint directory evaluated, or the baseline's name.
    pub source: String,
    /// Which checkpoint of the run: `best`, `latest` or `step-N` (`given` for a checkpoint
    /// directory, `-` for a baseline); evaluations written before it was recorded used the
    /// newest.
    #[serde(default = "newest_checkpoint")]
    pub checkpoint: String,
    /// How a trained agent acted: `sample` (the paper's) or `mode` (what evaluations written
    /// before it was recorded did).
    #[serde(default = "mode_of_policy")]
    pub act: ActMode,
    /// The race scenario's preset.
    #[serde(default)]
    pub preset: ctxrace_config::RacePreset,
    /// Indices (in the grid's `c_v`-major order) of the contexts raced; none: the whole grid.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contexts: Option<Vec<usize>>,
    /// What a trained agent was told about the rivals' context (the context ablation; the
    /// protocol tells the truth).
    #[serde(default, skip_serializing_if = "ToldContext::is_true")]
    pub told: ToldContext,
    /// cMask's mask, fixed instead of chosen (the context ablation).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mask: Option<[f32; 2]>,
}

/// What a trained agent is told about the rivals' context in an evaluation: the truth (the
/// paper's protocol), or, to measure what the context is worth, zeros or another episode's.
/// The rivals always drive by the true context.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum ToldContext {
    /// The episode's own context.
    #[default]
    True,
    /// `c = (0, 0)`, the centre of the training range.
    Zeros,
    /// Another raced context, drawn uniformly from the others, seeded by the episode
    /// ([`ToldContext::told`]).
    Other,
}

impl ToldContext {
    /// Whether the agent is told the truth.
    pub fn is_true(&self) -> bool {
        *self == ToldContext::True
    }

    /// The context the agent is told in the episode of grid context `index` reset from `seed`,
    /// when `raced` (grid indices, into `grid`) are the contexts of the evaluation; `None`: the
    /// truth. `Other` with a single raced context tells that one.
    pub fn told(
        self,
        grid: &[Context],
        raced: &[usize],
        index: usize,
        seed: u64,
    ) -> Option<Context> {
        match self {
            ToldContext::True => None,
            ToldContext::Zeros => Some(Context::default()),
            ToldContext::Other => {
                let others: Vec<usize> = raced.iter().copied().filter(|&i| i != index).collect();
                if others.is_empty() {
                    return Some(grid[index]);
                }
                // a stream of its own, apart from the ego's noise seeded by the same episode
                let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x7E11_C0A7_E47C_0DE5);
                Some(grid[others[rng.random_range(0..others.len())]])
            }
        }
    }
}

fn newest_checkpoint() -> String {
    "latest".into()
}

fn mode_of_policy() -> ActMode {
    ActMode::Mode
}

/// One evaluation episode.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalEpisode {
    /// Rival speed context `c_v`.
    pub context_speed: f64,
    /// Rival steering context `c_θ`.
    pub context_steer: f64,
    /// Index of the lap within its context, `0..laps`.
    pub lap: usize,
    /// Seed the episode was reset with.
    pub seed: u64,
    /// PG of the episode, `[0, 1]`.
    pub progress: f64,
    /// OT of the episode.
    pub overtakes: i32,
    /// The episode ended in an ego–rival collision.
    pub a2a: bool,
    /// The episode ended with the ego hitting a wall.
    pub wall_crash: bool,
    /// The ego completed the lap.
    pub lap_complete: bool,
    /// Lap time when completed (s), else empty.
    pub lap_time: Option<f64>,
    /// Decisions taken.
    pub steps: usize,
    /// Sum of rewards.
    pub episode_return: f64,
    /// The car in the lead at the end ([`EpisodeMetrics::leader`]; 0 the ego); empty in records
    /// written before it was kept.
    #[serde(default)]
    pub leader: Option<usize>,
}

/// The episodes of one context, aggregated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ContextSummary {
    /// Rival speed context `c_v`.
    pub context_speed: f64,
    /// Rival steering context `c_θ`.
    pub context_steer: f64,
    /// Both context values inside the training range.
    pub in_distribution: bool,
    /// Episodes aggregated.
    pub laps: usize,
    /// Mean PG.
    pub progress: f64,
    /// Mean OT per episode.
    pub overtakes: f64,
    /// Episodes ending in an ego–rival collision, per [`A2A_PER_LAPS`] laps.
    pub a2a: f64,
    /// Fraction of episodes ending at a wall.
    pub wall_crash: f64,
    /// Fraction of episodes completing the lap.
    pub lap_complete: f64,
    /// Mean episode return.
    pub episode_return: f64,
}

/// The means over the contexts of one split of an evaluation (in or out of the training
/// distribution): the split values `ctxrace eval` prints, `ctxrace report` tabulates and Python's
/// `Evaluation.means` returns.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SplitMeans {
    /// Contexts averaged.
    pub contexts: usize,
    /// Mean PG.
    pub progress: f64,
    /// Mean OT per episode.
    pub overtakes: f64,
    /// Mean A2A per [`A2A_PER_LAPS`] laps.
    pub a2a: f64,
    /// Mean fraction of episodes ending at a wall.
    pub wall_crash: f64,
}

impl SplitMeans {
    /// The means of `rows` (each context counts once, whatever its laps); `None` without rows.
    pub fn of<'a>(rows: impl IntoIterator<Item = &'a ContextSummary>) -> Option<Self> {
        let rows: Vec<&ContextSummary> = rows.into_iter().collect();
        let n = rows.len() as f64;
        let mean = |f: fn(&ContextSummary) -> f64| rows.iter().map(|r| f(r)).sum::<f64>() / n;
        (!rows.is_empty()).then(|| Self {
            contexts: rows.len(),
            progress: mean(|r| r.progress),
            overtakes: mean(|r| r.overtakes),
            a2a: mean(|r| r.a2a),
            wall_crash: mean(|r| r.wall_crash),
        })
    }

    /// The means of the rows of `summary` in (`inside`) or out of the training distribution.
    pub fn split(summary: &[ContextSummary], inside: bool) -> Option<Self> {
        Self::of(summary.iter().filter(|s| s.in_distribution == inside))
    }
}

/// Aggregates episodes per context, in the order contexts first appear.
pub fn summarise(episodes: &[EvalEpisode], train_range: f64) -> Vec<ContextSummary> {
    let mut keys: Vec<(f64, f64)> = Vec::new();
    for e in episodes {
        let key = (e.context_speed, e.context_steer);
        if !keys.contains(&key) {
            keys.push(key);
        }
    }
    keys.into_iter()
        .map(|(cv, ct)| {
            let eps: Vec<&EvalEpisode> = episodes
                .iter()
                .filter(|e| e.context_speed == cv && e.context_steer == ct)
                .collect();
            let n = eps.len() as f64;
            let mean = |f: &dyn Fn(&EvalEpisode) -> f64| eps.iter().map(|e| f(e)).sum::<f64>() / n;
            ContextSummary {
                context_speed: cv,
                context_steer: ct,
                in_distribution: Context {
                    speed: cv,
                    steer: ct,
                }
                .within(train_range),
                laps: eps.len(),
                progress: mean(&|e| e.progress),
                overtakes: mean(&|e| e.overtakes as f64),
                a2a: mean(&|e| e.a2a as u8 as f64) * A2A_PER_LAPS,
                wall_crash: mean(&|e| e.wall_crash as u8 as f64),
                lap_complete: mean(&|e| e.lap_complete as u8 as f64),
                episode_return: mean(&|e| e.episode_return),
            }
        })
        .collect()
}

impl ContextSummary {
    /// The context summarised.
    pub fn context(&self) -> Context {
        Context {
            speed: self.context_speed,
            steer: self.context_steer,
        }
    }
}

/// The reset seed of lap `lap` of context `index` in an evaluation seeded `seed` (distinct for
/// every episode of an evaluation).
pub fn episode_seed(seed: u64, index: usize, lap: usize) -> u64 {
    seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ ((index as u64) << 32 | lap as u64)
}

impl EvalEpisode {
    /// The record of lap `lap` in `context`, reset with `seed`, from the simulator's metrics of
    /// the episode and whether the ego completed the lap.
    pub fn new(
        context: Context,
        lap: usize,
        seed: u64,
        metrics: &EpisodeMetrics,
        lap_complete: bool,
    ) -> Self {
        Self {
            context_speed: context.speed,
            context_steer: context.steer,
            lap,
            seed,
            progress: metrics.progress,
            overtakes: metrics.overtakes,
            a2a: metrics.a2a,
            wall_crash: metrics.wall_crash,
            lap_complete,
            lap_time: metrics.lap_time,
            steps: metrics.steps,
            episode_return: metrics.episode_return,
            leader: Some(metrics.leader),
        }
    }
}

/// Races lap `lap` of `context` from `seed` to its end with `driver`, showing `observe` every
/// decision ([`Ego::drive_observed`]); returns its record.
pub fn run_episode<D: Ego>(
    env: &mut RaceEnv,
    driver: &mut D,
    context: Context,
    seed: u64,
    lap: usize,
    observe: impl FnMut(&RaceEnv, Decided),
) -> Result<EvalEpisode, DriveError<D::Error>> {
    let last = driver.drive_observed(env, context, seed, observe)?;
    Ok(EvalEpisode::new(
        context,
        lap,
        seed,
        env.metrics(),
        last.lap_complete,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(cv: f64, ct: f64, progress: f64, a2a: bool) -> EvalEpisode {
        EvalEpisode {
            context_speed: cv,
            context_steer: ct,
            lap: 0,
            seed: 0,
            progress,
            overtakes: 1,
            a2a,
            wall_crash: false,
            lap_complete: progress >= 1.0,
            lap_time: None,
            steps: 10,
            episode_return: 2.0,
            leader: Some(0),
        }
    }

    #[test]
    fn told_context_is_another_raced_one_spread_over_them() {
        let grid = Context::grid(7, 0.3);
        let raced: Vec<usize> = (17..=48).collect();
        assert_eq!(ToldContext::True.told(&grid, &raced, 20, 5), None);
        assert_eq!(
            ToldContext::Zeros.told(&grid, &raced, 20, 5),
            Some(Context::default())
        );
        let mut seen = std::collections::BTreeSet::new();
        for lap in 0..2000 {
            let seed = episode_seed(0, 20, lap);
            let told = ToldContext::Other.told(&grid, &raced, 20, seed).unwrap();
            let k = grid.iter().position(|c| *c == told).unwrap();
            assert!(k != 20 && raced.contains(&k), "told grid context {k}");
            assert_eq!(ToldContext::Other.told(&grid, &raced, 20, seed), Some(told));
            seen.insert(k);
        }
        assert_eq!(
            seen.len(),
            raced.len() - 1,
            "every other raced context is drawn"
        );
        assert_eq!(ToldContext::Other.told(&grid, &[3], 3, 9), Some(grid[3]));
    }

    #[test]
    fn csv_round_trip_keeps_missing_lap_times() {
        use ctxrace_run::results::{read_csv, write_csv};
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("e.csv");
        let lap = |speed, steer, lap_time| {
            let metrics = EpisodeMetrics {
                progress: 0.4,
                lap_time,
                ..EpisodeMetrics::default()
            };
            EvalEpisode::new(Context { speed, steer }, 0, 7, &metrics, lap_time.is_some())
        };
        let rows = vec![lap(0.0, 0.1, Some(31.5)), lap(-0.3, 0.3, None)];
        write_csv(&path, &rows).unwrap();
        assert_eq!(read_csv::<EvalEpisode>(&path).unwrap(), rows);
    }

    #[test]
    fn summary_per_context_with_a2a_per_fifty_laps() {
        let eps = [
            episode(0.1, 0.0, 1.0, false),
            episode(0.1, 0.0, 0.5, true),
            episode(0.3, -0.2, 0.2, true),
        ];
        let s = summarise(&eps, 0.15);
        assert_eq!(s.len(), 2);
        assert!(s[0].in_distribution && !s[1].in_distribution);
        assert!((s[0].progress - 0.75).abs() < 1e-12);
        assert!((s[0].a2a - 25.0).abs() < 1e-12);
        assert!((s[0].lap_complete - 0.5).abs() < 1e-12);
        assert!((s[1].a2a - 50.0).abs() < 1e-12);
    }
}
