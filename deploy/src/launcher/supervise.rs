//! The supervision loop ([`supervise`]): each tick it (re)starts what is due, reads the
//! telemetry, checks liveness, reaps what exited (restarting what crashed) and shows the
//! progress.

use crate::progress::progress_bar;
use anyhow::Result;
use ctxrace_config::validate::Causes;
use ctxrace_config::{ExperimentConfig, SupervisorConfig};
use ctxrace_ipc::{
    termination_flag, IpcError, RunBounds, RunTransport, TelemetrySubscriber, WeightsReceiver,
};
use ctxrace_learner::runlog::{EpisodeLog, RateMeter};
use ctxrace_run::results::ReplayStreams;
use ctxrace_run::run_dir::ACTOR_REPORTS;
use indicatif::ProgressBar;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use super::children::{Children, Supervised};
use super::cleanup::DeadNodeCleaner;
use super::liveness::Liveness;
use super::progress::{replay_streams, Progress, RestartCosts};
use super::stalls::Stalls;
use super::status::write_status;
use super::summary::RunEnd;

/// What the supervision loop leaves for the run's last status and closing line.
pub(super) struct Supervision {
    /// The run's figures as the loop last saw them.
    pub(super) p: Progress,
    /// What restarts cost the run.
    pub(super) costs: RestartCosts,
    /// The longest pauses it saw.
    pub(super) stalls: Stalls,
    /// How it ended: complete, interrupted, or the error that stopped it.
    pub(super) end: Result<RunEnd>,
}

/// The supervision loop, until the run is complete, interrupted or stopped by an error.
pub(super) fn supervise(
    cfg: &ExperimentConfig,
    dir: &Path,
    transport: &RunTransport,
    children: &mut Children,
) -> Supervision {
    let actors = children.actors.len();
    let mut s = match Supervisor::new(cfg, dir, transport, actors) {
        Ok(s) => s,
        Err(e) => {
            return Supervision {
                p: Progress::new(actors),
                costs: RestartCosts::default(),
                stalls: Stalls::new(actors),
                end: Err(e),
            }
        }
    };
    let end = watch(&mut s, children);
    Supervision {
        costs: s.p.restart_costs(),
        stalls: s.liveness.stalls.clone(),
        p: s.p,
        end,
    }
}

/// Ticks `s` over `children` until the run is complete or interrupted.
fn watch(s: &mut Supervisor<'_>, children: &mut Children) -> Result<RunEnd> {
    let stop = termination_flag()?;
    loop {
        std::thread::sleep(Duration::from_millis(100));
        if stop.load(Ordering::Relaxed) {
            s.bar
                .abandon_with_message("interrupted: stopping (checkpoint, snapshot)");
            return Ok(RunEnd::Interrupted);
        }
        s.start_due(children)?;
        s.read_telemetry(children)?;
        s.read_replay_streams(&children.replay);
        s.check_liveness(children);
        if s.reap(children)? {
            return Ok(RunEnd::Trained);
        }
        s.show()?;
    }
}

/// The value of a telemetry read, or `None` with a warning (the error and its causes).
fn tolerate<T>(read: Result<T, IpcError>) -> Option<T> {
    read.map_err(|e| tracing::warn!("telemetry: {}", Causes(&e)))
        .ok()
}

/// What the supervision loop reads, shows and remembers from tick to tick.
struct Supervisor<'a> {
    /// `[supervisor]`: restarts and timeouts.
    cfg: &'a SupervisorConfig,
    /// The run directory.
    dir: &'a Path,
    /// The run's env-step budget.
    budget: u64,
    telemetry: TelemetrySubscriber,
    weights: WeightsReceiver,
    /// The training episodes and rates written.
    episodes: EpisodeLog,
    meter: RateMeter,
    bar: ProgressBar,
    /// When supervision started.
    start: Instant,
    p: Progress,
    liveness: Liveness,
    cleaner: DeadNodeCleaner,
    /// The replay's per-actor counts, read once a second.
    replay_took: ReplayStreams,
    last_streams: Instant,
    last_status: Instant,
    /// When the bar last moved.
    tick: Instant,
}

impl<'a> Supervisor<'a> {
    /// The supervision of the run of `cfg` in `dir` with `actors` actors, on `transport`.
    fn new(
        cfg: &'a ExperimentConfig,
        dir: &'a Path,
        transport: &RunTransport,
        actors: usize,
    ) -> Result<Self> {
        let telemetry = TelemetrySubscriber::new(transport, RunBounds::of(cfg, actors))?;
        let plan = cfg.plan();
        let weights = WeightsReceiver::new(transport, plan.gradient_steps)?;
        let episodes = EpisodeLog::open(dir, "launcher")?;
        let bar = progress_bar(plan.env_steps, "env steps");
        Ok(Self {
            cfg: &cfg.supervisor,
            dir,
            budget: plan.env_steps,
            telemetry,
            weights,
            episodes,
            meter: RateMeter::default(),
            bar,
            start: Instant::now(),
            p: Progress::new(actors),
            liveness: Liveness::new(&cfg.supervisor, plan.replay.min_fill as u64, actors),
            cleaner: DeadNodeCleaner::new(transport.prefix()),
            replay_took: ReplayStreams::default(),
            last_streams: Instant::now(),
            last_status: Instant::now(),
            tick: Instant::now(),
        })
    }

