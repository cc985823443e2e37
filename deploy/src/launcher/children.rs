//! The run's child processes: each one's starts, its failures and restarts with back-off, its
//! stop.

use anyhow::{bail, Context as _, Result};
use ctxrace_config::validate::CONFIG_EXIT_CODE;
use ctxrace_config::SupervisorConfig;
use ctxrace_ipc::RunKey;
use ctxrace_run::lock::{die_with_parent, DirLock};
use ctxrace_run::run_dir::{open_append, ACTOR_REPORTS};
use std::path::Path;
use std::process::{Child, Command, ExitStatus};
use std::time::{Duration, Instant};

use super::stalls::Overdue;

/// Longest wait between two restarts of one process.
const MAX_BACKOFF: Duration = Duration::from_secs(30);
/// Time the children get to stop after SIGTERM before they are killed.
const STOP_GRACE: Duration = Duration::from_secs(30);

/// The run's processes: the replay, the learner and the actors.
pub(super) struct Children {
    /// The replay.
    pub(super) replay: Supervised,
    /// The learner.
    pub(super) learner: Supervised,
    /// The actors, by id.
    pub(super) actors: Vec<Supervised>,
}

impl Children {
    /// Stops whatever still runs, all at once (the replay takes the actors' last chunks,
    /// whatever its rate limiter says, until their senders have closed, then writes its
    /// snapshot), and waits for the actors, then for the learner and the replay
    /// ([`wait_all`]).
    pub(super) fn stop(&mut self) -> Result<()> {
        for p in self.actors.iter_mut() {
            p.stop();
        }
        self.learner.stop();
        self.replay.stop();
        wait_all(&mut self.actors)?;
        wait_all([&mut self.learner, &mut self.replay])
    }
}

/// What every start of a child inherits from the launcher: the run directory's lock, which it
/// holds too while it runs, and the run's key, handed over a pipe of its own
/// ([`RunKey::hand_to`]).
pub(super) struct Inherited {
    /// The run directory's lock.
    pub(super) lock: DirLock,
    /// The run's key.
    pub(super) key: RunKey,
}

impl Inherited {
    /// A second handle on the lock, with the key, for another child.
    pub(super) fn try_clone(&self) -> Result<Self> {
        Ok(Self {
            lock: self.lock.try_clone()?,
            key: self.key.clone(),
        })
    }
}

/// One supervised child process.
pub(super) struct Supervised {
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
    pub(super) retired: bool,
    /// When it was last (re)started.
    started_at: Instant,
    /// When its last sign of life (heartbeat, status) arrived, since its start.
    pub(super) last_sign: Option<Instant>,
    /// Since when it has made no progress (an actor's policy lagging, the learner taking no
    /// gradient step), within its current start.
    pub(super) stalled: Overdue,
    /// When it failed, within the restart window.
    failures: std::collections::VecDeque<Instant>,
    /// The run directory's lock and the run's key, which every start of it is handed.
    inherited: Inherited,
}

impl Supervised {
    /// The process `name`, a run of this binary with `args`, logging into `logs`, holding the
    /// lock and given the key `inherited` holds; due to start at once.
    pub(super) fn new(name: String, args: Vec<String>, logs: &Path, inherited: Inherited) -> Self {
        Self {
            inherited,
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

    /// Actor `id` of the run in `dir` ([`Supervised::new`]), continuing the incarnations of its
    /// earlier launches ([`earlier_actor_starts`]).
    pub(super) fn actor(
        id: usize,
        args: Vec<String>,
        dir: &Path,
        logs: &Path,
        inherited: Inherited,
    ) -> Self {
        let mut actor = Self::new(format!("actor {id}"), args, logs, inherited);
        actor.earlier_starts = earlier_actor_starts(dir, id);
        actor
    }

    /// Whether the process runs (a start of it has not been reaped).
    pub(super) fn running(&self) -> bool {
        self.child.is_some()
    }

    /// Its current (or last) start, counted across the run's launches from 0, as its report's
    /// name counts it.
    pub(super) fn incarnation(&self) -> u64 {
        self.earlier_starts + self.starts - 1
    }

    /// Starts the process if it is down, not retired and its restart is due; returns whether
    /// it started.
    pub(super) fn start_if_due(&mut self) -> Result<bool> {
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
    pub(super) fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// Starts the process (again), handing it the run's key over a fresh pipe; actors are told
    /// how often they ran before.
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
        self.inherited.lock.share_with(&mut cmd);
        // the launcher's copy of the pipe closes once the child has its own
        let _key_pipe = self
            .inherited
            .key
            .hand_to(&mut cmd)
            .with_context(|| format!("handing the run's key to {}", self.name))?;
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
    pub(super) fn exited(&mut self, status: ExitStatus, cfg: &SupervisorConfig) -> Result<()> {
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

    /// How long the process has sent no sign of life at `now`: zero before its first sign of
    /// this start (while it starts up).
    pub(super) fn quiet(&self, now: Instant) -> Duration {
        self.last_sign
            .map_or(Duration::ZERO, |t| now.saturating_duration_since(t))
    }

    /// Kills the process if its last sign of life (or its start, if none came) is older than
    /// the heartbeat timeout; it is then reaped as a crash.
    pub(super) fn kill_if_silent(&mut self, timeout: Duration) {
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
    pub(super) fn kill(&mut self, why: &str) {
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
    pub(super) fn reap(&mut self) -> Result<Option<ExitStatus>> {
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
fn wait_all<'a>(procs: impl IntoIterator<Item = &'a mut Supervised>) -> Result<()> {
    let deadline = Instant::now() + STOP_GRACE;
    for p in procs {
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
