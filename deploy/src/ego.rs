//! Who drives the ego in `race`, `eval`, `track check` and the first look: a reference policy,
//! a trained agent loaded from a checkpoint (`ctxrace_run::trained`) or a policy trained
//! elsewhere (an MLP file, `ctxrace_nn::policy::mlp`), turned into the actor's episode driver
//! ([`Driver`]).

use anyhow::{Context as _, Result};
use ctxrace_actor::driver::Driver;
use ctxrace_nn::Policy;
use ctxrace_run::trained::{CheckpointChoice, TrainedAgent};
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::ActMode;
use ctxrace_sim::RaceEnv;
use std::path::{Path, PathBuf};

/// What drives the ego.
#[derive(Clone, Debug)]
pub enum EgoSpec {
    /// A reference policy.
    Baseline(BaselineKind),
    /// A trained agent.
    Trained(Box<TrainedAgent>),
    /// A policy trained elsewhere: the MLP file and its bytes.
    Mlp(PathBuf, Vec<u8>),
}

impl EgoSpec {
    /// The policy at `path`: an MLP policy file (`*.safetensors`), else a trained agent's
    /// checkpoint or run folder (its checkpoint `choice`).
    pub fn load(path: &Path, choice: CheckpointChoice) -> Result<Self> {
        if ctxrace_nn::policy::mlp::is_mlp_file(path) {
            let bytes = ctxrace_nn::policy::mlp::read_mlp_file(path)
                .with_context(|| format!("reading {}", path.display()))?;
            return Ok(EgoSpec::Mlp(path.to_path_buf(), bytes));
        }
        Ok(EgoSpec::Trained(Box::new(TrainedAgent::load(
            path, choice,
        )?)))
    }

    /// The name reports group by: the algorithm, the baseline, or the MLP file's stem.
    pub fn name(&self) -> String {
        match self {
            EgoSpec::Baseline(kind) => kind.name().into(),
            EgoSpec::Trained(t) => t.agent.algo.name().into(),
            EgoSpec::Mlp(path, _) => path
                .file_stem()
                .map_or("mlp".into(), |s| s.to_string_lossy().into_owned()),
        }
    }

    /// The trained agent's or MLP file's path, or the baseline's name: how an evaluation's
    /// workers and records name the ego.
    pub fn source(&self) -> String {
        match self {
            EgoSpec::Trained(t) => t.checkpoint.display().to_string(),
            EgoSpec::Mlp(path, _) => path.display().to_string(),
            EgoSpec::Baseline(_) => self.name(),
        }
    }

    /// A driver for `env`'s episodes; a trained agent acts by `act`.
    pub fn driver(&self, env: &RaceEnv, act: ActMode) -> Result<Driver> {
        Ok(match self {
            EgoSpec::Baseline(kind) => Driver::baseline(*kind, env),
            EgoSpec::Trained(t) => {
                Driver::agent(&t.agent, &t.weights, env, act).with_context(|| {
                    format!(
                        "the checkpoint {} does not fit this race's observations ({} values)",
                        t.checkpoint.display(),
                        env.obs_dim()
                    )
                })?
            }
            EgoSpec::Mlp(path, bytes) => Driver::policy(
                Policy::mlp(bytes, env.obs_dim())
                    .with_context(|| format!("{} as the ego of this race", path.display()))?,
                act,
            ),
        })
    }
}
