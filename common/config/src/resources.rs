//! What a run asks of the machine, checked before anything starts: every size and count of an
//! experiment within a sane bound ([`check_bounds`], part of [`ExperimentConfig::validate_run`]),
//! the replay snapshot inside the run folder, the memory a run needs estimated from the agent's
//! sizes ([`MemoryEstimate`]) and, with the threads, held against the machine
//! ([`check_machine`]); and config files read with a size bound, never echoed
//! ([`read_config_text`]).

use crate::agents::AlgoKind;
use crate::experiment::ExperimentConfig;
use crate::validate::{in_range, ValueError};
use std::io::Read;
use std::ops::Bound;
use std::path::{Component, Path, PathBuf};

/// The largest config or matrix file read (bytes): ctxrace's own are a few kilobytes.
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;
/// The most gradient steps per env step (`[train] train_ratio`; the paper's: 1, its SAC: 2).
pub const MAX_TRAIN_RATIO: f64 = 1000.0;
/// The longest episode (`[race] max_time`, s; the paper's: 240).
pub const MAX_EPISODE_SECS: f64 = 3600.0;
/// The widest layer of any network (units, hidden sizes; the paper's widest: 512).
pub const MAX_WIDTH: usize = 16384;
/// The deepest MLP (layers).
pub const MAX_LAYERS: usize = 64;
/// The longest imagination horizon (`[agent] dreamer.horizon`; the paper's: 15).
pub const MAX_HORIZON: usize = 1000;
/// The most env steps of a run (`[train] env_steps`; the paper's: 100 000).
pub const MAX_ENV_STEPS: u64 = 10_000_000_000;

/// Why a config cannot be read, or a run does not fit this machine.
#[derive(Debug, thiserror::Error)]
pub enum ResourceError {
    /// The file could not be opened or read.
    #[error("reading {}: {cause}", .path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// The file is larger than a config may be (its content is not shown).
    #[error(
        "{} holds {bytes} bytes, more than the {} a config may hold; is it the right file?",
        .path.display(),
        MAX_CONFIG_BYTES
    )]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Its size.
        bytes: u64,
    },
    /// The file is not UTF-8 text (its content is not shown).
    #[error("{} is not UTF-8 text; is it the right file?", .path.display())]
    NotText {
        /// The file.
        path: PathBuf,
    },
    /// The run needs more memory than the machine has.
    #[error(
        "the run needs at least {} of memory ({estimate}), more than this machine's {}; lower \
         [replay] capacity, the agent's widths ([agent] dreamer.units, deter, hidden, \
         head_units, sac.hidden), dreamer.horizon or the batch, or run on a larger machine",
        gib(.estimate.total()),
        gib(*.memory)
    )]
    Memory {
        /// What the run needs.
        estimate: MemoryEstimate,
        /// The machine's memory (bytes).
        memory: u64,
    },
    /// More learner threads than the machine has cores.
    #[error(
        "[train] threads = {threads} is more than the {cores} cores of this machine; give at \
         most {cores} (--threads), or leave it out for the algorithm's default"
    )]
    Threads {
        /// The threads asked for.
        threads: usize,
        /// The machine's cores.
        cores: usize,
    },
}

/// `bytes` in GiB, for messages.
fn gib(bytes: u64) -> String {
    format!("{:.1} GiB", bytes as f64 / (1u64 << 30) as f64)
}

