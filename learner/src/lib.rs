//! ctxrace's training algorithms behind one [`Algorithm`] trait, the learner process
//! ([`process`]) and the single-process trainer ([`inline`], which continues exactly from its
//! [`resume`] points), which share one cadence of logs, checkpoints and best policy
//! ([`cadence`]).

pub mod adam;
pub mod algorithm;
mod behaviour;
pub mod best;
pub mod cadence;
#[cfg(test)]
mod candle_sac;
pub mod checkpoint;
pub mod cmask;
pub mod dreamer;
pub mod error;
pub mod inline;
pub mod process;
pub mod resume;
pub mod returns;
pub mod runlog;
pub mod sac;
mod sac_core;
#[cfg(test)]
mod sequences;
pub mod shards;
pub mod tensorboard;
pub mod world_model;

pub use algorithm::{Algorithm, Batch, Metrics};
pub use dreamer::Dreamer;
pub use error::{LearnerError, Result};
pub use sac::Sac;

use ctxrace_config::agents::{AgentConfig, AlgoKind};
use ctxrace_nn::policy::ACT_DIM;

/// A fresh agent of `agent.algo` for LiDAR frames of `frame_dim` values (SAC stacks
/// `agent.sac.frames` of them) and the racing actions (steering, speed). A DreamerV3 variant
/// splits each batch over `workers` threads ([`Dreamer::set_workers`]); SAC steps on the
/// calling thread.
pub fn build(agent: &AgentConfig, frame_dim: usize, workers: usize) -> Result<Box<dyn Algorithm>> {
    agent.validate()?;
    Ok(match agent.algo {
        AlgoKind::Sac => Box::new(Sac::new(
            frame_dim * agent.sac.frames,
            ACT_DIM,
            agent.sac.clone(),
        )?),
        AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => {
            let mut dreamer = Dreamer::new(agent.dreamer(), frame_dim, ACT_DIM)?;
            dreamer.set_workers(workers);
            Box::new(dreamer)
        }
    })
}
