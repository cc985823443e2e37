//! A trained agent read back from its run directory: the checkpoint chosen (best, latest or a
//! given step), verified, with its agent configuration, its policy weights and the run's
//! experiment, for `eval`, `race` and the first look after training.

use crate::best::best_checkpoint;
use crate::checkpoint::{checkpoints, latest_checkpoint, verify};
use anyhow::{bail, Context as _, Result};
use ctxrace_config::{AgentConfig, ExperimentConfig};
use ctxrace_run::run_dir::{AGENT_FILE, CONFIG_FILE, POLICY_FILE};
use std::path::{Path, PathBuf};

/// Which checkpoint of a run directory to load.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CheckpointChoice {
    /// The policy at the peak of the smoothed training return (the paper's `best_`).
    Best,
    /// The newest checkpoint.
    Latest,
    /// The checkpoint after this many gradient steps.
    Step(u64),
}

/// A name that is no [`CheckpointChoice`].
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("'{0}' is not best, latest or step-N (e.g. step-5000)")]
pub struct UnknownCheckpointChoice(pub String);

impl std::str::FromStr for CheckpointChoice {
    type Err = UnknownCheckpointChoice;

    fn from_str(s: &str) -> std::result::Result<Self, UnknownCheckpointChoice> {
        match s {
            "best" => Ok(Self::Best),
            "latest" => Ok(Self::Latest),
            _ => s
                .strip_prefix("step-")
                .and_then(|n| n.parse().ok())
                .map(Self::Step)
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
            bail!(
                "{} is neither a checkpoint (no {POLICY_FILE}) nor a run directory with \
                 checkpoints/step-*; train one with `ctxrace train`",
                path.display()
            );
        };
        verify(&checkpoint)?;
        let agent_path = checkpoint.join(AGENT_FILE);
        let text = std::fs::read_to_string(&agent_path)
            .with_context(|| format!("reading {}", agent_path.display()))?;
        let table: toml::Table =
            toml::from_str(&text).with_context(|| format!("parsing {}", agent_path.display()))?;
        let agent = AgentConfig::from_saved_table(table)
            .map_err(|e| anyhow::anyhow!("{}: {e}", agent_path.display()))?;
        let policy_path = checkpoint.join(POLICY_FILE);
        let weights = std::fs::read(&policy_path)
            .with_context(|| format!("reading {}", policy_path.display()))?;
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
}

/// The checkpoint `choice` of the run directory `run`, or an error saying which there are
/// (the intact `best` among them when every `step-*` is damaged).
fn pick_checkpoint(run: &Path, choice: CheckpointChoice) -> Result<PathBuf> {
    let found = match choice {
        CheckpointChoice::Best => best_checkpoint(run),
        CheckpointChoice::Latest => latest_checkpoint(run),
        CheckpointChoice::Step(n) => checkpoints(run)
            .into_iter()
            .find(|c| c.file_name() == Some(std::ffi::OsStr::new(&format!("step-{n:010}")))),
    };
    found.ok_or_else(|| {
        let steps: Vec<String> = checkpoints(run)
            .iter()
            .filter(|c| verify(c).is_ok())
            .filter_map(|c| {
                c.file_name()?
                    .to_str()?
                    .strip_prefix("step-")?
                    .parse::<u64>()
                    .ok()
            })
            .map(|n| format!("step-{n}"))
            .collect();
        let best_intact = best_checkpoint(run).is_some_and(|b| verify(&b).is_ok());
        let why = match choice {
            CheckpointChoice::Best => {
                " (the learner saves it when the policy drove a training episode; runs trained \
                 before ctxrace kept it have none)"
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
        match alternatives.is_empty() {
            true => anyhow::anyhow!(
                "{} has no {choice} checkpoint{why} and no other intact one; train it again \
                 with `ctxrace train`",
                run.display()
            ),
            false => anyhow::anyhow!(
                "{} has no {choice} checkpoint{why}; pass --checkpoint {}",
                run.display(),
                alternatives.join(" or ")
            ),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::checkpoint::{write_atomically, STATE_FILE};
    use ctxrace_run::run_dir::{BEST_DIR, CHECKPOINTS};

    /// A sealed checkpoint `name` of `run` holding an agent and a policy.
    fn checkpoint(run: &Path, name: &str) -> PathBuf {
        let agent = toml::to_string(&AgentConfig::default()).unwrap();
        write_atomically(&run.join(CHECKPOINTS).join(name), |d| {
            std::fs::write(d.join(STATE_FILE), "step = 1").unwrap();
            std::fs::write(d.join(crate::best::BEST_FILE), "").unwrap();
            std::fs::write(d.join(AGENT_FILE), &agent).unwrap();
            std::fs::write(d.join(POLICY_FILE), name).unwrap();
            Ok(())
        })
        .unwrap()
    }

    #[test]
    fn an_intact_best_is_loaded_and_named_when_every_step_is_damaged() {
        let run = tempfile::tempdir().unwrap();
        for name in ["step-0000000001", "step-0000000002"] {
            let dir = checkpoint(run.path(), name);
            std::fs::write(dir.join(POLICY_FILE), "damaged").unwrap();
        }
        let best = checkpoint(run.path(), BEST_DIR);
        let agent = TrainedAgent::load(run.path(), CheckpointChoice::Best).unwrap();
        assert_eq!(agent.checkpoint, best);
        assert_eq!(agent.weights, BEST_DIR.as_bytes());
        let err = TrainedAgent::load(run.path(), CheckpointChoice::Latest)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("no latest checkpoint intact")
                && err.contains("every step-* checkpoint is damaged")
                && err.contains("pass --checkpoint best (intact)"),
            "{err}"
        );
        // with the best damaged too, nothing is offered
        std::fs::write(best.join(POLICY_FILE), "damaged").unwrap();
        let err = format!(
            "{:#}",
            TrainedAgent::load(run.path(), CheckpointChoice::Best).unwrap_err()
        );
        assert!(err.contains("damaged"), "{err}");
        let err = TrainedAgent::load(run.path(), CheckpointChoice::Latest)
            .unwrap_err()
            .to_string();
        assert!(err.contains("no other intact one"), "{err}");
    }
}
