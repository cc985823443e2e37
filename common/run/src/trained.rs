//! A trained agent read back from its run directory: the checkpoint chosen (best, latest or a
//! given step), verified, with its agent configuration, its policy weights and the run's
//! experiment, for `eval`, `race` and the first look after training.

use crate::checkpoint::{
    best_at_dir, best_checkpoint, checkpoint_step, checkpoints, latest_checkpoint, verify,
    CheckpointError,
};
use crate::run_dir::{AGENT_FILE, CONFIG_FILE, POLICY_FILE};
use ctxrace_config::agents::AgentConfigError;
use ctxrace_config::{AgentConfig, ExperimentConfig, ExperimentError, RaceConfig};
use std::path::{Path, PathBuf};

/// Why a trained agent could not be read back; each names the folder or file and, where there
/// is one, the way out.
#[derive(Debug, thiserror::Error)]
pub enum TrainedAgentError {
    /// The path is neither a checkpoint nor a run directory with checkpoints.
    #[error(
        "{} is neither a checkpoint (no {POLICY_FILE}) nor a run directory with \
         checkpoints/step-*; train one with `ctxrace train`",
        .0.display()
    )]
    NotTrained(PathBuf),
    /// The run directory has no intact checkpoint of the choice.
    #[error("{}", missing_message(.run, .choice, .why, .alternatives))]
    Missing {
        /// The run directory.
        run: PathBuf,
        /// The checkpoint asked for.
        choice: CheckpointChoice,
        /// Why there is none, when known (a clause starting with a space, or empty).
        why: &'static str,
        /// The intact checkpoints to pass instead (`best (intact)`, `latest`, `step-N`).
        alternatives: Vec<String>,
    },
    /// The checkpoint is damaged (its seal does not hold).
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// A file of the checkpoint could not be read.
    #[error("reading {}", .path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The checkpoint's agent configuration is no TOML.
    #[error("parsing {}", .path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: toml::de::Error,
    },
    /// The checkpoint's agent configuration is refused.
    #[error("{}", .path.display())]
    Agent {
        /// The file.
        path: PathBuf,
        /// Why (it names the key).
        #[source]
        source: Box<AgentConfigError>,
    },
    /// The run's experiment could not be read.
    #[error(transparent)]
    Experiment(#[from] ExperimentError),
}

/// [`TrainedAgentError::Missing`]'s message.
fn missing_message(
    run: &Path,
    choice: &CheckpointChoice,
    why: &str,
    alternatives: &[String],
) -> String {
    match alternatives.is_empty() {
        true => format!(
            "{} has no {choice} checkpoint{why} and no other intact one; train it again with \
             `ctxrace train`",
            run.display()
        ),
        false => format!(
            "{} has no {choice} checkpoint{why}; pass --checkpoint {}",
            run.display(),
            alternatives.join(" or ")
        ),
    }
}

/// The outcome of reading a trained agent.
type Result<T> = std::result::Result<T, TrainedAgentError>;

/// Which checkpoint of a run directory to load; the evaluation protocol's by default.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum CheckpointChoice {
    /// The policy at the peak of the smoothed training return (the paper's `best_`).
    #[default]
    Best,
    /// The newest checkpoint.
    Latest,
    /// The checkpoint after this many gradient steps.
    Step(u64),
    /// The best policy as it was after this many environment steps (`[train] keep_best_at`).
    BestAt(u64),
}

/// A name that is no [`CheckpointChoice`].
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("'{0}' is not best, latest, step-N (e.g. step-5000) or best-at-N (e.g. best-at-25000)")]
pub struct UnknownCheckpointChoice(pub String);

impl std::str::FromStr for CheckpointChoice {
    type Err = UnknownCheckpointChoice;

    fn from_str(s: &str) -> std::result::Result<Self, UnknownCheckpointChoice> {
        match s {
            "best" => Ok(Self::Best),
            "latest" => Ok(Self::Latest),
            _ => None
                .or_else(|| s.strip_prefix("step-")?.parse().ok().map(Self::Step))
                .or_else(|| s.strip_prefix("best-at-")?.parse().ok().map(Self::BestAt))
                .ok_or_else(|| UnknownCheckpointChoice(s.to_string())),
        }
    }
}

impl std::fmt::Display for CheckpointChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Best => write!(f, "best"),
            Self::Latest => write!(f, "latest"),
            Self::Step(n) => write!(f, "step-{n}"),
            Self::BestAt(n) => write!(f, "best-at-{n}"),
        }
    }
}

/// A trained agent's acting side as stored in a checkpoint.
#[derive(Clone, Debug)]
pub struct TrainedAgent {
    /// The checkpoint directory.
    pub checkpoint: PathBuf,
    /// The agent's configuration.
    pub agent: AgentConfig,
    /// The policy weights (safetensors bytes).
    pub weights: Vec<u8>,
    /// The experiment of the run it belongs to, when the run directory is known.
    pub experiment: Option<ExperimentConfig>,
}

