//! The launcher of `ctxrace train`: starts the replay, the learner and `N` actors as child
//! processes of this binary on a fresh iceoryx2 prefix, shows one progress bar, writes the
//! training episodes, restarts crashed processes with back-off (an actor draws fresh episodes,
//! the learner resumes from its newest checkpoint, the replay from its snapshot), and stops
//! everything cleanly at the end or on Ctrl-C/SIGTERM; finally it removes the run's shared
//! memory. Before it starts, it removes the shared memory of runs whose launcher died
//! ([`sweep_orphaned_runs`]).
//!
//! Each child's tracing output goes to `<run>/logs/<role>.log` (level info unless `RUST_LOG`
//! says otherwise).
//!
//! The replay stores `[train] env_steps` steps and no more (its rate limiter holds the actors to
//! the learner's pace meanwhile; once the budget is stored they wait, idle). The run ends when
//! the learner has taken its gradient steps (it exits by itself; it can be up to `[replay]
//! error_buffer_steps` ahead of the actors, and a replay restart loses the steps after its
//! snapshot: then fewer are stored). Then the actors, the replay and the learner are stopped
//! together: the replay takes the actors' last chunks whatever its limiter says (past the budget
//! as surplus), so that a clean run drops no step.

use crate::progress::progress_bar;
use crate::TrackArgs;
use anyhow::{bail, Context as _, Result};
use ctxrace_config::validate::{Causes, CONFIG_EXIT_CODE};
use ctxrace_config::{ExperimentConfig, SupervisorConfig};
use ctxrace_ipc::wire::{named_reasons, ReplayStatus, REASONS};
use ctxrace_ipc::{
    claim_run, cleanup, remove_dead_nodes, run_prefix, sweep_orphaned_runs, termination_flag,
    CleanupReport, IpcError, RunBounds, RunTransport, TelemetrySubscriber, WeightsReceiver,
    TRAJECTORY_BUFFER,
};
use ctxrace_learner::runlog::{EpisodeLog, RateMeter};
use ctxrace_run::lock::{die_with_parent, DirLock};
use ctxrace_run::results::{read_json, ReplayStreams, TrainingEpisode};
use ctxrace_run::run_dir::{
    open_append, ACTOR_REPORTS, LEARNER_STATUS, LOGS, REPLAY_REPORT, REPLAY_STREAMS, STATUS_FILE,
};
use std::path::Path;
use std::process::{Child, Command, ExitStatus};
use std::sync::atomic::Ordering;
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Longest wait between two restarts of one process.
const MAX_BACKOFF: Duration = Duration::from_secs(30);
/// Time the children get to stop after SIGTERM before they are killed.
const STOP_GRACE: Duration = Duration::from_secs(30);
/// How long a cleanup of dead nodes may take before the supervisor logs it as overrunning.
const CLEANUP_LIMIT: Duration = Duration::from_secs(5);

/// Removes the resources of crashed processes' nodes on a thread of its own: a cleanup that
/// hangs (it sat two minutes on a management segment another user had truncated) must not keep
/// the supervisor from restarting actors or reaping the learner. One cleanup runs at a time; a
/// crash during one asks for another once it ends.
struct DeadNodeCleaner {
    clean: std::sync::Arc<dyn Fn() -> Result<CleanupReport> + Send + Sync>,
    limit: Duration,
    running: Option<(Instant, mpsc::Receiver<Result<CleanupReport>>)>,
    overrun_logged: bool,
    again: bool,
}

impl DeadNodeCleaner {
    /// A cleaner of the dead nodes of the run with `prefix`.
    fn new(prefix: &str) -> Self {
        let prefix = prefix.to_string();
        Self::with(move || Ok(remove_dead_nodes(&prefix)?), CLEANUP_LIMIT)
    }

    /// A cleaner running `clean`, logged as overrunning after `limit`.
    fn with(
        clean: impl Fn() -> Result<CleanupReport> + Send + Sync + 'static,
        limit: Duration,
    ) -> Self {
        Self {
            clean: std::sync::Arc::new(clean),
            limit,
            running: None,
            overrun_logged: false,
            again: false,
        }
    }

    /// Starts a cleanup, or asks for one after the running one.
    fn request(&mut self) {
        if self.running.is_some() {
            self.again = true;
            return;
        }
        let (done, result) = mpsc::channel();
        let clean = self.clean.clone();
        let spawned = std::thread::Builder::new()
            .name("dead-node-cleanup".into())
            .spawn(move || {
                let _ = done.send(clean());
            });
        match spawned {
            Ok(_) => {
                self.running = Some((Instant::now(), result));
                self.overrun_logged = false;
            }
            Err(e) => tracing::warn!("starting the cleanup of dead nodes: {e}"),
        }
    }

    /// Logs the running cleanup's outcome when it has ended, or once that it overruns its
    /// limit; never waits.
    fn poll(&mut self) {
        let Some((started, result)) = &self.running else {
            return;
        };
        let took = started.elapsed();
        match result.try_recv() {
            Ok(Ok(r)) => tracing::info!(
                "dead nodes cleaned up in {took:.1?}: {} removed, {} failed",
                r.dead_nodes_removed,
                r.dead_nodes_failed
            ),
            Ok(Err(e)) => tracing::warn!("cleaning up dead nodes: {e:#}"),
            Err(mpsc::TryRecvError::Disconnected) => {
                tracing::warn!("the cleanup of dead nodes ended without a result")
            }
            Err(mpsc::TryRecvError::Empty) => {
                if took > self.limit && !self.overrun_logged {
                    tracing::warn!(
                        "the cleanup of dead nodes has run for {took:.1?} (limit {:?}); \
                         supervision goes on without it",
                        self.limit
                    );
                    self.overrun_logged = true;
                }
                return;
            }
        }
        self.running = None;
        if std::mem::take(&mut self.again) {
            self.request();
        }
    }
}

/// How long a condition that must not last has held (an actor's policy lagging, a learner
/// taking no gradient step).
#[derive(Debug, Default)]
struct Overdue {
    since: Option<Instant>,
}

impl Overdue {
    /// Notes whether the condition `holds` at `now`; once it has held for longer than
    /// `timeout` without a break, returns for how long.
    fn check(&mut self, holds: bool, now: Instant, timeout: Duration) -> Option<Duration> {
        if !holds {
            self.since = None;
            return None;
        }
        let held = now.saturating_duration_since(*self.since.get_or_insert(now));
        (held > timeout).then_some(held)
    }
}

