//! The actor process (`ctxrace actor`): runs [`Collector`] episodes against the run's replay,
//! acting with the newest policy weights the learner broadcast (uniform random actions until
//! the first weights and for its share of the prefill), and publishes episode metrics and a
//! heartbeat.
//!
//! New weights are taken before every decision, mid-episode too (every step carries the
//! version that chose it), and while the actor waits for the replay to take its chunks. The
//! replay takes from the actor with the fewest steps taken first, so an actor that got ahead
//! at the start (it filled its queue while the other was starting) waits, blocked, until the
//! others catch up: hundreds of gradient steps. When weights were loaded only at episode
//! boundaries, which a blocked actor does not reach, it came back from that wait with its first
//! weights (`versions` `[0, 470, ...]` beside `[0, 10, 30, ...]`), or none.

use crate::collect::{CollectError, Collector};
use ctxrace_config::validate::Causes;
use ctxrace_config::ExperimentConfig;
use ctxrace_ipc::{
    termination_flag, Heartbeat, IpcError, MetricsPublisher, RunTransport, SenderOptions,
    TrajectorySender, WeightsReceiver,
};
use ctxrace_nn::policy::ACT_DIM;
use ctxrace_nn::Policy;
use ctxrace_sim::race::RaceEnv;
use ctxrace_sim::RaceError;
use ctxrace_tracks::Track;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Seconds between heartbeats.
const HEARTBEAT_EVERY: Duration = Duration::from_secs(1);

