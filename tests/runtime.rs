//! Cross-process tests of the training runtime: the real `ctxrace` binary as launcher, replay,
//! learner and actor processes over iceoryx2 shared memory (each run on its own prefix, which
//! the launcher removes at the end).

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A small SAC run on the generated track: fast gradient steps, a tight rate limiter, and
/// episodes of at most 100 decisions, so that every actor reaches many episode boundaries (where
/// it loads new weights) whatever the policy learns.
fn config(env_steps: u64) -> String {
    format!(
        r#"track = "generated:0"
[race]
rivals = 1
max_time = 10.0
[agent]
algo = "sac"
[agent.sac]
hidden = 32
batch_size = 32
[train]
env_steps = {env_steps}
prefill = 400
train_ratio = 0.25
policy_every = 10
checkpoint_every = 100
log_every = 50
threads = 1
[replay]
error_buffer_steps = 64
snapshot_every_secs = 1
"#
    )
}

/// Starts `ctxrace train` with `actors` actors in `dir/run`.
fn launch(dir: &Path, env_steps: u64, actors: usize) -> (Child, PathBuf) {
    launch_with(dir, env_steps, actors, "")
}

/// [`launch`] with `extra` TOML appended to the experiment.
fn launch_with(dir: &Path, env_steps: u64, actors: usize, extra: &str) -> (Child, PathBuf) {
    let cfg = dir.join("exp.toml");
    std::fs::write(&cfg, config(env_steps) + extra).unwrap();
    let run = dir.join("run");
    let child = Command::new(env!("CARGO_BIN_EXE_ctxrace"))
        .arg("train")
        .arg(&cfg)
        .args(["--actors", &actors.to_string(), "--run-dir"])
        .arg(&run)
        .env("RUST_LOG", "warn")
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    (child, run)
}