/// Most env steps an actor can take past what the replay stored of it without any of them
/// being stored: its chunks waiting in the replay's queue ([`TRAJECTORY_BUFFER`]), one in its
/// backlog and one being filled, one step a decision. Beyond it, the actor stepped on while
/// its chunks were taken and not stored (rejected) or lost.
const UNSTORED_SLACK: u64 = ((TRAJECTORY_BUFFER + 2) * ctxrace_ipc::wire::MAX_CHUNK) as u64;

/// Whether an actor's steps reach the replay: the replay's count of its stored steps, and the
/// actor's env steps (its heartbeat's) when that count last grew.
#[derive(Debug, Default)]
struct StreamWatch {
    stored: u64,
    beat_at_store: u64,
    starved: Overdue,
}

impl StreamWatch {
    /// Takes the replay's newest count of the actor's stored steps and the actor's newest env
    /// steps at `now`; once the actor has been more than [`UNSTORED_SLACK`] steps past the
    /// last growth of its stored count for longer than `timeout`, returns for how long.
    fn check(
        &mut self,
        stored: u64,
        beat: u64,
        now: Instant,
        timeout: Duration,
    ) -> Option<Duration> {
        if stored != self.stored {
            (self.stored, self.beat_at_store) = (stored, beat);
        }
        let starved = beat > self.beat_at_store + UNSTORED_SLACK;
        self.starved.check(starved, now, timeout)
    }

    /// A new start of the actor: its env steps count from 0 again.
    fn actor_started(&mut self) {
        self.beat_at_store = 0;
        self.starved = Overdue::default();
    }
}

/// One supervised child process.
struct Supervised {
    name: String,
    args: Vec<String>,
    /// The process's log file (its stderr, appended across restarts).
    log: std::path::PathBuf,
    child: Option<Child>,
    starts: u64,
    /// Starts of this process in earlier launches of the run (a resumed run's actors continue
    /// their incarnations, so that they draw fresh episodes).
    earlier_starts: u64,
    restart_at: Option<Instant>,
    /// Set once the process should stay down.
    retired: bool,
    /// When it was last (re)started.
    started_at: Instant,
    /// When its last sign of life (heartbeat, status) arrived, since its start.
    last_sign: Option<Instant>,
    /// Since when it has made no progress (an actor's policy lagging, the learner taking no
    /// gradient step), within its current start.
    stalled: Overdue,
    /// When it failed, within the restart window.
    failures: std::collections::VecDeque<Instant>,
    /// The run directory's lock, which the process holds too while it runs.
    lock: DirLock,
}

impl Supervised {
    fn new(name: String, args: Vec<String>, logs: &Path, lock: DirLock) -> Self {
        Self {
            lock,
            log: logs.join(format!("{}.log", name.replace(' ', "-"))),
            name,
            args,
            child: None,
            starts: 0,
            earlier_starts: 0,
            restart_at: Some(Instant::now()),
            retired: false,
            started_at: Instant::now(),
            last_sign: None,
            stalled: Overdue::default(),
            failures: std::collections::VecDeque::new(),
        }
    }

    /// Starts the process if it is down, not retired and its restart is due; returns whether
    /// it started.
    fn start_if_due(&mut self) -> Result<bool> {
        let due = self.child.is_none()
            && !self.retired
            && self.restart_at.is_some_and(|t| Instant::now() >= t);
        if due {
            if self.starts > 0 {
                tracing::warn!("restarting {} (start {})", self.name, self.starts + 1);
            }
            self.start()?;
        }
        Ok(due)
    }

    /// The process id of its running start (0 when it is down).
    fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// Starts the process (again); actors are told how often they ran before.
    fn start(&mut self) -> Result<()> {
        let exe = std::env::current_exe().context("locating the ctxrace binary")?;
        let mut cmd = Command::new(exe);
        cmd.args(&self.args);
        if self.name.starts_with("actor") {
            cmd.args([
                "--incarnation",
                &(self.earlier_starts + self.starts).to_string(),
            ]);
        }
        let log =
            open_append(&self.log).with_context(|| format!("opening {}", self.log.display()))?;
        cmd.stderr(log);
        if std::env::var_os("RUST_LOG").is_none() {
            cmd.env("RUST_LOG", "info");
        }
        // the children die with the launcher, even when it is killed outright, and hold the run's
        // lock until they have exited (a snapshot or checkpoint they finish is theirs)
        die_with_parent(&mut cmd);
        self.lock.share_with(&mut cmd);
        self.child = Some(
            cmd.spawn()
                .with_context(|| format!("starting {}", self.name))?,
        );
        self.starts += 1;
        self.restart_at = None;
        self.started_at = Instant::now();
        self.last_sign = None;
        self.stalled = Overdue::default();
        Ok(())
    }

    /// Counts a failure; an error with the reason and the process's last log lines once more
    /// than `max_restarts` fall within the restart window.
    fn failed(&mut self, why: &str, cfg: &SupervisorConfig) -> Result<()> {
        let now = Instant::now();
        let window = Duration::from_secs(cfg.restart_window_secs);
        self.failures.push_back(now);
        while self.failures.front().is_some_and(|t| now - *t > window) {
            self.failures.pop_front();
        }
        if self.failures.len() > cfg.max_restarts as usize {
            bail!(
                "{} {why}, its {} failure in {} s (at most {} restarts are allowed, [supervisor] \
                 max_restarts); stopping the run. Its last log lines ({}):\n{}",
                self.name,
                ordinal(self.failures.len()),
                cfg.restart_window_secs,
                cfg.max_restarts,
                self.log.display(),
                log_tail(&self.log, 20)
            );
        }
        tracing::warn!(
            "{} {why}; restarting it{}",
            self.name,
            match self.name.as_str() {
                "replay" => " from its snapshot",
                "learner" => " from its checkpoint",
                _ => "",
            }
        );
        self.schedule_restart();
        Ok(())
    }

    /// Handles its exit with `status`: a [`CONFIG_EXIT_CODE`] exit (an error a restart would
    /// meet again) stops the run at once with its last log lines; any other counts as a
    /// failure ([`Supervised::failed`]).
    fn exited(&mut self, status: ExitStatus, cfg: &SupervisorConfig) -> Result<()> {
        if status.code() == Some(CONFIG_EXIT_CODE) {
            bail!(
                "{} stopped on an error that a restart would meet again; stopping the run. Its \
                 last log lines ({}):\n{}",
                self.name,
                self.log.display(),
                log_tail(&self.log, 20)
            );
        }
        self.failed(&format!("exited ({status})"), cfg)
    }

