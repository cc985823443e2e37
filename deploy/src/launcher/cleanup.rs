//! Shared-memory cleanup: of the runs whose launcher died (before a run starts), of crashed
//! processes' nodes (while it runs, on a thread of its own) and of the run itself (at its end).

use anyhow::Result;
use ctxrace_config::validate::Causes;
use ctxrace_ipc::{cleanup, remove_dead_nodes, sweep_orphaned_runs, CleanupReport};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// How long a cleanup of dead nodes may take before the supervisor logs it as overrunning.
const CLEANUP_LIMIT: Duration = Duration::from_secs(5);

/// Removes the shared memory of runs whose launcher died ([`sweep_orphaned_runs`]), logging
/// what it removed and what it keeps because the run's processes live on.
pub(super) fn sweep_dead_runs() {
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
}

/// Removes the shared memory of the run with `prefix`, logging what it removed.
pub(super) fn remove_run(prefix: &str) {
    match cleanup(prefix) {
        Ok(report) => tracing::info!("shared memory of {prefix} removed: {report:?}"),
        Err(e) => tracing::warn!("cleaning up {prefix}: {}", Causes(&e)),
    }
}

/// Removes the resources of crashed processes' nodes on a thread of its own: a cleanup that
/// hangs (it sat two minutes on a management segment another user had truncated) must not keep
/// the supervisor from restarting actors or reaping the learner. One cleanup runs at a time; a
/// crash during one asks for another once it ends.
pub(super) struct DeadNodeCleaner {
    clean: std::sync::Arc<dyn Fn() -> Result<CleanupReport> + Send + Sync>,
    limit: Duration,
    running: Option<(Instant, mpsc::Receiver<Result<CleanupReport>>)>,
    overrun_logged: bool,
    again: bool,
}

impl DeadNodeCleaner {
    /// A cleaner of the dead nodes of the run with `prefix`.
    pub(super) fn new(prefix: &str) -> Self {
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
    pub(super) fn request(&mut self) {
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
    pub(super) fn poll(&mut self) {
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::Arc;

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