/// Reads a config file as text: a regular file of at most [`MAX_CONFIG_BYTES`] (checked before
/// it is read, and again while reading a file that grows), UTF-8; the errors name the file and
/// never show its content.
pub fn read_config_text(path: &Path) -> Result<String, ResourceError> {
    let read_error = |cause| ResourceError::Read {
        path: path.to_path_buf(),
        cause,
    };
    let file = std::fs::File::open(path).map_err(read_error)?;
    let meta = file.metadata().map_err(read_error)?;
    if meta.is_dir() {
        return Err(read_error(std::io::Error::other("it is a folder")));
    }
    let too_large = |bytes| ResourceError::TooLarge {
        path: path.to_path_buf(),
        bytes,
    };
    if meta.len() > MAX_CONFIG_BYTES {
        return Err(too_large(meta.len()));
    }
    let mut bytes = Vec::new();
    file.take(MAX_CONFIG_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(read_error)?;
    if bytes.len() as u64 > MAX_CONFIG_BYTES {
        return Err(too_large(bytes.len() as u64));
    }
    String::from_utf8(bytes).map_err(|_| ResourceError::NotText {
        path: path.to_path_buf(),
    })
}

/// Checks that every size and count of `cfg` lies within its sane bound, and that `[replay]
/// snapshot_path` stays inside the run folder; the error names the key, its value and the fix.
pub fn check_bounds(cfg: &ExperimentConfig) -> Result<(), ValueError> {
    let t = &cfg.train;
    in_range(
        "[train] train_ratio",
        t.train_ratio,
        (Bound::Excluded(0.0), Bound::Included(MAX_TRAIN_RATIO)),
        "it is the gradient steps per env step (the paper: 1)",
    )?;
    in_range(
        "[train] env_steps",
        t.env_steps,
        ..=MAX_ENV_STEPS,
        "the paper trains 100000",
    )?;
    in_range(
        "[race] max_time",
        cfg.race.max_time,
        (Bound::Excluded(0.0), Bound::Included(MAX_EPISODE_SECS)),
        "the seconds an episode lasts at most (the paper: 240)",
    )?;
    let (s, d) = (&cfg.agent.sac, &cfg.agent.dreamer);
    let widths = [
        ("[agent] sac.hidden", s.hidden),
        ("[agent] dreamer.units", d.units),
        ("[agent] dreamer.deter", d.deter),
        ("[agent] dreamer.hidden", d.hidden),
        ("[agent] dreamer.head_units", d.head_units),
        ("[agent] dreamer.mask.units", d.mask.units),
        ("[agent] dreamer.stoch", d.stoch),
        ("[agent] dreamer.classes", d.classes),
        ("[agent] dreamer.bins", d.bins),
    ];
    for (key, width) in widths {
        in_range(
            key,
            width,
            1..=MAX_WIDTH,
            "the paper's widest layer has 512",
        )?;
    }
    let depths = [
        ("[agent] sac.layers", s.layers),
        ("[agent] dreamer.layers", d.layers),
        ("[agent] dreamer.head_layers", d.head_layers),
        ("[agent] dreamer.mask.layers", d.mask.layers),
    ];
    for (key, layers) in depths {
        in_range(key, layers, ..=MAX_LAYERS, "the paper's MLPs have 2 to 5")?;
    }
    in_range(
        "[agent] dreamer.horizon",
        d.horizon,
        1..=MAX_HORIZON,
        "the imagined steps per start (the paper: 15)",
    )?;
    if let Some(path) = &cfg.replay.snapshot_path {
        let inside = path.components().all(|c| matches!(c, Component::Normal(_)));
        if !inside || path.as_os_str().is_empty() {
            return Err(ValueError::OutOfRange {
                key: "[replay] snapshot_path".into(),
                value: format!("{path:?}"),
                bounds: "a file inside the run folder (relative, without ..)".into(),
                fix: "name it relative to the run folder, e.g. \"replay.snapshot\", or leave it \
                      out"
                .into(),
            });
        }
    }
    Ok(())
}

/// The memory a run needs at least, by where it goes (bytes): the replay buffer at capacity,
/// the learner's parameters with their gradients and Adam moments and its largest activations,
/// and the actors' policies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MemoryEstimate {
    /// The replay buffer, full.
    pub replay: u64,
    /// The learner: parameters ×4 (weights, gradients, two moments) and one step's activations.
    pub learner: u64,
    /// Every actor's acting policy.
    pub actors: u64,
}