    /// Kills the process if its last sign of life (or its start, if none came) is older than
    /// the heartbeat timeout; it is then reaped as a crash.
    fn kill_if_silent(&mut self, timeout: Duration) {
        let quiet = self.last_sign.unwrap_or(self.started_at).elapsed();
        if quiet > timeout {
            self.kill(&format!(
                "sent no sign of life for {:.0} s: killing it as hung",
                quiet.as_secs_f64()
            ));
        }
    }

    /// Kills the running process (not a retired one), saying `why`; it is then reaped as a
    /// crash and restarted.
    fn kill(&mut self, why: &str) {
        let Some(child) = &mut self.child else { return };
        if self.retired {
            return;
        }
        tracing::warn!("{} {why}", self.name);
        // reaped at once, so that the next look does not find it again
        let _ = child.kill();
        let _ = child.wait();
    }

    /// Reaps the process if it exited; returns its status.
    fn reap(&mut self) -> Result<Option<ExitStatus>> {
        let Some(child) = &mut self.child else {
            return Ok(None);
        };
        let status = child.try_wait()?;
        if status.is_some() {
            self.child = None;
        }
        Ok(status)
    }

    /// Schedules the next start after a back-off of 1 s doubling with each failure within the
    /// restart window, at most [`MAX_BACKOFF`]: a process whose last failure lies outside the window
    /// restarts after 1 s again, one that keeps failing waits longer and longer.
    fn schedule_restart(&mut self) {
        let recent = self.failures.len().saturating_sub(1).min(5) as u32;
        let backoff = Duration::from_secs(1 << recent).min(MAX_BACKOFF);
        self.restart_at = Some(Instant::now() + backoff);
    }

    /// Asks the process to stop (SIGTERM) and keeps it down.
    fn stop(&mut self) {
        self.retired = true;
        self.restart_at = None;
        if let Some(child) = &self.child {
            // SAFETY: sending a signal to our own child's pid.
            unsafe {
                libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
            }
        }
    }
}

/// Live figures for the progress bar.
#[derive(Default)]
struct Progress {
    env_steps: u64,
    grad_steps: u64,
    /// The newest weights version verified so far (a restarted learner's broadcasts start
    /// lower): no actor can report driving a newer one.
    newest_version: u64,
    episodes: u64,
    /// Each actor's env steps at its newest reported episode: their sum is an episode row's
    /// env steps while the replay's count lags behind (it reports once a second, and the first
    /// second holds the prefill and more).
    actor_steps: Vec<u64>,
    recent_progress: Vec<f64>,
    fill: u64,
    capacity: u64,
    actor_versions: Vec<u64>,
    /// The replay's newest status.
    replay: ReplayStatus,
    /// Malformed or implausible telemetry and weights the launcher itself refused.
    telemetry_rejected: u64,
    /// `telemetry_rejected` by reason ([`ctxrace_ipc::wire::REASONS`]).
    telemetry_rejected_by_reason: [u64; REASONS.len()],
    weights_rejected: u64,
    /// Steps the replay had stored when it last crashed, until its restart reports what its
    /// snapshot restored.
    inserted_at_crash: Option<u64>,
    /// Steps replays stored and lost in a crash (not in the snapshot they restarted from).
    lost_in_restarts: u64,
    /// Each actor's env steps at its newest heartbeat (of its current start).
    actor_beat_steps: Vec<u64>,
    /// Env steps sent by actor starts that died without writing their report, counted to
    /// their last heartbeat (the closing summary's "sent" reads the reports).
    killed_actor_steps: u64,
    /// Gradient steps taken twice: those a learner had taken past its newest checkpoint when
    /// it died, which its restart, resuming from that checkpoint, takes again.
    repeated_grad_steps: u64,
}

/// What restarts cost a run, for its closing summary.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct RestartCosts {
    /// Steps stored by a replay and lost in its crash.
    lost: u64,
    /// Steps sent by killed actors (to their last heartbeat), which wrote no report.
    killed_actor_steps: u64,
    /// Gradient steps a restarted learner took again.
    repeated_grad_steps: u64,
}

impl Progress {
    /// Takes the replay's newest status; the first one of a restarted replay tells how many
    /// of the steps stored before the crash its snapshot restored: the rest are lost.
    fn replay_status(&mut self, s: ReplayStatus) {
        if let Some(before) = self.inserted_at_crash.take() {
            self.lost_in_restarts += before.saturating_sub(s.restored_inserts);
        }
        self.env_steps = s.inserted;
        self.fill = s.fill;
        self.capacity = s.capacity;
        self.replay = s;
    }

    /// Notes a replay crash, taking `last`, the dead replay's status not yet read.
    fn replay_crashed(&mut self, last: Option<ReplayStatus>) {
        if let Some(s) = last {
            self.replay_status(s);
        }
        // a restart that crashed before its first status restored what the first one held
        self.inserted_at_crash.get_or_insert(self.replay.inserted);
    }

    /// Notes that actor `id` died; `reported` says whether its start wrote its report (else its
    /// steps to its last heartbeat are counted as sent by a killed actor).
    fn actor_died(&mut self, id: usize, reported: bool) {
        if let Some(steps) = self.actor_beat_steps.get_mut(id) {
            if !reported {
                self.killed_actor_steps += *steps;
            }
            *steps = 0;
        }
    }

    /// Notes that the learner died; its restart resumes from the checkpoint at `resume_step`,
    /// so the gradient steps it had taken past that are taken again.
    fn learner_died(&mut self, resume_step: u64) {
        self.repeated_grad_steps += self.grad_steps.saturating_sub(resume_step);
        self.grad_steps = self.grad_steps.min(resume_step);
    }

    /// What restarts have cost the run so far.
    fn restart_costs(&self) -> RestartCosts {
        RestartCosts {
            lost: self.lost_in_restarts,
            killed_actor_steps: self.killed_actor_steps,
            repeated_grad_steps: self.repeated_grad_steps,
        }
    }

    /// An episode row's env steps: the replay's count, or the actors' own while that lags (it
    /// comes once a second), never past `budget`, which the replay never stores more than: the
    /// actors' counts take in steps of rejected chunks (which do not hold an actor back), and a
    /// corrupted report may claim any plausible count.
    fn row_env_steps(&self, budget: u64) -> u64 {
        self.env_steps
            .max(self.actor_steps.iter().sum())
            .min(budget)
    }

