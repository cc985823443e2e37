//! What a run asks of the machine, checked before anything starts: the memory a run needs
//! estimated from the agent's sizes ([`MemoryEstimate`]) and, with the threads, held against the
//! machine ([`check_machine`]).

use crate::agents::AlgoKind;
use crate::experiment::ExperimentConfig;

/// Why a run does not fit this machine.
#[derive(Debug, thiserror::Error)]
pub enum ResourceError {
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
    /// Many more actor processes than the machine has cores.
    #[error(
        "{actors} actor processes on {cores} cores: more than {MAX_ACTORS_PER_CORE} a core, they \
         would mostly wait for each other and the learner; give at most {} (--actors), or pass \
         --oversubscribe to run them anyway",
        MAX_ACTORS_PER_CORE * .cores
    )]
    Actors {
        /// The actors asked for.
        actors: usize,
        /// The machine's cores.
        cores: usize,
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

/// The memory a run needs at least, by where it goes (bytes): the replay buffer at capacity,
/// the learner's parameters with their gradients and Adam moments and its largest activations,
/// the actors' policies, and the map of each process that loads the track.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MemoryEstimate {
    /// The replay buffer, full.
    pub replay: u64,
    /// The learner: parameters ×4 (weights, gradients, two moments) and one step's activations.
    pub learner: u64,
    /// Every actor's acting policy.
    pub actors: u64,
    /// The track's map in every process that loads it (each actor and the launcher): a byte a
    /// pixel held, and 4 more while its image is decoded (RGBA).
    pub maps: u64,
}

/// Bytes a map pixel takes in a process that loads it, at the peak of its loading.
const MAP_BYTES_PER_PIXEL: u64 = 5;

impl MemoryEstimate {
    /// The estimate for `cfg` with `actors` actor processes on a track whose map has
    /// `map_pixels` pixels (0 for a procedural track) (float arithmetic: a size that overflows
    /// an integer comes out as the largest `u64`).
    pub fn of(cfg: &ExperimentConfig, actors: usize, map_pixels: u64) -> Self {
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
            maps: map_pixels
                .saturating_mul(MAP_BYTES_PER_PIXEL)
                .saturating_mul(actors as u64 + 1),
        }
    }

    /// The whole run (bytes).
    pub fn total(&self) -> u64 {
        self.replay
            .saturating_add(self.learner)
            .saturating_add(self.actors)
            .saturating_add(self.maps)
    }
}

impl std::fmt::Display for MemoryEstimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "replay {}, learner {}, actors {}, maps {}",
            gib(self.replay),
            gib(self.learner),
            gib(self.actors),
            gib(self.maps)
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

/// Actor processes a core may run without `oversubscribe`.
pub const MAX_ACTORS_PER_CORE: usize = 4;

/// Checks that a run of `cfg` with `actors` actors on a track whose map has `map_pixels`
/// pixels fits `machine`: its memory estimate within
/// the machine's memory, learner threads set in the config within its cores, and at most
/// [`MAX_ACTORS_PER_CORE`] actors a core unless `oversubscribe`.
pub fn check_machine(
    cfg: &ExperimentConfig,
    actors: usize,
    map_pixels: u64,
    machine: &Machine,
    oversubscribe: bool,
) -> Result<(), ResourceError> {
    if !oversubscribe && actors > MAX_ACTORS_PER_CORE * machine.cores {
        return Err(ResourceError::Actors {
            actors,
            cores: machine.cores,
        });
    }
    if let Some(threads) = cfg.train.threads.filter(|&t| t > machine.cores) {
        return Err(ResourceError::Threads {
            threads,
            cores: machine.cores,
        });
    }
    let estimate = MemoryEstimate::of(cfg, actors, map_pixels);
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
    fn a_run_larger_than_the_machine_is_refused_with_its_estimate() {
        let small = Machine {
            memory: 8 << 30,
            cores: 2,
        };
        let paper = cfg("[agent]\nalgo = \"cmask\"\n").unwrap();
        check_machine(&paper, 2, 0, &small, false).unwrap();
        let big =
            cfg("[agent]\nalgo = \"cmask\"\n[agent.dreamer]\nhorizon = 1000\nunits = 16384\n")
                .unwrap();
        let err = check_machine(&big, 2, 0, &small, false)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("the run needs at least") && err.contains("8.0 GiB"),
            "{err}"
        );
        let threads = cfg("[train]\nthreads = 100000\n").unwrap();
        let err = check_machine(&threads, 1, 0, &small, false)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("threads = 100000 is more than the 2 cores"),
            "{err}"
        );
        // 64 actors on 2 cores: refused unless asked for
        let err = check_machine(&paper, 64, 0, &small, false)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("64 actor processes on 2 cores") && err.contains("--oversubscribe"),
            "{err}"
        );
        check_machine(&paper, 8, 0, &small, false).unwrap();
        check_machine(&paper, 64, 0, &small, true).unwrap();
        // a map of 10,000 x 10,000 pixels (the largest image a track may have) in 8 actors and
        // the launcher: 4.2 GiB, counted
        let maps = MemoryEstimate::of(&paper, 8, 100_000_000);
        assert_eq!(maps.maps, 4_500_000_000);
        let lone = Machine {
            memory: 4 << 30,
            cores: 2,
        };
        let err = check_machine(&paper, 8, 100_000_000, &lone, false)
            .unwrap_err()
            .to_string();
        assert!(err.contains("maps 4.2 GiB"), "{err}");
        check_machine(&paper, 8, 1_000_000, &lone, false).unwrap();
        assert!(Machine::this().memory > 0 && Machine::this().cores > 0);
    }
}