/// Why the actor process stopped on an error.
#[derive(Debug, thiserror::Error)]
pub enum ActorError {
    /// The race could not be set up from the experiment.
    #[error(transparent)]
    Race(#[from] RaceError),
    /// The trajectory stream to the replay could not be opened.
    #[error("connecting to the replay")]
    Connect(#[source] IpcError),
    /// The transport failed.
    #[error(transparent)]
    Ipc(#[from] IpcError),
    /// A decision could not be taken.
    #[error(transparent)]
    Collect(#[from] CollectError),
}

/// What an actor process needs.
pub struct ActorOptions {
    /// The run's iceoryx2 prefix.
    pub prefix: String,
    /// The run's key, which seals and checks every message.
    pub key: ctxrace_ipc::RunKey,
    /// This actor's id, `0..actors`.
    pub id: u32,
    /// Actors in the run.
    pub actors: usize,
    /// How many times this actor was started before (restarts draw fresh episodes).
    pub incarnation: u64,
    /// The experiment.
    pub experiment: ExperimentConfig,
    /// The track.
    pub track: Arc<Track>,
}

/// What an actor did, reported when it stops.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct ActorReport {
    /// The actor's id.
    pub id: u32,
    /// Its earlier starts.
    pub incarnation: u64,
    /// Decisions taken.
    pub decisions: u64,
    /// Steps delivered to the replay.
    pub sent_steps: u64,
    /// Steps dropped (still waiting for the replay when the actor stopped).
    pub dropped_steps: u64,
    /// Weights broadcasts refused (bad version, length or checksum, or not this agent's).
    pub weights_rejected: u64,
    /// Policy versions loaded, in order.
    pub versions: Vec<u64>,
}

/// Runs the actor until SIGTERM/SIGINT.
pub fn run(opts: ActorOptions) -> Result<ActorReport, ActorError> {
    let cfg = &opts.experiment;
    let env = RaceEnv::new(opts.track.clone(), cfg.race.clone())?;
    let frame_dim = env.obs_dim();
    let seed = cfg
        .train
        .seed
        .wrapping_add(1 + opts.id as u64)
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(opts.incarnation);
    let mut collector = Collector::for_experiment(env, cfg, seed);
    let role = format!("actor-{}", opts.id);
    let transport = RunTransport::open(&opts.prefix, opts.actors, &role, &opts.key)?;
    let mut weights = WeightsReceiver::new(&transport, cfg.plan().gradient_steps)?;
    let telemetry = MetricsPublisher::new(&transport)?;
    let mut sender = TrajectorySender::new(
        &transport,
        opts.id,
        frame_dim,
        ACT_DIM,
        SenderOptions::default(),
    )
    .map_err(ActorError::Connect)?;
    let prefill = cfg.train.prefill / opts.actors.max(1) as u64;
    let mut policy: Option<(u64, Policy)> = None;
    let mut last_beat = Instant::now() - HEARTBEAT_EVERY;
    let mut versions = Vec::new();
    let mut weights_refused = 0;
    let mut telemetry_failed = 0u64;
    let stop = termination_flag()?;
    while !stop.load(Ordering::Relaxed) {
        if last_beat.elapsed() >= HEARTBEAT_EVERY {
            let beat = telemetry.heartbeat(Heartbeat {
                actor_id: opts.id,
                pid: std::process::id(),
                env_steps: collector.decisions(),
                policy_version: policy.as_ref().map_or(0, |(v, _)| *v),
                dropped_steps: sender.stats().dropped_steps,
                ..Default::default()
            });
            advisory(beat, "heartbeat", opts.id, &mut telemetry_failed);
            last_beat = Instant::now();
        }
        // newest weights first, also while we wait below
        let newest = weights.latest_with(|version, bytes| {
            match &mut policy {
                Some((v, p)) => p.load(bytes).map(|_| *v = version),
                None => Policy::new(&cfg.agent, frame_dim, bytes, seed)
                    .map(|p| policy = Some((version, p))),
            }
            .map(|_| version)
        })?;
        match newest {
            Some(Ok(version)) => versions.push(version),
            Some(Err(e)) => {
                weights_refused += 1;
                tracing::warn!("actor {}: weights rejected: {e}", opts.id)
            }
            None => {}
        }
        // the replay has no room for our chunks (its rate limiter paces the actors to the
        // learner, or it restarts): wait for it instead of stepping, so that nothing is dropped
        if sender.backlog() > 0 {
            match sender.deliver(Duration::from_millis(100)) {
                // a signal can interrupt the wait
                Err(_) if stop.load(Ordering::Relaxed) => break,
                result => result?,
            };
            continue;
        }
        let version = policy.as_ref().map_or(0, |(v, _)| *v);
        let acting = match &mut policy {
            Some((_, p)) if collector.decisions() >= prefill => Some(p),
            _ => None,
        };
        // the episode this decision belongs to (a new one starts at a boundary)
        let episode = collector.episodes() - u64::from(!collector.at_episode_boundary());
        let mut push_error = Ok(());
        let finished = collector.step(acting, |s| {
            if push_error.is_ok() {
                push_error = sender.push(episode, version, s);
            }
        })?;
        if let Err(e) = push_error {
            // a signal can interrupt a send; anything else is a real failure
            if stop.load(Ordering::Relaxed) {
                break;
            }
            return Err(e.into());
        }
        if let Some(f) = finished {
            let m = &f.metrics;
            let report = telemetry.episode(ctxrace_ipc::EpisodeReport {
                actor_id: opts.id,
                episode_id: f.episode,
                env_steps: collector.decisions(),
                steps: m.steps as u64,
                context: [f.context.speed as f32, f.context.steer as f32],
                progress: m.progress as f32,
                overtakes: m.overtakes,
                a2a: m.a2a as u32,
                wall_crash: m.wall_crash as u32,
                episode_return: m.episode_return as f32,
                by_policy: u32::from(f.by_policy),
                ..Default::default()
            });
            advisory(report, "episode report", opts.id, &mut telemetry_failed);
        }
    }
    // a send interrupted by the stop signal fails; what was delivered before still counts
    let before = sender.stats();
    let stats = sender.close().unwrap_or_else(|e| {
        tracing::warn!(
            "actor {}: closing the trajectory stream: {}",
            opts.id,
            Causes(&e)
        );
        before
    });
    tracing::info!(
        "actor {} stopping: {} steps sent, {} dropped",
        opts.id,
        stats.sent_steps,
        stats.dropped_steps
    );
    Ok(ActorReport {
        id: opts.id,
        incarnation: opts.incarnation,
        decisions: collector.decisions(),
        sent_steps: stats.sent_steps,
        dropped_steps: stats.dropped_steps,
        weights_rejected: weights.rejected() + weights_refused,
        versions,
    })
}

/// Telemetry is advisory: a heartbeat or an episode report that cannot be sent (iceoryx2 could
/// not loan a sample: `LoanError(OutOfMemory)` when its segment was written over) is logged,
/// the first and every 100th, and the actor races on. An actor whose heartbeats keep failing
/// falls silent, and the launcher restarts it after the heartbeat timeout, with fresh ports.
fn advisory(sent: Result<(), ctxrace_ipc::IpcError>, what: &str, actor: u32, failed: &mut u64) {
    if let Err(e) = sent {
        *failed += 1;
        if *failed % 100 == 1 {
            tracing::warn!(
                "actor {actor}: sending a {what}: {} ({} telemetry messages not sent so far)",
                Causes(&e),
                failed
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A telemetry message that cannot be sent is counted, not returned: the actor races on.
    #[test]
    fn telemetry_that_cannot_be_sent_is_counted_not_fatal() {
        let mut failed = 0;
        advisory(Ok(()), "heartbeat", 0, &mut failed);
        assert_eq!(failed, 0);
        for _ in 0..3 {
            advisory(
                Err(ctxrace_ipc::IpcError::NoActors),
                "heartbeat",
                0,
                &mut failed,
            );
        }
        assert_eq!(failed, 3);
    }
}