    /// Each actor's policy age: gradient steps between the learner's newest broadcast and the
    /// version the actor last reported driving with.
    fn policy_lags(&self) -> impl Iterator<Item = u64> + '_ {
        self.actor_versions
            .iter()
            .map(|v| self.grad_steps.saturating_sub(*v))
    }

    fn message(&self, start: Instant) -> String {
        let secs = start.elapsed().as_secs_f64().max(1e-9);
        let mean = if self.recent_progress.is_empty() {
            0.0
        } else {
            self.recent_progress.iter().sum::<f64>() / self.recent_progress.len() as f64
        };
        let lag = self.policy_lags().max().unwrap_or(0);
        let rejected = self.replay.rejected + self.telemetry_rejected + self.weights_rejected;
        format!(
            "| {} grad ({:.1}/s) | {} episodes, progress {mean:.3} | replay {:.0}% | lag {lag}{}",
            self.grad_steps,
            self.grad_steps as f64 / secs,
            self.episodes,
            100.0 * self.fill as f64 / self.capacity.max(1) as f64,
            if rejected > 0 {
                format!(" | {rejected} rejected (status.json)")
            } else {
                String::new()
            },
        )
    }

    /// The live status file's contents: counters, each actor's policy version and its age in
    /// gradient steps, rejections by reason, the replay's longest stall, and `learner`, the
    /// learner's own transport counters ([`learner_status`]); each actor's steps the replay
    /// stored and the chunks it rejected, from `streams` ([`replay_streams`]).
    fn status(&self, learner: serde_json::Value, streams: &ReplayStreams) -> serde_json::Value {
        let r = &self.replay;
        let actors: Vec<serde_json::Value> = self
            .actor_versions
            .iter()
            .zip(self.policy_lags())
            .enumerate()
            .map(|(id, (version, lag))| {
                serde_json::json!({
                    "id": id,
                    "policy_version": version,
                    "policy_lag": lag,
                    "stored_steps": streams.stored_by_actor.get(id),
                    "surplus_steps": streams.surplus_by_actor.get(id),
                    "rejected_chunks": streams.rejected_by_actor.get(id),
                })
            })
            .collect();
        serde_json::json!({
            "env_steps": self.env_steps,
            "grad_steps": self.grad_steps,
            "episodes": self.episodes,
            "actor_versions": self.actor_versions,
            "actors": actors,
            "max_policy_lag": self.policy_lags().max().unwrap_or(0),
            "replay": {
                "inserted": r.inserted,
                "sampled": r.sampled,
                "fill": r.fill,
                "capacity": r.capacity,
                "batches": r.batches,
                "dropped_chunks": r.dropped_chunks,
                "rejected": r.rejected,
                "rejected_by_reason": named_reasons(&r.rejected_by_reason),
                "restored_inserts": r.restored_inserts,
                "budget_stored": streams.budget_stored(),
                "surplus": streams.surplus_by_actor.iter().sum::<u64>(),
                "lost_in_restarts": self.lost_in_restarts,
                "longest_turn_ms": r.longest_turn_us as f64 / 1e3,
            },
            "killed_actor_steps": self.killed_actor_steps,
            "repeated_grad_steps": self.repeated_grad_steps,
            "learner": learner,
            "launcher_rejected": {
                "telemetry": self.telemetry_rejected,
                "telemetry_by_reason": named_reasons(&self.telemetry_rejected_by_reason),
                "weights": self.weights_rejected,
            },
        })
    }
}

/// The flags that reproduce `tracks` on a child's command line.
fn track_flags(tracks: &TrackArgs) -> Vec<String> {
    let mut v = Vec::new();
    if let Some(d) = &tracks.tracks_dir {
        v.extend(["--tracks-dir".into(), d.display().to_string()]);
    }
    if tracks.raceline_file {
        v.push("--raceline-file".into());
    }
    for (flag, value) in [
        ("--v-max", tracks.v_max),
        ("--a-lat", tracks.a_lat),
        ("--a-long", tracks.a_long),
    ] {
        if let Some(x) = value {
            v.extend([flag.into(), x.to_string()]);
        }
    }
    v
}

/// What the launcher says when a shared-memory segment it reads is truncated under it.
const BUS_ERROR_MESSAGE: &[u8] = b"\nctxrace train: the run's shared memory was truncated or \
    removed under the launcher (SIGBUS); the run stops here, its processes with it (they stop \
    when the launcher dies). The next `ctxrace train` removes the run's files; resume this run \
    with --resume.\n";

/// Writes [`BUS_ERROR_MESSAGE`] to stderr and dies of the signal, as without a handler.
extern "C" fn on_bus_error(_: libc::c_int) {
    // SAFETY: write, signal and raise are async-signal-safe; the message is a static buffer.
    unsafe {
        libc::write(
            2,
            BUS_ERROR_MESSAGE.as_ptr().cast(),
            BUS_ERROR_MESSAGE.len(),
        );
        libc::signal(libc::SIGBUS, libc::SIG_DFL);
        libc::raise(libc::SIGBUS);
    }
}

/// Makes a SIGBUS (a segment truncated under the launcher, which iceoryx2 maps) say what
/// happened before the launcher dies of it, instead of dying without a word.
fn explain_bus_errors() {
    // SAFETY: installs a handler that only calls async-signal-safe functions.
    unsafe {
        libc::signal(
            libc::SIGBUS,
            on_bus_error as *const () as libc::sighandler_t,
        );
    }
}

/// Runs a training run with `actors` actor processes in `dir` (which holds `config.toml`).
pub fn run(
    cfg: &ExperimentConfig,
    dir: &Path,
    lock: &DirLock,
    actors: usize,
    tracks: &TrackArgs,
) -> Result<()> {
    explain_bus_errors();
    if actors == 0 {
        bail!("--actors must be at least 1");
    }
    let run_id = format!(
        "{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis())
    );
    match sweep_orphaned_runs() {
        Ok(sweep) => {
            if !sweep.swept.is_empty() {
                tracing::warn!(
                    "removed the shared memory of runs whose launcher died: {:?}",
                    sweep.swept
                )
            }
            for (prefix, pids) in &sweep.kept {
                tracing::warn!(
                    "the launcher of run {prefix} died but its processes {pids:?} live on; \
                     its shared memory stays until they end (kill them to free it)"
                )
            }
        }
        Err(e) => tracing::warn!("sweeping the shared memory of dead runs: {}", Causes(&e)),
    }
    let prefix = run_prefix(&run_id);
    claim_run(&prefix)?;
    let common = |role: &str| {
        vec![
            role.to_string(),
            "--run-dir".into(),
            dir.display().to_string(),
            "--prefix".into(),
            prefix.clone(),
            "--actors".into(),
            actors.to_string(),
        ]
    };
    let logs = dir.join(LOGS);
    std::fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    let mut replay = Supervised::new("replay".into(), common("replay"), &logs, lock.try_clone()?);
    let mut learner = Supervised::new(
        "learner".into(),
        common("learner"),
        &logs,
        lock.try_clone()?,
    );
    let mut actor_procs: Vec<Supervised> = (0..actors)
        .map(|k| {
            let mut args = common("actor");
            args.extend(["--id".into(), k.to_string()]);
            args.extend(track_flags(tracks));
            let mut actor = Supervised::new(format!("actor {k}"), args, &logs, lock.try_clone()?);
            actor.earlier_starts = earlier_actor_starts(dir, k);
            Ok(actor)
        })
        .collect::<Result<_>>()?;

    let transport = RunTransport::open(&prefix, actors, "launcher")?;
    let costs = supervise(
        cfg,
        dir,
        &transport,
        &mut replay,
        &mut learner,
        &mut actor_procs,
    );
    // stop whatever still runs, all at once: the replay takes the actors' last chunks, whatever
    // its rate limiter says, until their senders have closed, then writes its snapshot
    for p in actor_procs.iter_mut() {
        p.stop();
    }
    learner.stop();
    replay.stop();
    wait_all(&mut actor_procs)?;
    let mut rest = [learner, replay];
    wait_all(&mut rest)?;
    drop(transport);
    match cleanup(&prefix) {
        Ok(report) => tracing::info!("shared memory of {prefix} removed: {report:?}"),
        Err(e) => tracing::warn!("cleaning up {prefix}: {}", Causes(&e)),
    }
    let costs = costs?;
    eprintln!("{}", step_summary(dir, costs));
    Ok(())
}

