//! The evaluated runs a report reads, grouped by algorithm, track and number of rivals (a group's
//! runs are its training seeds), with the paper's metrics and splits: each run's metric averaged
//! over its in- or out-of-distribution contexts, and those per-run means over a group's seeds.

use anyhow::{bail, Result};
use ctxrace_config::AlgoKind;
use ctxrace_run::results::{read_csv, read_json, TrainingEpisode};
use ctxrace_run::run_dir::{
    EVAL_CONTEXTS_CSV, EVAL_DIR, EVAL_EPISODES, EVAL_META, TRAINING_EPISODES,
};
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::evaluation::EvalMeta;
use ctxrace_sim::evaluation::{summarise, ContextSummary, EvalEpisode, SplitMeans};
use ctxrace_sim::masks::{load_summary, MaskSummary};
use std::path::{Path, PathBuf};

/// One evaluated agent or baseline, as read from disk.
#[derive(Clone, Debug)]
pub struct Run {
    /// The evaluation directory.
    pub dir: PathBuf,
    /// What was evaluated.
    pub meta: EvalMeta,
    /// Per-context results.
    pub contexts: Vec<ContextSummary>,
    /// The training episodes, when the run was given as a training run directory that has them.
    pub training: Vec<TrainingEpisode>,
    /// cMask's masks in the evaluation, when it recorded them.
    pub masks: Option<MaskSummary>,
}

impl Run {
    /// Reads an evaluation directory, or a training run directory with an `eval/` inside.
    pub fn load(path: &Path) -> Result<Self> {
        let (dir, training) = if path.join(EVAL_META).is_file() {
            (path.to_path_buf(), Vec::new())
        } else if path.join(EVAL_DIR).join(EVAL_META).is_file() {
            let csv = path.join(TRAINING_EPISODES);
            let training = if csv.is_file() {
                read_csv(&csv)?
            } else {
                Vec::new()
            };
            (path.join(EVAL_DIR), training)
        } else if !path.is_dir() {
            bail!("{}: no such directory", path.display());
        } else {
            bail!(
                "{}: neither an evaluation directory (no meta.json) nor a training run (no eval/meta.json)",
                path.display()
            );
        };
        let meta: EvalMeta = read_json(&dir.join(EVAL_META))?;
        if !(meta.train_range.is_finite() && meta.train_range >= 0.0) {
            bail!(
                "{}: train_range must be a number ≥ 0, not {}",
                dir.join(EVAL_META).display(),
                meta.train_range
            );
        }
        let contexts = load_contexts(&dir, meta.train_range)?;
        let masks = load_summary(&dir)?;
        Ok(Self {
            dir,
            meta,
            contexts,
            training,
            masks,
        })
    }
}

/// The per-context results of an evaluation directory: `contexts.csv`, or else `episodes.csv`
/// summarised.
fn load_contexts(dir: &Path, train_range: f64) -> Result<Vec<ContextSummary>> {
    let (csv, episodes) = (dir.join(EVAL_CONTEXTS_CSV), dir.join(EVAL_EPISODES));
    let (contexts, source) = if csv.is_file() {
        (read_csv::<ContextSummary>(&csv)?, csv)
    } else if episodes.is_file() {
        let eps: Vec<EvalEpisode> = read_csv(&episodes)?;
        (summarise(&eps, train_range), episodes)
    } else {
        bail!(
            "{}: holds neither contexts.csv nor episodes.csv",
            dir.display()
        );
    };
    if contexts.is_empty() {
        bail!("{}: no contexts", source.display());
    }
    let finite = |c: &ContextSummary| {
        [c.context_speed, c.context_steer]
            .into_iter()
            .chain(Metric::ALL.map(|m| m.of(c)))
            .all(f64::is_finite)
    };
    if let Some(c) = contexts.iter().find(|c| !finite(c)) {
        bail!(
            "{}: context ({}, {}) has a value that is not a number",
            source.display(),
            c.context_speed,
            c.context_steer
        );
    }
    Ok(contexts)
}

/// A metric of the paper's tables.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Metric {
    /// PG: track progress.
    Progress,
    /// OT: overtakes per episode.
    Overtakes,
    /// A2A: ego–rival collisions per 50 laps.
    A2a,
}

impl Metric {
    /// The columns of Table II, in order.
    pub const ALL: [Metric; 3] = [Metric::Progress, Metric::Overtakes, Metric::A2a];

    /// Its value in one context.
    pub fn of(self, c: &ContextSummary) -> f64 {
        match self {
            Metric::Progress => c.progress,
            Metric::Overtakes => c.overtakes,
            Metric::A2a => c.a2a,
        }
    }

    /// Higher is better (PG, OT), or lower (A2A).
    pub fn higher_is_better(self) -> bool {
        self != Metric::A2a
    }

    /// The paper's abbreviation.
    pub fn label(self) -> &'static str {
        match self {
            Metric::Progress => "PG",
            Metric::Overtakes => "OT",
            Metric::A2a => "A2A",
        }
    }

    /// An arrow pointing the better way.
    pub fn arrow(self) -> &'static str {
        if self.higher_is_better() {
            "↑"
        } else {
            "↓"
        }
    }
}

/// In or out of the training distribution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    /// Both context values inside the training range.
    In,
    /// At least one context value outside it.
    Out,
}

impl Split {
    /// Both splits, in table order.
    pub const ALL: [Split; 2] = [Split::In, Split::Out];