    /// (Re)starts what is due; the telemetry of a start is checked against its own history.
    fn start_due(&mut self, children: &mut Children) -> Result<()> {
        if children.replay.start_if_due()? {
            self.telemetry.replay_started(children.replay.pid());
        }
        children.learner.start_if_due()?;
        for (id, actor) in children.actors.iter_mut().enumerate() {
            if actor.start_if_due()? {
                self.telemetry.actor_started(id, actor.pid());
                self.liveness.actor_started(id);
            }
        }
        Ok(())
    }

    /// Reads the telemetry, best effort (a dying peer must not take the launcher down): the
    /// heartbeats, the weights version, the replay's status, the rejections and the episodes,
    /// which it writes as rows of the training episodes.
    fn read_telemetry(&mut self, children: &mut Children) -> Result<()> {
        self.read_heartbeats(&mut children.actors);
        if let Some(s) = tolerate(self.telemetry.replay_status()).flatten() {
            children.replay.last_sign = Some(Instant::now());
            self.p.replay_status(s);
        }
        self.p.telemetry_rejected = self.telemetry.rejected();
        self.p.telemetry_rejected_by_reason = self.telemetry.rejected_by_reason();
        self.p.weights_rejected = self.weights.rejected();
        for e in tolerate(self.telemetry.episodes()).unwrap_or_default() {
            let row = self.p.episode(&e, self.budget);
            self.episodes.write(&row)?;
        }
        Ok(())
    }

    /// Reads the actors' heartbeats, each a sign of life of its actor; the weights are read
    /// after them, since their policy versions must not be ahead of them.
    fn read_heartbeats(&mut self, actors: &mut [Supervised]) {
        let beats = self.telemetry.heartbeats(|| {
            self.p
                .weights(tolerate(self.weights.latest_with(|v, _| v)).flatten())
        });
        for hb in tolerate(beats).unwrap_or_default() {
            self.p.heartbeat(&hb);
            if let Some(a) = actors.get_mut(hb.actor_id as usize) {
                a.last_sign = Some(Instant::now());
            }
        }
    }

    /// Reads the replay's per-actor counts once a second; a replay's file from before its
    /// restart counts its old start: none until it writes.
    fn read_replay_streams(&mut self, replay: &Supervised) {
        if self.last_streams.elapsed() >= Duration::from_secs(1) {
            self.replay_took = replay
                .last_sign
                .map_or(ReplayStreams::default(), |_| replay_streams(self.dir));
            self.last_streams = Instant::now();
        }
    }

    /// Kills what is hung or stalled ([`Liveness::check`]).
    fn check_liveness(&mut self, children: &mut Children) {
        self.liveness
            .check(children, &self.p, &self.replay_took, self.dir);
    }

    /// Reaps what exited: a crash is counted (what it cost the run) and restarted with
    /// back-off, and the crashed nodes are cleaned up so that their peers stop waiting for
    /// them; a learner that finished ends the run ([`Supervisor::finish`]). Returns whether the
    /// run ended.
    fn reap(&mut self, children: &mut Children) -> Result<bool> {
        let mut crashed = false;
        for (id, proc) in children.actors.iter_mut().enumerate() {
            if let Some(status) = proc.reap()? {
                if !proc.retired {
                    let report = format!("actor-{id}-{}.json", proc.incarnation());
                    let reported = self.dir.join(ACTOR_REPORTS).join(report).exists();
                    self.p.actor_died(id, reported);
                    proc.exited(status, self.cfg)?;
                    crashed = true;
                }
            }
        }
        let replay = &mut children.replay;
        if let Some(status) = replay.reap()? {
            if !replay.retired {
                self.p
                    .replay_crashed(tolerate(self.telemetry.replay_status()).flatten());
                replay.exited(status, self.cfg)?;
                crashed = true;
            }
        }
        let learner = &mut children.learner;
        if let Some(status) = learner.reap()? {
            if status.success() {
                self.finish()?;
                return Ok(true);
            }
            self.p
                .learner_died(ctxrace_learner::process::resume_step(self.dir));
            learner.exited(status, self.cfg)?;
            crashed = true;
        }
        if crashed {
            self.cleaner.request();
        }
        self.cleaner.poll();
        Ok(false)
    }

    /// Ends the bar at the run's last figures and writes its last status file.
    fn finish(&mut self) -> Result<()> {
        self.bar.set_position(self.p.env_steps.min(self.budget));
        self.bar.finish_with_message(self.p.message(self.start));
        write_status(self.dir, &self.p, &self.replay_took, &self.liveness.stalls)
    }

    /// Writes the status file once a second; moves the bar on and writes the rates every
    /// 250 ms.
    fn show(&mut self) -> Result<()> {
        if self.last_status.elapsed() >= Duration::from_secs(1) {
            write_status(self.dir, &self.p, &self.replay_took, &self.liveness.stalls)?;
            self.last_status = Instant::now();
        }
        if self.tick.elapsed() >= Duration::from_millis(250) {
            let p = &self.p;
            self.bar.set_position(p.env_steps.min(self.budget));
            self.bar.set_message(p.message(self.start));
            self.tick = Instant::now();
            if let Some(rates) = self
                .meter
                .read(p.env_steps, p.grad_steps, (p.fill, p.capacity))
            {
                self.episodes.rates(p.env_steps, &rates)?;
            }
        }
        Ok(())
    }
}