/// One line on where the run's steps went, from the replay's own counts first: stored (of
/// each actor), past the budget, rejected, lost in replay crashes; then what the actors report
/// sending (every start of each, a killed one counted to its last heartbeat), what of that is
/// not accounted for, and dropped; and the gradient steps restarted learners took twice.
fn step_summary(dir: &Path, costs: RestartCosts) -> String {
    let read = |path: &Path| -> Option<serde_json::Value> {
        serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
    };
    let mut sent = std::collections::BTreeMap::<u64, u64>::new();
    let mut dropped = 0;
    if let Ok(entries) = std::fs::read_dir(dir.join(ACTOR_REPORTS)) {
        for report in entries.flatten().filter_map(|e| read(&e.path())) {
            let id = report["id"].as_u64().unwrap_or(0);
            *sent.entry(id).or_default() += report["sent_steps"].as_u64().unwrap_or(0);
            dropped += report["dropped_steps"].as_u64().unwrap_or(0);
        }
    }
    let shares: Vec<String> = sent.values().map(u64::to_string).collect();
    let lost = costs.lost;
    let total = sent.values().sum::<u64>() + costs.killed_actor_steps;
    let join = |v: &[u64]| v.iter().map(u64::to_string).collect::<Vec<_>>().join(" / ");
    let mut line = String::from("steps: ");
    let mut taken = None;
    if let Some(replay) = read(&dir.join(REPLAY_REPORT)) {
        let stored = replay["inserted"].as_u64().unwrap_or(0);
        line += &format!("{stored} stored by the replay");
        // what the replay itself took of each actor: its count, not the actors' claims
        let streams = replay_streams(dir);
        let surplus = streams.surplus_by_actor.iter().sum::<u64>();
        if !streams.stored_by_actor.is_empty() {
            line += &format!(" ({} of each actor", join(&streams.stored_by_actor));
            // a restarted replay counts from its restart
            let restarted = replay["restored_inserts"].as_u64().unwrap_or(0) > 0;
            line += if restarted { ", its last start)" } else { ")" };
        }
        if stored < streams.env_steps {
            line += &format!(
                ", {} short of the run's budget of {} (the learner took its gradient steps first)",
                streams.env_steps - stored,
                streams.env_steps
            );
        }
        if surplus > 0 {
            line += &format!(
                ", {surplus} past the run's budget of {} (taken, not stored: {} of each actor)",
                streams.env_steps,
                join(&streams.surplus_by_actor)
            );
        }
        line += &format!(
            ", {} rejected{}, longest replay stall {:.1} ms",
            replay["rejected"],
            if streams.rejected_by_actor.iter().any(|&n| n > 0) {
                format!(
                    " (chunks of each actor {})",
                    join(&streams.rejected_by_actor)
                )
            } else {
                String::new()
            },
            replay["longest_turn_ms"].as_f64().unwrap_or(0.0)
        );
        if lost > 0 {
            line += &format!(
                "; {lost} LOST in replay restarts (stored, not in the snapshot it restarted from)"
            );
        }
        taken = Some(stored + surplus + lost);
    }
    line += &format!(
        "; the actors report {total} sent ({}{})",
        shares.join(" / "),
        match costs.killed_actor_steps {
            0 => String::new(),
            k => format!(", and {k} by killed actors to their last heartbeat"),
        }
    );
    if let Some(taken) = taken {
        let unaccounted = total.saturating_sub(taken);
        if unaccounted > 0 {
            line += &format!(
                "; {unaccounted} sent neither stored nor counted (in rejected chunks, or \
                 waiting at a replay that crashed)"
            );
        }
    }
    if dropped > 0 {
        line += &format!(
            "; {dropped} DROPPED (the replay did not take them before their actor stopped: \
             see actors/*.json)"
        );
    } else {
        line += "; none dropped";
    }
    if costs.repeated_grad_steps > 0 {
        line += &format!(
            "; {} gradient steps TAKEN TWICE (a learner restarted from its checkpoint after \
             taking them)",
            costs.repeated_grad_steps
        );
    }
    line
}

/// How many times actor `id` ran in earlier launches of the run in `dir` (its reports).
fn earlier_actor_starts(dir: &Path, id: usize) -> u64 {
    let prefix = format!("actor-{id}-");
    std::fs::read_dir(dir.join(ACTOR_REPORTS))
        .map(|entries| {
            entries
                .filter_map(|e| e.ok())
                .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
                .count() as u64
        })
        .unwrap_or(0)
}

