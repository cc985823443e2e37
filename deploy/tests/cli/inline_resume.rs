//! `ctxrace train --inline --resume` continues a run killed (`kill -9`) at a random step exactly:
//! the resumed run's `episodes.csv`, cMask's `training_masks.csv` and every checkpoint file (the
//! best policy's and its copies kept at `keep_best_at` included) equal the uninterrupted run's
//! byte for byte. The replay is small enough to wrap, and each run is
//! killed twice, so that a resumed run is resumed again.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// A few hundred gradient steps on tiny networks, a resume point at every episode boundary and
/// a replay of 1,200 steps (it wraps after the prefill's 500 and as many more).
const CONFIG: &str = r#"
track = "generated:0"
[race]
rivals = 1
max_time = 20.0
[agent]
algo = "cmask"
[agent.dreamer]
units = 16
layers = 1
deter = 16
hidden = 16
stoch = 4
classes = 4
head_units = 16
head_layers = 1
batch = 2
length = 8
[agent.dreamer.mask]
units = 16
[train]
env_steps = 3000
prefill = 500
train_ratio = 0.1
checkpoint_every = 20
log_every = 2
threads = 1
resume_every_secs = 0
keep_best_at = [1500, 2500]
[replay]
capacity = 1200
"#;

fn train(config: &Path, run: &Path, algo: &str, resume: bool) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_ctxrace"));
    cmd.args([
        "train",
        config.to_str().unwrap(),
        "--inline",
        "--algo",
        algo,
    ])
    .args(["--run-dir", run.to_str().unwrap()])
    .env_remove("CTXRACE_TRACKS_DIR")
    .stdout(Stdio::null())
    .stderr(Stdio::piped());
    if resume {
        cmd.arg("--resume");
    }
    cmd
}

/// Every file of the run's checkpoints, by path below `checkpoints/`, `episodes.csv` and (cMask)
/// `training_masks.csv`.
fn records(run: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    for log in ["episodes.csv", "training_masks.csv"] {
        if let Ok(bytes) = std::fs::read(run.join(log)) {
            out.insert(PathBuf::from(log), bytes);
        }
    }
    let root = run.join("checkpoints");
    for dir in std::fs::read_dir(&root).unwrap() {
        let dir = dir.unwrap().path();
        for file in std::fs::read_dir(&dir).unwrap() {
            let file = file.unwrap().path();
            let name = file.strip_prefix(&root).unwrap().to_path_buf();
            out.insert(name, std::fs::read(&file).unwrap());
        }
    }
    out
}

/// Rows of `episodes.csv` (header excluded), 0 while it does not exist.
fn rows(run: &Path) -> usize {
    std::fs::read_to_string(run.join("episodes.csv"))
        .map(|t| t.lines().count().saturating_sub(1))
        .unwrap_or(0)
}

/// Starts the run (resuming it if `resume`) and kills it with SIGKILL once `episodes.csv`
/// holds `at` rows (the step it is at then is wherever that episode's end found it).
fn kill_after(config: &Path, run: &Path, algo: &str, resume: bool, at: usize) {
    let mut child = train(config, run, algo, resume).spawn().unwrap();
    let start = Instant::now();
    while rows(run) < at {
        if let Some(status) = child.try_wait().unwrap() {
            panic!("{algo}: the run ended ({status}) before {at} episodes");
        }
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "{algo}: no {at} episodes"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    child.kill().unwrap();
    child.wait().unwrap();
}

#[test]
fn a_run_killed_at_random_steps_and_resumed_writes_the_uninterrupted_runs_files() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("tiny.toml");
    std::fs::write(&config, CONFIG).unwrap();
    // a different pair of kill points each time, printed so that a failure can be replayed
    let seed = std::env::var("CTXRACE_RESUME_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .subsec_nanos() as u64
        });
    eprintln!("kill points from CTXRACE_RESUME_SEED={seed}");
    for (k, algo) in ["cmask", "sac"].into_iter().enumerate() {
        let whole = dir.path().join(format!("{algo}-whole"));
        let o = train(&config, &whole, algo, false).output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let episodes = rows(&whole);
        assert!(episodes > 20, "{algo}: {episodes} episodes");
        let kept = records(&whole);
        for step in [1500, 2500] {
            let manifest = PathBuf::from(format!("best-at-{step}/manifest.toml"));
            assert!(
                kept.contains_key(&manifest),
                "{algo}: no best policy kept at {step}"
            );
        }
        let masks = kept.contains_key(Path::new("training_masks.csv"));
        assert_eq!(
            masks,
            algo == "cmask",
            "{algo}: training_masks.csv only for cMask"
        );
        // two kill points in the run's episodes, the second after the first
        let mix = |x: u64| {
            x.wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407)
        };
        let (r1, r2) = (mix(seed + k as u64), mix(mix(seed + k as u64)));
        let first = 2 + (r1 >> 33) as usize % (episodes / 2);
        let second = first + 1 + (r2 >> 33) as usize % (episodes - first - 2);
        let cut = dir.path().join(format!("{algo}-cut"));
        kill_after(&config, &cut, algo, false, first);
        kill_after(&config, &cut, algo, true, second);
        let o = train(&config, &cut, algo, true).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{err}");
        assert!(err.contains("continues from its resume point"), "{err}");
        let (want, got) = (records(&whole), records(&cut));
        assert_eq!(
            want.keys().collect::<Vec<_>>(),
            got.keys().collect::<Vec<_>>(),
            "{algo} killed after {first} and {second} episodes: the files differ"
        );
        for (name, bytes) in &want {
            assert!(
                &got[name] == bytes,
                "{algo} killed after {first} and {second} episodes: {} differs",
                name.display()
            );
        }
        assert!(
            !cut.join("resume").exists(),
            "a finished run keeps no resume point"
        );
    }
}