impl MemoryEstimate {
    /// The estimate for `cfg` with `actors` actor processes (float arithmetic: a size that
    /// overflows an integer comes out as the largest `u64`).
    pub fn of(cfg: &ExperimentConfig, actors: usize) -> Self {
        const F32: f64 = 4.0;
        let beams = cfg.race.lidar.beams as f64;
        let act = 2.0;
        let ctx = crate::agents::CONTEXT_DIM as f64;
        let mlp = |input: f64, width: f64, layers: f64, output: f64| {
            input * width + (layers - 1.0).max(0.0) * width * width + width * output
        };
        let replay = cfg.replay.capacity as f64 * (F32 * (beams + act + 5.0) + 9.0);
        let (params, policy, activations) = match cfg.agent.algo {
            AlgoKind::Sac => {
                let s = &cfg.agent.sac;
                let (w, l) = (s.hidden as f64, s.layers as f64);
                let obs = beams * s.frames as f64 + ctx;
                let actor = mlp(obs, w, l, 2.0 * act);
                let critic = mlp(obs + act, w, l, 1.0);
                // the actor, two critics and their targets
                let params = actor + 4.0 * critic;
                let rows = s.batch_size as f64;
                (params, actor, rows * l * w * 9.0)
            }
            AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => {
                let d = &cfg.agent.dreamer;
                let (units, layers) = (d.units as f64, d.layers as f64);
                let (deter, hidden) = (d.deter as f64, d.hidden as f64);
                let z = (d.stoch * d.classes) as f64;
                let feat = deter + z;
                let (hu, hl, bins) = (d.head_units as f64, d.head_layers as f64, d.bins as f64);
                let encoder = mlp(beams + ctx, units, layers, units);
                let decoder = mlp(feat, units, layers, beams);
                let rssm = 3.0 * deter * (hidden + deter)
                    + (z + act + ctx) * hidden
                    + deter * hidden
                    + (deter + units) * hidden
                    + 2.0 * hidden * z;
                let actor = mlp(feat + ctx, hu, hl, 2.0 * act);
                // reward, continue, critic and slow critic
                let heads = 4.0 * mlp(feat + ctx, hu, hl, bins) + actor;
                let mask = 4.0 * mlp(feat, d.mask.units as f64, d.mask.layers as f64, 4.0);
                let params = encoder + decoder + rssm + heads + mask;
                let rows = (d.batch * d.length) as f64;
                let seq_row = 6.0 * layers * units + 6.0 * deter + 4.0 * hidden + 4.0 * z;
                let img_row = 6.0 * deter + 3.0 * hidden + 3.0 * z + 8.0 * hl * hu + 3.0 * bins;
                let activations = rows * seq_row + rows * d.horizon as f64 * img_row;
                (params, encoder + rssm + actor, activations)
            }
        };
        let bytes = |floats: f64| (floats * F32).min(u64::MAX as f64) as u64;
        Self {
            replay: replay.min(u64::MAX as f64) as u64,
            learner: bytes(4.0 * params + activations),
            actors: bytes(policy * actors as f64),
        }
    }

    /// The whole run (bytes).
    pub fn total(&self) -> u64 {
        self.replay
            .saturating_add(self.learner)
            .saturating_add(self.actors)
    }
}

impl std::fmt::Display for MemoryEstimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "replay {}, learner {}, actors {}",
            gib(self.replay),
            gib(self.learner),
            gib(self.actors)
        )
    }
}

/// The machine a run is launched on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Machine {
    /// Memory (bytes): the machine's, or its cgroup's limit when lower.
    pub memory: u64,
    /// Cores this process may use.
    pub cores: usize,
}