/// Waits up to [`STOP_GRACE`] for the processes to exit, then kills them.
fn wait_all(procs: &mut [Supervised]) -> Result<()> {
    let deadline = Instant::now() + STOP_GRACE;
    for p in procs.iter_mut() {
        while p.child.is_some() {
            if p.reap()?.is_some() {
                break;
            }
            if Instant::now() > deadline {
                if let Some(c) = &mut p.child {
                    tracing::warn!("{} did not stop in time; killing it", p.name);
                    c.kill()?;
                    c.wait()?;
                }
                p.child = None;
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    Ok(())
}

/// "1st", "2nd", "3rd", "4th", …
fn ordinal(n: usize) -> String {
    let suffix = match (n % 10, n % 100) {
        (1, 11) | (2, 12) | (3, 13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}

/// The last `n` lines of a log file (indented), or a note that it cannot be read.
fn log_tail(path: &Path, n: usize) -> String {
    match std::fs::read_to_string(path) {
        Ok(text) => {
            let lines: Vec<&str> = text.lines().collect();
            let tail = &lines[lines.len().saturating_sub(n)..];
            if tail.is_empty() {
                "    (empty)".into()
            } else {
                tail.iter()
                    .map(|l| format!("    {l}"))
                    .collect::<Vec<_>>()
                    .join("\n")
            }
        }
        Err(e) => format!("    (unreadable: {e})"),
    }
}

/// The value of a telemetry read, or `None` with a warning (the error and its causes).
fn tolerate<T>(read: Result<T, IpcError>) -> Option<T> {
    read.map_err(|e| tracing::warn!("telemetry: {}", Causes(&e)))
        .ok()
}

/// Reads [`REPLAY_STREAMS`]; empty where the file is missing or unreadable (the checks wait for
/// the next one).
fn replay_streams(dir: &Path) -> ReplayStreams {
    read_json(&dir.join(REPLAY_STREAMS)).unwrap_or_default()
}

/// The learner's status file of its current start ([`LEARNER_STATUS`]): null before its first,
/// an `error` naming the file and the cause where it cannot be read as JSON.
fn learner_status(dir: &Path) -> serde_json::Value {
    let path = dir.join(LEARNER_STATUS);
    if !path.exists() {
        return serde_json::Value::Null;
    }
    read_json(&path).unwrap_or_else(|e| serde_json::json!({ "error": Causes(&e).to_string() }))
}

/// The supervision loop; returns when the run is complete or interrupted, with what restarts
/// cost it.
fn supervise(
    cfg: &ExperimentConfig,
    dir: &Path,
    transport: &RunTransport,
    replay: &mut Supervised,
    learner: &mut Supervised,
    actors: &mut [Supervised],
) -> Result<RestartCosts> {
    let mut telemetry = TelemetrySubscriber::new(transport, RunBounds::of(cfg, actors.len()))?;
    let plan = cfg.plan();
    let mut weights = WeightsReceiver::new(transport, plan.gradient_steps)?;
    let mut episodes = EpisodeLog::open(dir, "launcher")?;
    let mut meter = RateMeter::default();
    let bar = progress_bar(plan.env_steps, "env steps");
    let start = Instant::now();
    let mut p = Progress {
        actor_versions: vec![0; actors.len()],
        actor_steps: vec![0; actors.len()],
        actor_beat_steps: vec![0; actors.len()],
        ..Progress::default()
    };
    let mut tick = Instant::now();
    let mut last_status = Instant::now();
    let mut cleaner = DeadNodeCleaner::new(transport.prefix());
    let mut last_grad_steps = p.grad_steps;
    let mut streams: Vec<StreamWatch> = actors.iter().map(|_| StreamWatch::default()).collect();
    let mut replay_took = ReplayStreams::default();
    let mut last_streams = Instant::now();
    let stop = termination_flag()?;
    loop {
        std::thread::sleep(Duration::from_millis(100));
        if stop.load(Ordering::Relaxed) {
            bar.abandon_with_message("interrupted: stopping (checkpoint, snapshot)");
            return Ok(p.restart_costs());
        }
        // (re)start what is due; the telemetry of a start is checked against its own history
        if replay.start_if_due()? {
            telemetry.replay_started();
        }
        learner.start_if_due()?;
        for (id, actor) in actors.iter_mut().enumerate() {
            if actor.start_if_due()? {
                telemetry.actor_started(id, actor.pid());
                streams[id].actor_started();
            }
        }
        // telemetry is best effort: a dying peer must not take the launcher down; the weights
        // are read after the heartbeats, whose policy versions must not be ahead of them
        let beats = telemetry.heartbeats(|| {
            if let Some(version) = tolerate(weights.latest_with(|v, _| v)).flatten() {
                p.grad_steps = version;
                p.newest_version = p.newest_version.max(version);
            }
            p.newest_version
        });
        for hb in tolerate(beats).unwrap_or_default() {
            if let Some(v) = p.actor_versions.get_mut(hb.actor_id as usize) {
                *v = hb.policy_version;
            }
            if let Some(steps) = p.actor_beat_steps.get_mut(hb.actor_id as usize) {
                *steps = hb.env_steps;
            }
            if let Some(a) = actors.get_mut(hb.actor_id as usize) {
                a.last_sign = Some(Instant::now());
            }
        }
        if let Some(s) = tolerate(telemetry.replay_status()).flatten() {
            replay.last_sign = Some(Instant::now());
            p.replay_status(s);
        }
        p.telemetry_rejected = telemetry.rejected();
        p.telemetry_rejected_by_reason = telemetry.rejected_by_reason();
        p.weights_rejected = weights.rejected();
        for e in tolerate(telemetry.episodes()).unwrap_or_default() {
            p.episodes += 1;
            if let Some(steps) = p.actor_steps.get_mut(e.actor_id as usize) {
                *steps = e.env_steps;
            }
            p.recent_progress.push(e.progress as f64);
            if p.recent_progress.len() > 20 {
                p.recent_progress.remove(0);
            }
            episodes.write(&TrainingEpisode {
                env_steps: p.row_env_steps(plan.env_steps),
                grad_steps: p.grad_steps,
                actor: e.actor_id,
                episode: e.episode_id,
                context_speed: e.context[0] as f64,
                context_steer: e.context[1] as f64,
                progress: e.progress as f64,
                overtakes: e.overtakes,
                a2a: e.a2a != 0,
                wall_crash: e.wall_crash != 0,
                episode_return: e.episode_return as f64,
                steps: e.steps as usize,
            })?;
        }
        // reap and decide; a crashed process's node is cleaned up so that its peers stop
        // waiting for it
        let silence = Duration::from_secs(cfg.supervisor.heartbeat_timeout_secs);
        for proc in std::iter::once(&mut *replay).chain(actors.iter_mut()) {
            proc.kill_if_silent(silence);
        }
        // progress, not just heartbeats: weights reach every actor, the learner trains
        let stall = Duration::from_secs(cfg.supervisor.stall_timeout_secs);
        let now = Instant::now();
        let lags: Vec<u64> = p.policy_lags().collect();
        for (actor, lag) in actors.iter_mut().zip(lags) {
            let lagging = actor.child.is_some() && lag > cfg.supervisor.max_policy_lag;
            if let Some(held) = actor.stalled.check(lagging, now, stall) {
                actor.kill(&format!(
                    "has driven a policy {lag} gradient steps behind the learner's newest for \
                     {:.0} s ([supervisor] max_policy_lag = {}): the weights stopped reaching \
                     it; killing it",
                    held.as_secs_f64(),
                    cfg.supervisor.max_policy_lag
                ));
            }
        }
        if last_streams.elapsed() >= Duration::from_secs(1) {
            // a replay's file from before its restart counts its old start: none until it writes
            replay_took = replay
                .last_sign
                .map_or(ReplayStreams::default(), |_| replay_streams(dir));
            last_streams = Instant::now();
        }
        for ((actor, watch), (&stored, &beat)) in actors
            .iter_mut()
            .zip(&mut streams)
            .zip(replay_took.stored_by_actor.iter().zip(&p.actor_beat_steps))
        {
            if actor.child.is_none() {
                continue;
            }
            if let Some(held) = watch.check(stored, beat, now, stall) {
                actor.kill(&format!(
                    "took env steps up to {beat} while none of its steps reached the replay for \
                     {:.0} s (the replay holds {stored} of them): killing it",
                    held.as_secs_f64()
                ));
            }
        }
        let replay_serves = replay.child.is_some()
            && replay.last_sign.is_some_and(|t| t.elapsed() < silence)
            && p.replay.inserted >= plan.replay.min_fill as u64;
        let idle = learner.child.is_some() && replay_serves && p.grad_steps == last_grad_steps;
        if let Some(held) = learner.stalled.check(idle, now, stall) {
            learner.kill(&format!(
                "took no gradient step in {:.0} s while the replay held {} steps (its own \
                 counters: {}): killing it",
                held.as_secs_f64(),
                p.replay.inserted,
                learner_status(dir)
            ));
        }
        last_grad_steps = p.grad_steps;
        let mut crashed = false;
        for (id, proc) in actors.iter_mut().enumerate() {
            if let Some(status) = proc.reap()? {
                if !proc.retired {
                    let incarnation = proc.earlier_starts + proc.starts - 1;
                    let report = format!("actor-{id}-{incarnation}.json");
                    p.actor_died(id, dir.join(ACTOR_REPORTS).join(report).exists());
                    proc.exited(status, &cfg.supervisor)?;
                    crashed = true;
                }
            }
        }
        if let Some(status) = replay.reap()? {
            if !replay.retired {
                p.replay_crashed(tolerate(telemetry.replay_status()).flatten());
                replay.exited(status, &cfg.supervisor)?;
                crashed = true;
            }
        }
        if let Some(status) = learner.reap()? {
            if status.success() {
                bar.set_position(p.env_steps.min(plan.env_steps));
                bar.finish_with_message(p.message(start));
                ctxrace_run::results::write_json(
                    &dir.join(STATUS_FILE),
                    &p.status(learner_status(dir), &replay_took),
                )?;
                return Ok(p.restart_costs());
            }
            p.learner_died(ctxrace_learner::process::resume_step(dir));
            learner.exited(status, &cfg.supervisor)?;
            crashed = true;
        }
        if crashed {
            cleaner.request();
        }
        cleaner.poll();
        if last_status.elapsed() >= Duration::from_secs(1) {
            ctxrace_run::results::write_json(
                &dir.join(STATUS_FILE),
                &p.status(learner_status(dir), &replay_took),
            )?;
            last_status = Instant::now();
        }
        if tick.elapsed() >= Duration::from_millis(250) {
            bar.set_position(p.env_steps.min(plan.env_steps));
            bar.set_message(p.message(start));
            tick = Instant::now();
            if let Some(rates) = meter.read(p.env_steps, p.grad_steps, (p.fill, p.capacity)) {
                episodes.rates(p.env_steps, &rates)?;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_condition_is_overdue_only_after_holding_past_its_timeout_without_a_break() {
        let t0 = Instant::now();
        let (s, timeout) = (Duration::from_secs(1), Duration::from_secs(5));
        let mut overdue = Overdue::default();
        assert_eq!(overdue.check(true, t0, timeout), None);
        assert_eq!(overdue.check(true, t0 + 5 * s, timeout), None);
        assert_eq!(overdue.check(true, t0 + 6 * s, timeout), Some(6 * s));
        // a break starts it over
        assert_eq!(overdue.check(false, t0 + 7 * s, timeout), None);
        assert_eq!(overdue.check(true, t0 + 8 * s, timeout), None);
        assert_eq!(overdue.check(true, t0 + 13 * s, timeout), None);
        assert_eq!(overdue.check(true, t0 + 14 * s, timeout), Some(6 * s));
    }
    use std::sync::atomic::AtomicU64;
    use std::sync::Arc;

    fn status(inserted: u64, restored_inserts: u64) -> ReplayStatus {
        ReplayStatus {
            inserted,
            restored_inserts,
            ..ReplayStatus::default()
        }
    }

    #[test]
    fn an_actor_is_starved_only_when_it_steps_far_past_its_stored_steps_for_long() {
        let t0 = Instant::now();
        let (s, timeout) = (Duration::from_secs(1), Duration::from_secs(5));
        let mut watch = StreamWatch::default();
        // stored grows with the actor's steps: never starved
        for k in 0..20u64 {
            assert_eq!(
                watch.check(64 * k, 64 * k + 500, t0 + Duration::from_secs(k), timeout),
                None
            );
        }
        // held up by the replay's rate limiter: it stops within the slack, and waits
        let at = 64 * 19;
        for k in 20..40u64 {
            let beat = (64 * k + 500).min(at + UNSTORED_SLACK);
            assert_eq!(
                watch.check(at, beat, t0 + Duration::from_secs(k), timeout),
                None
            );
        }
        // stepping on while nothing it sends is stored: starved once past the timeout
        let far = at + 500 + UNSTORED_SLACK + 1;
        assert_eq!(watch.check(at, far, t0 + 40 * s, timeout), None);
        assert_eq!(watch.check(at, far + 64, t0 + 46 * s, timeout), Some(6 * s));
        // a restart counts its steps from 0 again
        watch.actor_started();
        assert_eq!(watch.check(at, 100, t0 + 47 * s, timeout), None);
        assert_eq!(watch.check(at, 200, t0 + 60 * s, timeout), None);
    }

    #[test]
    fn steps_stored_before_a_replay_crash_and_not_restored_count_as_lost() {
        let mut p = Progress::default();
        p.replay_status(status(500, 0));
        // the dead replay's last status arrives with the crash; its restart restored 300
        p.replay_crashed(Some(status(800, 0)));
        p.replay_status(status(300, 300));
        assert_eq!(p.lost_in_restarts, 500);
        p.replay_status(status(900, 300));
        assert_eq!(p.lost_in_restarts, 500);
        // two crashes before the restart's first status: counted once
        p.replay_crashed(None);
        p.replay_crashed(None);
        p.replay_status(status(850, 850));
        assert_eq!(p.lost_in_restarts, 550);

        let dir = tempfile::tempdir().unwrap();
        let actors = dir.path().join(ACTOR_REPORTS);
        std::fs::create_dir(&actors).unwrap();
        for (id, sent) in [(0, 700), (1, 500)] {
            let report = serde_json::json!({ "id": id, "sent_steps": sent, "dropped_steps": 0 });
            std::fs::write(
                actors.join(format!("actor-{id}-0.json")),
                report.to_string(),
            )
            .unwrap();
        }
        let replay = serde_json::json!({ "inserted": 600, "rejected": 1, "longest_turn_ms": 1.0 });
        std::fs::write(dir.path().join(REPLAY_REPORT), replay.to_string()).unwrap();
        let line = step_summary(dir.path(), p.restart_costs());
        assert!(
            line.contains("600 stored by the replay, 1 rejected"),
            "{line}"
        );
        assert!(line.contains("550 LOST in replay restarts"), "{line}");
        assert!(
            line.contains("50 sent neither stored nor counted"),
            "{line}"
        );
        assert!(line.contains("none dropped"), "{line}");
        let clean = step_summary(
            dir.path(),
            RestartCosts {
                lost: 600,
                ..RestartCosts::default()
            },
        );
        assert!(
            !clean.contains("neither") && !clean.contains("TWICE"),
            "{clean}"
        );
    }

    #[test]
    fn an_episode_rows_env_steps_never_pass_the_budget() {
        let mut p = Progress {
            actor_steps: vec![700, 500],
            ..Progress::default()
        };
        // the replay's count lags: the actors' own
        p.replay_status(status(1000, 0));
        assert_eq!(p.row_env_steps(3000), 1200);
        // the replay's when it is ahead, never past the budget
        p.replay_status(status(2000, 0));
        assert_eq!(p.row_env_steps(3000), 2000);
        p.actor_steps = vec![30_000, 30_009];
        assert_eq!(p.row_env_steps(3000), 3000);
    }

    #[test]
    fn steps_of_killed_actors_and_repeated_gradient_steps_are_counted() {
        let mut p = Progress {
            actor_beat_steps: vec![300, 200],
            ..Progress::default()
        };
        // actor 0 killed outright (no report), actor 1 exited after writing its report
        p.actor_died(0, false);
        p.actor_died(1, true);
        assert_eq!(
            (p.killed_actor_steps, p.actor_beat_steps.clone()),
            (300, vec![0, 0])
        );
        // the learner broadcast step 450 and died; its newest checkpoint is at 400
        p.grad_steps = 450;
        p.learner_died(400);
        // it died again before broadcasting: nothing more is counted
        p.learner_died(400);
        assert_eq!((p.repeated_grad_steps, p.grad_steps), (50, 400));
        let dir = tempfile::tempdir().unwrap();
        let actors = dir.path().join(ACTOR_REPORTS);
        std::fs::create_dir(&actors).unwrap();
        let report = serde_json::json!({ "id": 1, "sent_steps": 700, "dropped_steps": 0 });
        std::fs::write(actors.join("actor-1-0.json"), report.to_string()).unwrap();
        let line = step_summary(dir.path(), p.restart_costs());
        assert!(
            line.contains("the actors report 1000 sent (700, and 300 by killed actors"),
            "{line}"
        );
        assert!(line.contains("50 gradient steps TAKEN TWICE"), "{line}");
    }

    #[test]
    fn the_summary_counts_steps_past_the_budget_from_the_replays_own_file() {
        let dir = tempfile::tempdir().unwrap();
        let actors = dir.path().join(ACTOR_REPORTS);
        std::fs::create_dir(&actors).unwrap();
        for (id, sent) in [(0, 1700), (1, 1500)] {
            let report = serde_json::json!({ "id": id, "sent_steps": sent, "dropped_steps": 0 });
            std::fs::write(
                actors.join(format!("actor-{id}-0.json")),
                report.to_string(),
            )
            .unwrap();
        }
        let replay = serde_json::json!({ "inserted": 3000, "rejected": 0, "longest_turn_ms": 1.0 });
        std::fs::write(dir.path().join(REPLAY_REPORT), replay.to_string()).unwrap();
        let streams = ReplayStreams {
            stored_by_actor: vec![1600, 1400],
            surplus_by_actor: vec![100, 60],
            rejected_by_actor: vec![0, 0],
            inserted: 3000,
            env_steps: 3000,
        };
        ctxrace_run::results::write_json(&dir.path().join(REPLAY_STREAMS), &streams).unwrap();
        let line = step_summary(dir.path(), RestartCosts::default());
        assert!(
            line.starts_with("steps: 3000 stored by the replay (1600 / 1400 of each actor), 160 past the run's budget of 3000"),
            "{line}"
        );
        // 3200 sent, 3160 taken: 40 unaccounted for
        assert!(
            line.contains("the actors report 3200 sent (1700 / 1500)"),
            "{line}"
        );
        assert!(
            line.contains("; 40 sent neither stored nor counted"),
            "{line}"
        );
    }

    /// A cleanup that hangs (as on a truncated management segment) holds up no poll: the
    /// overrun is noted, a crash meanwhile asks for one more cleanup, which runs once the
    /// hung one ends.
    #[test]
    fn a_hanging_cleanup_never_blocks_the_supervisor() {
        let runs = Arc::new(AtomicU64::new(0));
        let counted = runs.clone();
        let mut cleaner = DeadNodeCleaner::with(
            move || {
                if counted.fetch_add(1, Ordering::SeqCst) == 0 {
                    std::thread::sleep(Duration::from_millis(600));
                }
                Ok(CleanupReport::default())
            },
            Duration::from_millis(100),
        );
        let start = Instant::now();
        cleaner.request();
        cleaner.poll();
        std::thread::sleep(Duration::from_millis(200));
        cleaner.poll();
        assert!(cleaner.overrun_logged && cleaner.running.is_some());
        cleaner.request();
        assert!(cleaner.again);
        assert!(
            start.elapsed() < Duration::from_millis(500),
            "a poll waited"
        );
        while runs.load(Ordering::SeqCst) < 2 || cleaner.running.is_some() {
            cleaner.poll();
            assert!(
                start.elapsed() < Duration::from_secs(10),
                "no second cleanup"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(!cleaner.again);
        assert_eq!(runs.load(Ordering::SeqCst), 2);
    }
}
