//! The files of a run directory, named once for the processes that write them and the commands
//! that read them (`train` and its roles write, `eval`, `report`, `sweep` and `race` read).
//!
//! ```text
//! runs/<algo>-<track>-<rivals>r-s<seed>/
//!   config.toml            CONFIG_FILE: the experiment as trained (eval and report reuse it)
//!   .lock                  LOCK_FILE: held by the process writing the directory
//!   status.json            STATUS_FILE: the launcher's live counters
//!   replay-status.json     REPLAY_REPORT: the replay's final counters
//!   replay.snapshot        REPLAY_SNAPSHOT: the replay buffer, for restarts
//!   actors/actor-<id>-<n>.json   ACTOR_REPORTS: each actor incarnation's final counters
//!   logs/<role>.log        LOGS: each process's log
//!   episodes.csv           TRAINING_EPISODES: one row per finished training episode
//!   metrics.csv, metrics.jsonl   METRICS_CSV, METRICS_JSONL: the learner's metrics
//!   events.out.tfevents.*  TensorBoard event files
//!   checkpoints/step-<N>/  CHECKPOINTS: policy.safetensors (POLICY_FILE), agent.toml
//!                          (AGENT_FILE), the optimisers and the counters
//!   checkpoints/best/      BEST_DIR: the policy of the best training return
//!   eval/                  EVAL_DIR: meta.json (EVAL_META), job.json (EVAL_JOB), episodes.csv
//!                          (EVAL_EPISODES), contexts.csv and contexts.json (EVAL_CONTEXTS_*)
//! ```

/// The experiment as trained.
pub const CONFIG_FILE: &str = "config.toml";
/// The lock file of a directory being written.
pub const LOCK_FILE: &str = ".lock";
/// The launcher's live status.
pub const STATUS_FILE: &str = "status.json";
/// The replay's final counters.
pub const REPLAY_REPORT: &str = "replay-status.json";
/// The replay buffer's snapshot.
pub const REPLAY_SNAPSHOT: &str = "replay.snapshot";
/// The folder of the actors' final reports.
pub const ACTOR_REPORTS: &str = "actors";
/// The folder of the processes' logs.
pub const LOGS: &str = "logs";
/// The training episodes (training curves).
pub const TRAINING_EPISODES: &str = "episodes.csv";
/// The learner's metrics as CSV.
pub const METRICS_CSV: &str = "metrics.csv";
/// The learner's metrics as JSON lines.
pub const METRICS_JSONL: &str = "metrics.jsonl";
/// The folder of the checkpoints.
pub const CHECKPOINTS: &str = "checkpoints";
/// A checkpoint's acting-policy weights.
pub const POLICY_FILE: &str = "policy.safetensors";
/// A checkpoint's agent configuration.
pub const AGENT_FILE: &str = "agent.toml";
/// The best checkpoint's folder, inside [`CHECKPOINTS`].
pub const BEST_DIR: &str = "best";
/// The default evaluation folder of a run.
pub const EVAL_DIR: &str = "eval";
/// What an evaluation evaluated, and how.
pub const EVAL_META: &str = "meta.json";
/// The job of an evaluation in progress (to resume it).
pub const EVAL_JOB: &str = "job.json";
/// One row per evaluation episode.
pub const EVAL_EPISODES: &str = "episodes.csv";
/// One row per context of the grid.
pub const EVAL_CONTEXTS_CSV: &str = "contexts.csv";
/// The same as JSON.
pub const EVAL_CONTEXTS_JSON: &str = "contexts.json";