impl Machine {
    /// This machine, as Linux reports it (`/proc/meminfo`, the cgroup's `memory.max`, the
    /// process's CPU set); unbounded memory where it cannot be read.
    pub fn this() -> Self {
        let meminfo = std::fs::read_to_string("/proc/meminfo").unwrap_or_default();
        let total = meminfo
            .lines()
            .find_map(|l| l.strip_prefix("MemTotal:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            .map_or(u64::MAX, |kb| kb.saturating_mul(1024));
        let cgroup = std::fs::read_to_string("/sys/fs/cgroup/memory.max")
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok())
            .unwrap_or(u64::MAX);
        Self {
            memory: total.min(cgroup),
            cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        }
    }
}

/// Checks that a run of `cfg` with `actors` actors fits `machine`: its memory estimate within
/// the machine's memory, and learner threads set in the config within its cores.
pub fn check_machine(
    cfg: &ExperimentConfig,
    actors: usize,
    machine: &Machine,
) -> Result<(), ResourceError> {
    if let Some(threads) = cfg.train.threads.filter(|&t| t > machine.cores) {
        return Err(ResourceError::Threads {
            threads,
            cores: machine.cores,
        });
    }
    let estimate = MemoryEstimate::of(cfg, actors);
    if estimate.total() > machine.memory {
        return Err(ResourceError::Memory {
            estimate,
            memory: machine.memory,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(extra: &str) -> Result<ExperimentConfig, String> {
        ExperimentConfig::from_toml(extra, "test").map_err(|e| e.to_string())
    }

    #[test]
    fn sizes_and_counts_beyond_their_bounds_are_refused_by_key() {
        for (toml, says) in [
            (
                "[train]\ntrain_ratio = 1e9\n",
                "[train] train_ratio = 1000000000 must be",
            ),
            ("[race]\nmax_time = 1e300\n", "[race] max_time = 1e300 must"),
            (
                "[agent]\nalgo = \"cmask\"\n[agent.dreamer]\nhorizon = 100000000\n",
                "horizon",
            ),
            (
                "[agent]\nalgo = \"cmask\"\n[agent.dreamer]\nunits = 1000000\n",
                "dreamer.units",
            ),
            ("[train]\nenv_steps = 100000000000\n", "[train] env_steps"),
            (
                "[replay]\nsnapshot_path = \"/tmp/other/replay.snapshot\"\n",
                "inside the run",
            ),
            (
                "[replay]\nsnapshot_path = \"../other/replay.snapshot\"\n",
                "relative, without ..",
            ),
        ] {
            let err = cfg(toml).unwrap_err();
            assert!(err.contains(says), "{toml}: {err}");
        }
        cfg("[replay]\nsnapshot_path = \"snapshots/replay.snapshot\"\n").unwrap();
        cfg("").unwrap();
    }

    #[test]
    fn a_run_larger_than_the_machine_is_refused_with_its_estimate() {
        let small = Machine {
            memory: 8 << 30,
            cores: 2,
        };
        let paper = cfg("[agent]\nalgo = \"cmask\"\n").unwrap();
        check_machine(&paper, 2, &small).unwrap();
        let big =
            cfg("[agent]\nalgo = \"cmask\"\n[agent.dreamer]\nhorizon = 1000\nunits = 16384\n")
                .unwrap();
        let err = check_machine(&big, 2, &small).unwrap_err().to_string();
        assert!(
            err.contains("the run needs at least") && err.contains("8.0 GiB"),
            "{err}"
        );
        let threads = cfg("[train]\nthreads = 100000\n").unwrap();
        let err = check_machine(&threads, 1, &small).unwrap_err().to_string();
        assert!(
            err.contains("threads = 100000 is more than the 2 cores"),
            "{err}"
        );
        assert!(Machine::this().memory > 0 && Machine::this().cores > 0);
    }

    #[test]
    fn config_files_are_read_bounded_and_never_echoed() {
        let dir = tempfile::tempdir().unwrap();
        let big = dir.path().join("big.toml");
        let line = format!("track = \"{}\"\n", "x".repeat(2 << 20));
        std::fs::write(&big, &line).unwrap();
        let err = read_config_text(&big).unwrap_err().to_string();
        assert!(
            err.contains("more than the 1048576") && !err.contains("xxxx"),
            "{err}"
        );
        let binary = dir.path().join("bin.toml");
        std::fs::write(&binary, [0xff, 0xfe, b'a']).unwrap();
        let err = read_config_text(&binary).unwrap_err().to_string();
        assert!(err.contains("not UTF-8"), "{err}");
        let err = read_config_text(dir.path()).unwrap_err().to_string();
        assert!(err.contains("folder"), "{err}");
        std::fs::write(&big, "track = \"f1_esp\"\n").unwrap();
        assert_eq!(read_config_text(&big).unwrap(), "track = \"f1_esp\"\n");
    }
}