    /// Whether a context belongs to this split.
    pub fn contains(self, c: &ContextSummary, train_range: f64) -> bool {
        c.context().within(train_range) == (self == Split::In)
    }

    /// "In" or "Out".
    pub fn label(self) -> &'static str {
        match self {
            Split::In => "In",
            Split::Out => "Out",
        }
    }
}

/// Mean of `metric` over the contexts of `run` in `split`; `None` when it has no such context.
pub fn split_mean(run: &Run, split: Split, metric: Metric) -> Option<f64> {
    let inside = |c: &&ContextSummary| split.contains(c, run.meta.train_range);
    let means = SplitMeans::of(run.contexts.iter().filter(inside))?;
    Some(match metric {
        Metric::Progress => means.progress,
        Metric::Overtakes => means.overtakes,
        Metric::A2a => means.a2a,
    })
}

/// Mean and sample standard deviation of values from several seeds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stat {
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (divides by n − 1; 0 for one value).
    pub std: f64,
    /// Values averaged.
    pub n: usize,
}

impl Stat {
    /// The statistics of `values`; `None` when there are none.
    pub fn of(values: &[f64]) -> Option<Self> {
        let n = values.len();
        if n == 0 {
            return None;
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let var = if n > 1 {
            values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64
        } else {
            0.0
        };
        Some(Self {
            mean,
            std: var.sqrt(),
            n,
        })
    }
}

/// The runs of one algorithm on one track against one number of rivals: its training seeds.
#[derive(Clone, Debug)]
pub struct Group {
    /// Algorithm or baseline name.
    pub algo: String,
    /// Track name.
    pub track: String,
    /// Number of rivals.
    pub rivals: usize,
    /// The runs.
    pub runs: Vec<Run>,
}

impl Group {
    /// A baseline (`random`, `pure-pursuit`, `still`): a reference row that never competes.
    pub fn is_baseline(&self) -> bool {
        self.algo.parse::<BaselineKind>().is_ok()
    }

    /// Seed statistics of the per-run means of `metric` in `split`.
    pub fn stat(&self, split: Split, metric: Metric) -> Option<Stat> {
        let means: Vec<f64> = self
            .runs
            .iter()
            .filter_map(|r| split_mean(r, split, metric))
            .collect();
        Stat::of(&means)
    }

    /// Percentage change of the seed mean of `metric` from in- to out-of-distribution,
    /// `100 (out − in) / |in|`; `None` when either is missing or `in` is 0.
    pub fn delta_pct(&self, metric: Metric) -> Option<f64> {
        let inside = self.stat(Split::In, metric)?.mean;
        let outside = self.stat(Split::Out, metric)?.mean;
        (inside != 0.0).then(|| 100.0 * (outside - inside) / inside.abs())
    }

    /// The algorithm's name as in the paper, baselines marked.
    pub fn display_name(&self) -> String {
        let name = match self.algo.parse::<AlgoKind>() {
            Ok(algo) => algo.display_name(),
            Err(_) => self.algo.as_str(),
        };
        if self.is_baseline() {
            format!("{name} (baseline)")
        } else {
            name.to_string()
        }
    }

    /// "TRACK, N rival(s)": the section of the tables this group belongs to.
    pub fn section(&self) -> String {
        let s = if self.rivals == 1 { "" } else { "s" };
        format!("{}, {} rival{s}", self.track, self.rivals)
    }

    /// Sort key: track, rivals, then the algorithms in the paper's order ([`AlgoKind::ALL`]),
    /// other agents alphabetically, then the baselines.
    pub fn order(&self) -> (String, usize, usize, String) {
        let others = AlgoKind::ALL.len();
        let rank = if self.is_baseline() {
            others + 1
        } else {
            self.algo
                .parse::<AlgoKind>()
                .ok()
                .and_then(|a| AlgoKind::ALL.iter().position(|&b| b == a))
                .unwrap_or(others)
        };
        (self.track.clone(), self.rivals, rank, self.algo.clone())
    }
}

/// Groups runs by (algorithm, track, rivals), ordered by track, rivals and algorithm. Warns about
/// a training seed that appears twice in a group (the same run given twice?).
pub fn group(runs: Vec<Run>) -> Vec<Group> {
    let mut groups: Vec<Group> = Vec::new();
    for run in runs {
        let m = &run.meta;
        match groups
            .iter_mut()
            .find(|g| g.algo == m.algo && g.track == m.track && g.rivals == m.rivals)
        {
            Some(g) => {
                if let Some(twin) = g
                    .runs
                    .iter()
                    .find(|r| r.meta.train_seed == run.meta.train_seed)
                {
                    tracing::warn!(
                        "{} and {} are both {} seed {} on {}: averaging both",
                        twin.dir.display(),
                        run.dir.display(),
                        m.algo,
                        m.train_seed,
                        g.section()
                    );
                }
                g.runs.push(run);
            }
            None => groups.push(Group {
                algo: m.algo.clone(),
                track: m.track.clone(),
                rivals: m.rivals,
                runs: vec![run],
            }),
        }
    }
    groups.sort_by_key(Group::order);
    groups
}

/// The groups of each (track, rivals) section, in order.
pub fn sections(groups: &[Group]) -> impl Iterator<Item = &[Group]> {
    groups.chunk_by(|a, b| a.track == b.track && a.rivals == b.rivals)
}