impl TrainedAgent {
    /// Loads a checkpoint directory, or the checkpoint `choice` of a run directory.
    pub fn load(path: &Path, choice: CheckpointChoice) -> Result<Self> {
        let (checkpoint, run_dir) = if path.join(POLICY_FILE).exists() {
            let run = path.parent().and_then(Path::parent).map(Path::to_path_buf);
            (path.to_path_buf(), run)
        } else if !checkpoints(path).is_empty() || best_checkpoint(path).is_some() {
            (pick_checkpoint(path, choice)?, Some(path.to_path_buf()))
        } else {
            return Err(TrainedAgentError::NotTrained(path.to_path_buf()));
        };
        verify(&checkpoint)?;
        let agent_path = checkpoint.join(AGENT_FILE);
        let text =
            std::fs::read_to_string(&agent_path).map_err(|source| TrainedAgentError::Read {
                path: agent_path.clone(),
                source,
            })?;
        let table: toml::Table =
            toml::from_str(&text).map_err(|source| TrainedAgentError::Parse {
                path: agent_path.clone(),
                source,
            })?;
        let agent =
            AgentConfig::from_saved_table(table).map_err(|source| TrainedAgentError::Agent {
                path: agent_path.clone(),
                source: Box::new(source),
            })?;
        let policy_path = checkpoint.join(POLICY_FILE);
        let weights = std::fs::read(&policy_path).map_err(|source| TrainedAgentError::Read {
            path: policy_path.clone(),
            source,
        })?;
        let experiment = match run_dir.map(|r| r.join(CONFIG_FILE)) {
            Some(p) if p.exists() => Some(ExperimentConfig::load_saved(&p)?),
            _ => None,
        };
        Ok(Self {
            checkpoint,
            agent,
            weights,
            experiment,
        })
    }

    /// The race scenario it was trained in: its run's, else (a checkpoint outside a run) the
    /// default scenario.
    pub fn race(&self) -> RaceConfig {
        self.experiment
            .as_ref()
            .map(|e| e.race.clone())
            .unwrap_or_default()
    }

    /// Values in one of its observations: the LiDAR beams of [`TrainedAgent::race`].
    pub fn obs_dim(&self) -> usize {
        self.race().lidar.beams
    }
}

/// The checkpoint `choice` of the run directory `run`, or an error saying which there are
/// (the intact `best` among them when every `step-*` is damaged).
fn pick_checkpoint(run: &Path, choice: CheckpointChoice) -> Result<PathBuf> {
    let found = match choice {
        CheckpointChoice::Best => best_checkpoint(run),
        CheckpointChoice::Latest => latest_checkpoint(run),
        CheckpointChoice::Step(n) => checkpoints(run)
            .into_iter()
            .find(|c| checkpoint_step(c) == Some(n)),
        CheckpointChoice::BestAt(n) => Some(best_at_dir(run, n)).filter(|d| d.is_dir()),
    };
    found.ok_or_else(|| {
        let steps: Vec<String> = checkpoints(run)
            .iter()
            .filter(|c| verify(c).is_ok())
            .filter_map(|c| checkpoint_step(c))
            .map(|n| CheckpointChoice::Step(n).to_string())
            .collect();
        let best_intact = best_checkpoint(run).is_some_and(|b| verify(&b).is_ok());
        let why = match choice {
            CheckpointChoice::Best => {
                " (the learner saves it when the policy drove a training episode; runs trained \
                 before ctxrace kept it have none)"
            }
            CheckpointChoice::BestAt(_) => {
                " (kept only at the env steps of the run's [train] keep_best_at, once the \
                 policy had driven a training episode)"
            }
            CheckpointChoice::Latest if !checkpoints(run).is_empty() => {
                " intact (every step-* checkpoint is damaged; the warnings above say how)"
            }
            _ => "",
        };
        let alternatives: Vec<String> = (best_intact && choice != CheckpointChoice::Best)
            .then(|| "best (intact)".to_string())
            .into_iter()
            .chain((!steps.is_empty() && choice == CheckpointChoice::Best).then(|| "latest".into()))
            .chain(steps)
            .collect();
        TrainedAgentError::Missing {
            run: run.to_path_buf(),
            choice,
            why,
            alternatives,
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checkpoint_choices_read_back_as_they_print() {
        for choice in [
            CheckpointChoice::Best,
            CheckpointChoice::Latest,
            CheckpointChoice::Step(5000),
            CheckpointChoice::BestAt(25_000),
        ] {
            assert_eq!(choice.to_string().parse::<CheckpointChoice>(), Ok(choice));
        }
        for bad in ["step-", "best-at-x", "best-at--1", "last"] {
            let err = bad.parse::<CheckpointChoice>().unwrap_err().to_string();
            assert!(err.contains(bad) && err.contains("best-at-N"), "{err}");
        }
    }
}