/// Waits for the launcher; returns its stderr.
fn finish(child: Child, limit: Duration) -> String {
    let pid = child.id();
    let start = Instant::now();
    let waiter = std::thread::spawn(move || child.wait_with_output().unwrap());
    while !waiter.is_finished() {
        if start.elapsed() > limit {
            unsafe { libc::kill(pid as i32, libc::SIGTERM) };
            let out = waiter.join().unwrap();
            panic!(
                "launcher did not finish in {limit:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let out = waiter.join().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "launcher failed: {stderr}");
    stderr
}

fn json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// The actor reports of a run, by file name.
fn actor_reports(run: &Path) -> Vec<(String, Value)> {
    let mut v: Vec<_> = std::fs::read_dir(run.join("actors"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                json(&p),
            )
        })
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

/// Checks a clean run: counts reconcile, versions increase, the train ratio holds.
fn check_clean_run(run: &Path, actors: usize) {
    let replay = json(&run.join("replay-status.json"));
    let reports = actor_reports(run);
    assert_eq!(reports.len(), actors, "{reports:?}");
    let sent: u64 = reports
        .iter()
        .map(|(_, r)| r["sent_steps"].as_u64().unwrap())
        .sum();
    assert_eq!(
        replay["inserted"].as_u64().unwrap(),
        sent,
        "{replay} vs {reports:?}"
    );
    assert_eq!(replay["rejected"].as_u64().unwrap(), 0);
    // every actor loads strictly increasing versions; the replay does not share its intake
    // fairly between actors (one may supply most steps while another waits in backpressure and
    // reaches few episode boundaries), so only the run as a whole must see several
    let mut most = 0;
    for (name, r) in &reports {
        let versions: Vec<u64> = r["versions"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        assert!(!versions.is_empty(), "{name}: no weights loaded");
        assert!(
            versions.windows(2).all(|w| w[0] < w[1]),
            "{name}: {versions:?}"
        );
        most = most.max(versions.len());
    }
    assert!(most >= 2, "no actor loaded a second version: {reports:?}");
    // Reverb's ratio: samples per insert beyond the minimum fill, while the learner trained
    let inserted = replay["inserted_at_last_batch"].as_f64().unwrap();
    let sampled = replay["sampled"].as_f64().unwrap();
    let min_fill = replay["min_fill"].as_f64().unwrap();
    let spi = replay["samples_per_insert"].as_f64().unwrap();
    let ratio = sampled / (inserted - min_fill);
    assert!(
        (ratio / spi - 1.0).abs() < 0.1,
        "ratio {ratio} vs {spi}: {replay}"
    );
    assert!(run.join("checkpoints").read_dir().unwrap().count() >= 1);
    // the learner smoothed the returns of the episodes the policy drove and kept the best
    let best = std::fs::read_to_string(run.join("checkpoints/best/best.toml")).unwrap();
    let best: toml::Table = toml::from_str(&best).unwrap();
    assert!(best["episodes"].as_integer().unwrap() >= 1, "{best}");
    assert!(run.join("checkpoints/best/policy.safetensors").is_file());
    // TensorBoard event files of the learner and the launcher
    let tags: std::collections::HashSet<String> = ctxrace_learner::tensorboard::event_files(run)
        .iter()
        .flat_map(|f| ctxrace_learner::tensorboard::read_scalars(f).unwrap())
        .map(|r| r.tag)
        .collect();
    for tag in [
        "episode/progress",
        "episode/overtakes",
        "grad_steps_per_second",
    ] {
        assert!(tags.contains(tag), "no {tag} in {tags:?}");
    }
    // every process logs into the run directory (at RUST_LOG=warn a clean run's logs are empty)
    for role in ["replay", "learner", &format!("actor-{}", actors - 1)] {
        assert!(
            run.join(format!("logs/{role}.log")).exists(),
            "no log of {role}"
        );
    }
    assert!(
        std::fs::read_to_string(run.join("episodes.csv"))
            .unwrap()
            .lines()
            .count()
            > 10
    );
}

/// No shared-memory file of the launcher with `pid` is left behind.
fn assert_no_leftovers(pid: u32) {
    let prefix = format!("ctxrace_{pid}-");
    for dir in ["/dev/shm", "/tmp/iceoryx2"] {
        let Ok(entries) = std::fs::read_dir(dir) else {
            continue;
        };
        let left: Vec<String> = entries
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains(&prefix))
            .collect();
        assert!(left.is_empty(), "{dir}: {left:?}");
    }
}

#[test]
fn two_runs_side_by_side_reconcile_exactly() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let (child_a, run_a) = launch(a.path(), 6000, 3);
    let (child_b, run_b) = launch(b.path(), 4000, 2);
    let (pid_a, pid_b) = (child_a.id(), child_b.id());
    finish(child_a, Duration::from_secs(400));
    finish(child_b, Duration::from_secs(400));
    check_clean_run(&run_a, 3);
    check_clean_run(&run_b, 2);
    assert_no_leftovers(pid_a);
    assert_no_leftovers(pid_b);
}

/// The pid of a process of the run in `role` that is not in `not`.
fn find_pid(run: &Path, role: &str, not: &[u32]) -> Option<u32> {
    let run = run.to_string_lossy();
    std::fs::read_dir("/proc").ok()?.find_map(|e| {
        let pid: u32 = e.ok()?.file_name().to_str()?.parse().ok()?;
        let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
        let args: Vec<String> = cmd
            .split(|&b| b == 0)
            .map(|a| String::from_utf8_lossy(a).into_owned())
            .collect();
        let hit = args.get(1).is_some_and(|a| a == role)
            && args.iter().any(|a| a == run.as_ref())
            && !not.contains(&pid);
        hit.then_some(pid)
    })
}

/// Waits until `f` returns something.
fn wait_for<T>(what: &str, limit: Duration, mut f: impl FnMut() -> Option<T>) -> T {
    let start = Instant::now();
    loop {
        if let Some(x) = f() {
            return x;
        }
        assert!(start.elapsed() < limit, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn kill9(pid: u32) {
    unsafe { libc::kill(pid as i32, libc::SIGKILL) };
}

#[test]
fn killed_processes_are_restarted_and_training_completes() {
    let dir = tempfile::tempdir().unwrap();
    // long enough that the three kills and restarts happen well before the learner's target
    let env_steps = 12_000;
    let supervisor = "[supervisor]\nheartbeat_timeout_secs = 5\n";
    let (child, run) = launch_with(dir.path(), env_steps, 3, supervisor);
    let minute = Duration::from_secs(60);
    // wait for the first checkpoint, then kill an actor, the learner and the replay in turn
    wait_for("a checkpoint", 3 * minute, || {
        run.join("checkpoints").read_dir().ok()?.next().map(|_| ())
    });
    let mut actors = Vec::new();
    while actors.len() < 3 {
        actors.push(wait_for("actors", minute, || {
            find_pid(&run, "actor", &actors)
        }));
    }
    kill9(actors[1]);
    wait_for("the actor's restart", minute, || {
        find_pid(&run, "actor", &actors)
    });
    let learner = wait_for("learner", minute, || find_pid(&run, "learner", &[]));
    kill9(learner);
    wait_for("the learner's restart", minute, || {
        find_pid(&run, "learner", &[learner])
    });
    let replay = wait_for("replay", minute, || find_pid(&run, "replay", &[]));
    kill9(replay);
    wait_for("the replay's restart", minute, || {
        find_pid(&run, "replay", &[replay])
    });
    // a hung actor (stopped: alive but silent) is killed and restarted after 5 s
    let hung = actors[0];
    unsafe { libc::kill(hung as i32, libc::SIGSTOP) };
    wait_for("the hung actor to be killed", minute, || {
        std::fs::metadata(format!("/proc/{hung}"))
            .is_err()
            .then_some(())
    });
    let stderr = finish(child, 6 * minute);
    assert!(stderr.contains("sent no sign of life"), "{stderr}");
    for role in ["actor 1", "learner", "replay"] {
        assert!(
            stderr.contains(&format!("{role} exited")),
            "no restart of {role} reported: {stderr}"
        );
    }
    // the learner reached its target across the restart (it resumed from a checkpoint)
    let last = std::fs::read_dir(run.join("checkpoints"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .max()
        .unwrap();
    assert_eq!(
        last,
        format!("step-{:010}", ((env_steps - 400) as f64 * 0.25) as u64)
    );
    // a restarted actor reported under a later incarnation
    assert!(actor_reports(&run)
        .iter()
        .any(|(n, _)| !n.ends_with("-0.json")));
}

#[test]
fn a_process_that_keeps_failing_stops_the_run_with_its_reason() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("exp.toml");
    let text = config(2000) + "[supervisor]\nmax_restarts = 1\n";
    std::fs::write(&cfg, text).unwrap();
    let run = dir.path().join("run");
    // a damaged replay snapshot: the replay fails at every start
    std::fs::create_dir_all(&run).unwrap();
    std::fs::write(run.join("replay.snapshot"), b"CTXRPLY\0 not a snapshot").unwrap();
    let started = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_ctxrace"))
        .arg("train")
        .arg(&cfg)
        .args(["--actors", "1", "--run-dir"])
        .arg(&run)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    for needle in [
        "replay exited",
        "2nd failure",
        "max_restarts",
        "restoring replay snapshot",
    ] {
        assert!(stderr.contains(needle), "no '{needle}' in: {stderr}");
    }
    assert!(
        started.elapsed() < Duration::from_secs(60),
        "{:?}",
        started.elapsed()
    );
}
