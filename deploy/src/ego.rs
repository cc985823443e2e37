//! Who drives the ego in `race`, `eval`, `track check` and the first look: a reference policy
//! or a trained agent loaded from a checkpoint (`ctxrace_run::trained`), turned into the
//! actor's episode driver ([`Driver`]).

use anyhow::{Context as _, Result};
use ctxrace_actor::driver::Driver;
use ctxrace_run::trained::TrainedAgent;
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::ActMode;
use ctxrace_sim::RaceEnv;

/// What drives the ego.
#[derive(Clone, Debug)]
pub enum EgoSpec {
    /// A reference policy.
    Baseline(BaselineKind),
    /// A trained agent.
    Trained(Box<TrainedAgent>),
}

impl EgoSpec {
    /// The name reports group by: the algorithm or the baseline.
    pub fn name(&self) -> String {
        match self {
            EgoSpec::Baseline(kind) => kind.name().into(),
            EgoSpec::Trained(t) => t.agent.algo.name().into(),
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
        })
    }
}
