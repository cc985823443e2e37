//! The single-process trainer (`ctxrace train --inline`): an experience source, a sample store
//! and the learner in one loop, for development, tests and notebooks. It writes the run
//! directory the learner process and the launcher write (`episodes.csv`, the metrics, the
//! checkpoints and the best policy, by [`crate::cadence`]) and reports its progress to the
//! caller, which may show it.
//!
//! The source and the store are the traits of [`ctxrace_run::experience`]: the caller builds
//! them (the actor's `Collector` on a race, the replay's `ReplayBuffer` in memory) and passes
//! them in, so that the learner depends on the common crate only.

use crate::best::ReturnTracker;
use crate::cadence::{Cadence, CadenceError};
use crate::resume::{self, LoopState};
use crate::runlog::{EpisodeLog, LogError, RateMeter};
use crate::LearnerError;
use ctxrace_config::ExperimentConfig;
use ctxrace_nn::policy::{PolicyError, ACT_DIM};
use ctxrace_nn::Policy;
use ctxrace_run::experience::{ExperienceSource, SampleStore};
use ctxrace_run::results::TrainingMask;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Episodes whose mean progress [`InlineProgress::recent_progress`] reports.
const RECENT: usize = 10;

/// Why a single-process run stopped on an error; `E` is its experience source's error.
#[derive(Debug, thiserror::Error)]
pub enum InlineError<E> {
    /// The sample store was built for other steps than the source makes.
    #[error(
        "the sample store holds steps of {store_obs} observation and {store_act} action \
         values, the experience source makes {source_obs} and {source_act}: build the store \
         for the source's observation"
    )]
    StoreSizes {
        /// The store's observation size.
        store_obs: usize,
        /// The store's action size.
        store_act: usize,
        /// The source's observation size.
        source_obs: usize,
        /// The source's action size.
        source_act: usize,
    },
    /// The agent could not be built, or a training step failed.
    #[error(transparent)]
    Learner(#[from] LearnerError),
    /// The acting policy could not be built or reloaded.
    #[error(transparent)]
    Policy(#[from] PolicyError),
    /// The training episodes could not be logged.
    #[error(transparent)]
    Log(#[from] LogError),
    /// The metrics, a checkpoint or the best policy could not be written.
    #[error(transparent)]
    Cadence(#[from] CadenceError),
    /// The experience source could not take a decision.
    #[error(transparent)]
    Source(E),
}

/// Where a single-process run stands (after each decision and at its end).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InlineProgress {
    /// Decisions (environment steps) taken.
    pub decisions: u64,
    /// Gradient steps taken.
    pub grad_steps: u64,
    /// Training episodes started (the running one included).
    pub episodes: u64,
    /// Mean progress (PG) of the last 10 episodes, 0 before the first.
    pub recent_progress: f64,
    /// Time since the loop started.
    pub elapsed: Duration,
}

/// A finished single-process run.
#[derive(Clone, Debug, PartialEq)]
pub struct InlineRun {
    /// Where it ended.
    pub progress: InlineProgress,
    /// Its last checkpoint.
    pub checkpoint: PathBuf,
}

/// Trains `cfg`'s agent into the run directory `dir` in one loop on the experience of `source`,
/// kept in `store` (its stream 0). After the warm-up (`prefill` random steps, or with
/// `[agent] warmup = "episodes"` `warmup_episodes` episodes of the untrained policy) it keeps
/// the gradient steps at `train_ratio` per env step (with random steps as many in all as
/// the run plan's [`ctxrace_config::RunPlan::gradient_steps`]), drawing batches with `[agent] sampler`, reloads the
/// acting policy at the first episode boundary after every `policy_every` gradient steps, logs
/// and checkpoints. `on_decision` sees the progress after every decision.
///
/// A run reproduces from `cfg`'s seed when `source` is as `cfg` asks (the actor's
/// `Collector::for_experiment` with `[train] seed`) and `store` is new (`[replay] capacity`,
/// one stream). A store whose steps are not the source's fails before the first step.
pub fn run_inline<S: ExperienceSource<Policy = Policy>, B: SampleStore>(
    cfg: &ExperimentConfig,
    dir: &Path,
    source: &mut S,
    store: &mut B,
    mut on_decision: impl FnMut(&InlineProgress),
) -> Result<InlineRun, InlineError<S::Error>> {
    let t = &cfg.train;
    let plan = cfg.plan();
    let frame_dim = source.obs_dim();
    if (store.obs_dim(), store.act_dim()) != (frame_dim, ACT_DIM) {
        return Err(InlineError::StoreSizes {
            store_obs: store.obs_dim(),
            store_act: store.act_dim(),
            source_obs: frame_dim,
            source_act: ACT_DIM,
        });
    }
    let workers = t.threads_for(cfg.agent.algo);
    let mut algo = crate::build(&cfg.agent, frame_dim, workers)?;
    algo.set_diagnostics_every(t.log_every);
    let mut acting_weights = algo.policy_weights()?;
    let mut policy = Policy::new(&cfg.agent, frame_dim, &acting_weights, t.seed)?;
    let mut rng = ChaCha8Rng::seed_from_u64(t.seed ^ 0x7265_706c_6179);
    let (mut stale_policy, mut recent) = (false, Vec::<f64>::new());
    let mut trained_after = None;
    let mut tracker = ReturnTracker::default();
    // a resume point puts everything back where it was taken, the logs before they are opened
    if let Some(point) = resume::find(dir).map_err(CadenceError::from)? {
        point
            .restore(dir, algo.as_mut(), store)
            .map_err(CadenceError::from)?;
        source.restore(&point.state.source);
        rng.set_word_pos(point.state.sampler_rng_words);
        policy.load(&point.acting_weights)?;
        policy.carry(&point.state.policy);
        acting_weights = point.acting_weights;
        (stale_policy, recent) = (point.state.stale_policy, point.state.recent);
        trained_after = point.state.trained_after;
        tracker = point.tracker;
    }
    let spec = cfg.agent.batch_spec();
    let mut episodes = EpisodeLog::open(dir, "inline")?;
    let mut cadence = Cadence::open(dir, cfg, "inline-learner", tracker)?;
    let mut meter = RateMeter::default();
    let start = Instant::now();
    let mut last_point = Instant::now();
    let mut payload = Vec::new();
    let progress = |source: &S, grad_steps: u64, recent: &[f64]| InlineProgress {
        decisions: source.decisions(),
        grad_steps,
        episodes: source.episodes(),
        recent_progress: if recent.is_empty() {
            0.0
        } else {
            recent.iter().sum::<f64>() / recent.len() as f64
        },
        elapsed: start.elapsed(),
    };
    while source.decisions() < plan.env_steps {
        payload.clear();
        let by_policy = cfg.acts_by_policy(source.decisions());
        let acting = if by_policy { Some(&mut policy) } else { None };
        let finished = source
            .step(acting, &mut |s| s.encode(&mut payload))
            .map_err(InlineError::Source)?;
        store.insert_chunk(0, &payload, false);
        if let Some(f) = finished {
            let row = f.row(0, source.decisions(), algo.steps());
            episodes.write(&row)?;
            if let Some((mean, decisions)) = f.mean_mask {
                episodes.write_mask(&TrainingMask {
                    env_steps: row.env_steps,
                    grad_steps: row.grad_steps,
                    episode: row.episode,
                    context_speed: row.context_speed,
                    context_steer: row.context_steer,
                    mask_speed: mean[0],
                    mask_steer: mean[1],
                    decisions,
                })?;
            }
            recent.push(row.progress);
            if recent.len() > RECENT {
                recent.remove(0);
            }
            let policy_return = f.by_policy.then_some(f.record.episode_return);
            cadence.observe_returns(algo.as_ref(), policy_return)?;
        }
        cadence.env_steps_taken(source.decisions())?;
        if trained_after.is_none() {
            trained_after = cfg.warmup_end(source.decisions(), source.episodes());
        }
        if let Some(after) = trained_after {
            let due = plan.gradient_steps_due(source.decisions(), after);
            while algo.steps() < due {
                let Some(batch) = store.sample(spec, plan.replay.sampler, &mut rng) else {
                    break;
                };
                let metrics = algo.train_step(&batch)?;
                let env_steps = Some(source.decisions());
                stale_policy |= cadence.after_step(algo.as_ref(), metrics, env_steps)?;
            }
            if stale_policy && source.at_episode_boundary() {
                acting_weights = algo.policy_weights()?;
                policy.load(&acting_weights)?;
                stale_policy = false;
            }
        }
        // at an episode boundary only: the clock is read once an episode, not every decision
        let due = |since: Instant| since.elapsed().as_secs() >= t.resume_every_secs;
        if let Some(position) = source.position().filter(|_| due(last_point)) {
            let state = LoopState {
                source: position,
                sampler_rng_words: rng.get_word_pos(),
                policy: policy.carried(),
                stale_policy,
                trained_after,
                recent: recent.clone(),
            };
            let tracker = cadence.tracker();
            resume::write(
                dir,
                &state,
                algo.as_ref(),
                &acting_weights,
                &*store,
                tracker,
            )
            .map_err(CadenceError::from)?;
            last_point = Instant::now();
        }
        if source.decisions().is_multiple_of(50) {
            let held = (store.len() as u64, store.capacity() as u64);
            if let Some(rates) = meter.read(source.decisions(), algo.steps(), held) {
                episodes.rates(source.decisions(), &rates)?;
            }
        }
        on_decision(&progress(source, algo.steps(), &recent));
    }
    let checkpoint = cadence.finish(algo.as_ref())?;
    resume::remove(dir).map_err(CadenceError::from)?;
    Ok(InlineRun {
        progress: progress(source, algo.steps(), &recent),
        checkpoint,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::process::is_trained;
    use ctxrace_actor::collect::Collector;
    use ctxrace_actor::driver::Driver;
    use ctxrace_config::{AgentConfig, AlgoKind, Context, DreamerConfig, RaceConfig};
    use ctxrace_replay::ReplayBuffer;
    use ctxrace_run::results::{read_csv, TrainingEpisode};
    use ctxrace_run::run_dir::{METRICS_JSONL, TRAINING_EPISODES};
    use ctxrace_run::trained::{CheckpointChoice, TrainedAgent};
    use ctxrace_sim::driver::ActMode;
    use ctxrace_sim::evaluation::{episode_seed, run_episode};
    use ctxrace_sim::RaceEnv;
    use ctxrace_tracks::{Track, TrackOptions};
    use std::sync::Arc;

    /// A cMask run of 300 decisions on tiny networks (as the CLI tests' `train --inline`).
    const TINY_CMASK: &str = include_str!("../../testdata/tiny-cmask.toml");

    fn env(cfg: &ExperimentConfig) -> RaceEnv {
        let track = Arc::new(Track::load(&cfg.track, &TrackOptions::default()).unwrap());
        RaceEnv::new(track, cfg.race.clone()).unwrap()
    }

    #[test]
    fn a_program_trains_evaluates_and_reads_results_without_the_command_line() {
        let cfg = ExperimentConfig::from_toml(TINY_CMASK, "tiny").unwrap();
        let dir = tempfile::tempdir().unwrap();
        // the program composes the run: the actor's collector, the replay's buffer in memory
        let race = env(&cfg);
        let frame_dim = race.obs_dim();
        let mut collector = Collector::for_experiment(race, &cfg, cfg.train.seed);
        let mut buffer = ReplayBuffer::new(cfg.plan().replay.capacity, 1, frame_dim, ACT_DIM);
        let mut seen = 0;
        let run = run_inline(&cfg, dir.path(), &mut collector, &mut buffer, |p| {
            seen += 1;
            assert_eq!(p.decisions, seen);
        })
        .unwrap();
        assert_eq!(buffer.inserted(), 300 + run.progress.episodes);
        assert_eq!(seen, 300);
        assert_eq!(run.progress.decisions, 300);
        assert_eq!(run.progress.grad_steps, 10);
        assert!(is_trained(dir.path(), &cfg));
        assert!(run.checkpoint.ends_with("step-0000000010"));
        // the training curve and the metrics rows, read back as `ctxrace report` reads them
        let rows: Vec<TrainingEpisode> = read_csv(&dir.path().join(TRAINING_EPISODES)).unwrap();
        // every episode started but the one running at the end
        assert_eq!(rows.len() as u64, run.progress.episodes - 1);
        assert!(!rows.is_empty());
        assert!(rows.windows(2).all(|w| w[0].env_steps < w[1].env_steps));
        assert!(rows
            .iter()
            .all(|r| r.env_steps <= 300 && r.grad_steps <= 10));
        let metrics = std::fs::read_to_string(dir.path().join(METRICS_JSONL)).unwrap();
        assert_eq!(metrics.lines().count(), 5);
        assert!(metrics.lines().all(|l| l.contains("\"env_steps\"")));
        // one evaluation episode of the trained policy, driven as `ctxrace eval` drives it
        let trained = TrainedAgent::load(dir.path(), CheckpointChoice::Latest).unwrap();
        let mut race = env(&cfg);
        let mut driver =
            Driver::agent(&trained.agent, &trained.weights, &race, ActMode::Sample).unwrap();
        let context = Context::default();
        let seed = episode_seed(0, 0, 0);
        let mut decisions = 0;
        let lap = run_episode(&mut race, &mut driver, context, seed, 0, |_, _| {
            decisions += 1
        })
        .unwrap();
        assert_eq!(lap.steps + 1, decisions);
        assert_eq!((lap.seed, lap.context_speed), (seed, 0.0));
    }

    #[test]
    fn a_store_for_another_observation_fails_before_the_first_step() {
        let cfg = ExperimentConfig::from_toml(TINY_CMASK, "tiny").unwrap();
        let dir = tempfile::tempdir().unwrap();
        let race = env(&cfg);
        let frame_dim = race.obs_dim();
        let mut collector = Collector::for_experiment(race, &cfg, 0);
        let mut buffer = ReplayBuffer::new(100, 1, frame_dim + 1, ACT_DIM);
        let err = run_inline(&cfg, dir.path(), &mut collector, &mut buffer, |_| {})
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(&format!("{} observation", frame_dim + 1)) && err.contains("source"),
            "{err}"
        );
        assert_eq!(collector.decisions(), 0);
        assert!(std::fs::read_dir(dir.path()).unwrap().next().is_none());
    }

    #[test]
    fn the_world_model_learns_recorded_race_data() {
        // 2000 decisions of a random ego against one rival on a generated circuit
        let track = Arc::new(Track::load("generated:0", &TrackOptions::default()).unwrap());
        let race = RaceConfig {
            rivals: 1,
            ..RaceConfig::default()
        };
        let env = RaceEnv::new(track, race).unwrap();
        let frame_dim = env.obs_dim();
        let mut collector = Collector::new(env, 0.15, 1);
        let mut buffer = ReplayBuffer::new(10_000, 1, frame_dim, ACT_DIM);
        let mut payload = Vec::new();
        while collector.decisions() < 2000 {
            payload.clear();
            collector.step(None, |s| s.encode(&mut payload)).unwrap();
            buffer.insert_chunk(0, &payload, false);
        }
        let agent = AgentConfig {
            algo: AlgoKind::Dreamerv3,
            dreamer: DreamerConfig {
                units: 64,
                layers: 2,
                deter: 64,
                hidden: 64,
                stoch: 8,
                classes: 8,
                head_units: 64,
                head_layers: 2,
                batch: 8,
                length: 16,
                model_lr: 1e-3,
                ..DreamerConfig::default()
            },
            ..AgentConfig::default()
        };
        let mut algo = crate::build(&agent, frame_dim, 1).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut history = Vec::new();
        for _ in 0..150 {
            let batch = buffer
                .sample(agent.batch_spec(), agent.sampler, &mut rng)
                .unwrap();
            let m = algo.train_step(&batch).unwrap();
            history.push((m["model/recon"], m["model/reward"]));
        }
        let mean = |xs: &[(f64, f64)]| {
            let n = xs.len() as f64;
            let sum = xs.iter().fold((0.0, 0.0), |s, x| (s.0 + x.0, s.1 + x.1));
            (sum.0 / n, sum.1 / n)
        };
        let ((recon0, reward0), (recon1, reward1)) = (mean(&history[..10]), mean(&history[140..]));
        eprintln!("recon {recon0:.3} -> {recon1:.3}, reward {reward0:.3} -> {reward1:.3}");
        assert!(recon1 < 0.5 * recon0, "recon {recon0} -> {recon1}");
        assert!(reward1 < 0.5 * reward0, "reward {reward0} -> {reward1}");
    }
}
