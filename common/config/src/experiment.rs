//! An experiment: the track, the race scenario, the agent and the training schedule, as one TOML
//! file (`configs/*.toml`). Every table rejects unknown keys and fills missing ones with the
//! paper's values, so a file only names what it changes.

use crate::agents::{AgentConfig, AgentConfigError, AlgoKind, Warmup};
use crate::batch::BatchSpec;
use crate::config::{RaceConfig, RaceConfigError};
use crate::plan::RunPlan;
use crate::replay::ReplayOptions;
use crate::validate::{bounded_floats, finite_floats, in_range, ValueError};
use serde::{Deserialize, Serialize};
use std::ops::Bound;
use std::path::{Component, Path};

/// The most gradient steps per env step (`[train] train_ratio`; the paper's: 1, its SAC: 2).
pub const MAX_TRAIN_RATIO: f64 = 1000.0;
/// The widest layer of any network (units, hidden sizes; the paper's widest: 512).
pub const MAX_WIDTH: usize = 16384;
/// The deepest MLP (layers).
pub const MAX_LAYERS: usize = 64;
/// The longest imagination horizon (`[agent] dreamer.horizon`; the paper's: 15).
pub const MAX_HORIZON: usize = 1000;
/// The most env steps of a run (`[train] env_steps`; the paper's: 100 000).
pub const MAX_ENV_STEPS: u64 = 10_000_000_000;
/// The largest value of a positive agent knob (an epsilon, a clip, a loss weight, an initial
/// temperature): far above any the paper or its code uses.
pub const MAX_POSITIVE_KNOB: f64 = 1e6;

/// Why an experiment configuration is refused. Each message names the key (by its table), its
/// value and how to fix it; [`ExperimentError::In`] adds the file it came from.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    /// The file could not be read, is too large or is not text (its content is not shown).
    #[error("experiment config: {0}")]
    Read(crate::config_file::ConfigFileError),
    /// A refusal of the configuration read from `origin` (a file's path, or what the text is).
    #[error("{origin}: {error}")]
    In {
        /// Where the configuration came from.
        origin: String,
        /// The refusal.
        error: Box<ExperimentError>,
    },
    /// Not TOML, or a key or a value that a table does not take (with its line).
    #[error("{}", crate::validate::toml_message(.0))]
    Toml(toml::de::Error),
    /// The configuration could not be written as TOML.
    #[error("serialising the experiment config: {0}")]
    Serialise(toml::ser::Error),
    /// A float that is not finite (by its key path, with the default), or a value outside its
    /// range (with the range and the fix).
    #[error("{0}")]
    Value(ValueError),
    /// A value of the `[race]` table.
    #[error("[race] {0}")]
    Race(RaceConfigError),
    /// A value of the `[agent]` table.
    #[error("[agent] {0}")]
    Agent(AgentConfigError),
    /// DreamerV3's return-normalisation percentiles are out of order.
    #[error(
        "[agent] dreamer.return_low = {low} must be below dreamer.return_high = {high}; the \
         paper: 0.05 and 0.95"
    )]
    ReturnPercentiles {
        /// `dreamer.return_low`.
        low: f64,
        /// `dreamer.return_high`.
        high: f64,
    },
    /// No env step is left after the prefill.
    #[error(
        "[train] env_steps = {env_steps} must be above prefill = {prefill}: the learner starts \
         after the prefill and would take no gradient step; raise env_steps or lower prefill"
    )]
    NothingAfterPrefill {
        /// `[train] env_steps`.
        env_steps: u64,
        /// `[train] prefill`.
        prefill: u64,
    },
    /// The run would take no gradient step.
    #[error(
        "[train] train_ratio = {train_ratio} gives no gradient step over the {after_prefill} env \
         steps after the prefill; raise train_ratio or env_steps"
    )]
    NoGradientStep {
        /// `[train] train_ratio`.
        train_ratio: f64,
        /// Env steps after the prefill.
        after_prefill: u64,
    },
    /// The training contexts' half-width is out of range.
    #[error("[train] context_range = {0} must lie in [0, 0.9]")]
    ContextRange(f64),
    /// A `keep_best_at` step the run never reaches.
    #[error(
        "[train] keep_best_at = {step} lies outside the run's env steps 1..={env_steps}: keep \
         the best policy at steps the run takes"
    )]
    KeepBestAt {
        /// The step.
        step: u64,
        /// `[train] env_steps`.
        env_steps: u64,
    },
    /// A zero publication or logging interval, or zero threads.
    #[error("[train] policy_every, log_every and threads must be positive")]
    ZeroInterval,
    /// The supervisor could not tell a hung process from a live one.
    #[error(
        "[supervisor] restart_window_secs = {restart_window_secs} must be positive, and \
         heartbeat_timeout_secs = {heartbeat_timeout_secs} and stall_timeout_secs = \
         {stall_timeout_secs} at least 5 (heartbeats and weights come every second or more \
         often)"
    )]
    Supervisor {
        /// `[supervisor] restart_window_secs`.
        restart_window_secs: u64,
        /// `[supervisor] heartbeat_timeout_secs`.
        heartbeat_timeout_secs: u64,
        /// `[supervisor] stall_timeout_secs`.
        stall_timeout_secs: u64,
    },
    /// A `[replay]` key that the run derives from another table ([`RunPlan`]) was set.
    #[error(
        "[replay] {key} = {value} is set by the run from {from}; remove it from [replay] (set \
         {from} instead)"
    )]
    ReplayKeyDerived {
        /// The key.
        key: &'static str,
        /// Its value.
        value: f64,
        /// Where the run takes it from.
        from: &'static str,
    },
    /// Each actor's share of the replay holds less than one sampled window.
    #[error(
        "[replay] capacity = {capacity} gives each of the {actors} actors a ring of {ring} \
         steps, less than one sampled window of {window} steps: no batch could ever be \
         served; raise capacity to at least {needed} or run fewer actors"
    )]
    ReplayRing {
        /// `[replay] capacity`.
        capacity: usize,
        /// Actors of the run.
        actors: usize,
        /// Steps each actor's ring holds.
        ring: usize,
        /// Steps of one sampled window.
        window: usize,
        /// The smallest capacity that serves a batch.
        needed: usize,
    },
    /// One batch is larger than the batches' payload limit.
    #[error(
        "[replay] max_batch_floats = {max_batch_floats} is smaller than one batch of the agent \
         ({floats:?} floats for {spec:?} of {beams} beams); raise it or lower the batch"
    )]
    BatchTooLarge {
        /// `[replay] max_batch_floats`.
        max_batch_floats: usize,
        /// Floats of one batch (none: more than a `usize` holds).
        floats: Option<usize>,
        /// The agent's batch.
        spec: BatchSpec,
        /// LiDAR beams per observation.
        beams: usize,
    },
    /// The rate limiter's window cannot hold one batch.
    #[error(
        "[replay] error_buffer_steps = {error_buffer_steps} is too small for [train] \
         train_ratio = {train_ratio}: a batch of {steps} steps would wait forever; use at least \
         {needed}"
    )]
    ErrorBuffer {
        /// `[replay] error_buffer_steps`.
        error_buffer_steps: f64,
        /// `[train] train_ratio`.
        train_ratio: f64,
        /// Steps of one batch.
        steps: usize,
        /// The smallest window that holds one.
        needed: f64,
    },
}

impl ExperimentError {
    /// The refusal `self` of the configuration read from `origin`.
    fn within(self, origin: &str) -> Self {
        Self::In {
            origin: origin.to_string(),
            error: Box::new(self),
        }
    }
}

/// The training schedule (the `[train]` table).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Environment steps (decisions) to collect in all (the paper: 100k).
    pub env_steps: u64,
    /// Steps collected with uniformly random actions before the first gradient step (with
    /// `[agent] warmup = "random-steps"`, the default).
    pub prefill: u64,
    /// Gradient steps per environment step (the paper's code: 1).
    pub train_ratio: f64,
    /// Half-width of the training context range: each of `c_v, c_θ` is drawn from
    /// `U[−r, r]` once per episode (the paper: 0.15).
    pub context_range: f64,
    /// Seed of the agent's initialisation and noise, the episodes and the replay sampler.
    pub seed: u64,
    /// Gradient steps between publications of the policy weights to the actors.
    pub policy_every: u64,
    /// Gradient steps between checkpoints (0: only at the end).
    pub checkpoint_every: u64,
    /// Gradient steps between training-metric rows in `metrics.jsonl`.
    pub log_every: u64,
    /// Seconds between the resume points of a single-process run (`train --inline`), each
    /// written at the first episode boundary after (0: at every boundary); `--resume` continues
    /// from the newest exactly as if the run had not stopped.
    pub resume_every_secs: u64,
    /// Environment steps at which a single-process run keeps a copy of its best policy so far
    /// (`checkpoints/best-at-<N>`, evaluated with `--checkpoint best-at-<N>`), e.g. `[25000,
    /// 50000, 75000]`: how the policy `ctxrace eval` takes by default developed.
    pub keep_best_at: Vec<u64>,
    /// Worker threads of the learner: DreamerV3 and its variants split each batch over them;
    /// SAC always trains on one (the actors always act on one) [default:
    /// [`AlgoKind::learner_threads`]].
    pub threads: Option<usize>,
}

impl TrainConfig {
    /// The learner's thread count for `algo`: `threads` if set, else the algorithm's default.
    pub fn threads_for(&self, algo: crate::agents::AlgoKind) -> usize {
        self.threads.unwrap_or(algo.learner_threads())
    }
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            env_steps: 100_000,
            prefill: 2_500,
            train_ratio: 1.0,
            context_range: 0.15,
            seed: 0,
            policy_every: 10,
            checkpoint_every: 5_000,
            log_every: 100,
            resume_every_secs: 60,
            keep_best_at: Vec::new(),
            threads: None,
        }
    }
}

/// One training experiment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ExperimentConfig {
    /// Track: a name in the tracks folder, a map yaml path or `generated:SEED`.
    pub track: String,
    /// The race scenario.
    pub race: RaceConfig,
    /// The agent.
    pub agent: AgentConfig,
    /// The training schedule.
    pub train: TrainConfig,
    /// The replay buffer (its sampling ratio and minimum fill follow `train`).
    pub replay: ReplayOptions,
    /// How the launcher supervises the run's processes.
    pub supervisor: SupervisorConfig,
}

/// How the launcher keeps a run's processes alive (the `[supervisor]` table).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SupervisorConfig {
    /// Restarts one process (the replay, the learner, each actor) may need within
    /// `restart_window_secs`; one more stops the run with the process's last log lines, since a
    /// process that keeps failing (bad data, a bad value) will not recover by itself.
    pub max_restarts: u32,
    /// The window of `max_restarts` (s).
    pub restart_window_secs: u64,
    /// An actor whose heartbeat, or the replay whose status, has not been heard for this long
    /// (s) is taken as hung: it is killed and restarted like a crashed one.
    pub heartbeat_timeout_secs: u64,
    /// Most gradient steps an actor's policy may lag behind the learner's newest broadcast
    /// for `stall_timeout_secs` before the actor is restarted (weights stopped reaching it).
    pub max_policy_lag: u64,
    /// How long (s) an actor may lag more than `max_policy_lag`, or the learner go without a
    /// gradient step while the replay holds its prefill, before it is killed and restarted
    /// like a crashed process (a learner that keeps stalling stops the run after
    /// `max_restarts`).
    pub stall_timeout_secs: u64,
}

impl Default for SupervisorConfig {
    fn default() -> Self {
        Self {
            max_restarts: 5,
            restart_window_secs: 600,
            heartbeat_timeout_secs: 60,
            max_policy_lag: 1000,
            stall_timeout_secs: 300,
        }
    }
}

impl Default for ExperimentConfig {
    fn default() -> Self {
        Self {
            track: "f1_esp".into(),
            race: RaceConfig::default(),
            agent: AgentConfig::default(),
            train: TrainConfig::default(),
            replay: ReplayOptions::default(),
            supervisor: SupervisorConfig::default(),
        }
    }
}

impl ExperimentConfig {
    /// Parses TOML text; `origin` names it in errors.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, ExperimentError> {
        Self::from_toml_unnamed(text).map_err(|e| e.within(origin))
    }

    /// [`ExperimentConfig::from_toml`] without the origin in its errors.
    fn from_toml_unnamed(text: &str) -> Result<Self, ExperimentError> {
        // parsed as the struct first so that syntax and unknown keys are reported with their line
        let mut cfg: Self = toml::from_str(text).map_err(ExperimentError::Toml)?;
        let table = |name: &str| -> Result<toml::Table, ExperimentError> {
            let mut table: toml::Table = toml::from_str(text).map_err(ExperimentError::Toml)?;
            Ok(match table.remove(name) {
                Some(toml::Value::Table(t)) => t,
                _ => toml::Table::new(),
            })
        };
        if cfg.race.preset != crate::RacePreset::Default {
            cfg.race =
                crate::RaceConfig::from_table(table("race")?).map_err(ExperimentError::Race)?;
        }
        if cfg.agent.preset != crate::AgentPreset::Default {
            cfg.agent = AgentConfig::from_table(table("agent")?).map_err(ExperimentError::Agent)?;
        }
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads and checks a TOML file.
    pub fn load(path: &Path) -> Result<Self, ExperimentError> {
        let text = crate::config_file::read_config_text(path).map_err(ExperimentError::Read)?;
        Self::from_toml(&text, &path.display().to_string())
    }

    /// Reads the experiment a run directory recorded (its `config.toml`): as
    /// [`ExperimentConfig::load`], an `[agent]` recorded before `context_scale` existed reading
    /// as the scale that run trained with ([`crate::ContextScale::SAVED_WITHOUT_KEY`]).
    pub fn load_saved(path: &Path) -> Result<Self, ExperimentError> {
        let origin = path.display().to_string();
        let text = crate::config_file::read_config_text(path).map_err(ExperimentError::Read)?;
        let mut table: toml::Table =
            toml::from_str(&text).map_err(|e| ExperimentError::Toml(e).within(&origin))?;
        let agent = table
            .entry("agent")
            .or_insert_with(|| toml::Table::new().into());
        if let toml::Value::Table(agent) = agent {
            crate::ContextScale::fill_saved_table(agent);
        }
        // a table read from TOML always writes back
        let text = toml::to_string(&table).map_err(ExperimentError::Serialise)?;
        Self::from_toml(&text, &origin)
    }

    /// The configuration as TOML (what a run directory records).
    pub fn to_toml(&self) -> Result<String, ExperimentError> {
        toml::to_string(self).map_err(ExperimentError::Serialise)
    }

    /// What the run is held to: its budget, gradient-step target and replay ([`RunPlan`]).
    pub fn plan(&self) -> RunPlan {
        RunPlan::of(self)
    }

    /// Whether the agent's policy chooses the action after `decisions` decisions (not the
    /// uniformly random actions of the prefill).
    pub fn acts_by_policy(&self, decisions: u64) -> bool {
        match self.agent.warmup {
            Warmup::RandomSteps => decisions >= self.train.prefill,
            Warmup::Episodes => true,
        }
    }

    /// The decision count after which `train_ratio` gradient steps per env step are due, once
    /// the warm-up is over after `decisions` decisions in `episodes` episodes (the running one
    /// included); `None` while it lasts. `random-steps`: the prefill; `episodes`: the decision
    /// before the one that brought the replay's episodes to `warmup_episodes`, so that it is
    /// followed by a gradient step, as the paper's code trains after every env step from then.
    pub fn warmup_end(&self, decisions: u64, episodes: u64) -> Option<u64> {
        match self.agent.warmup {
            Warmup::RandomSteps => (decisions > self.train.prefill).then_some(self.train.prefill),
            Warmup::Episodes => {
                (episodes >= self.agent.warmup_episodes && decisions > 0).then(|| decisions - 1)
            }
        }
    }

    /// Checks every table for a run with one actor ([`ExperimentConfig::validate_run`]).
    pub fn validate(&self) -> Result<(), ExperimentError> {
        self.validate_run(1)
    }

    /// Checks every table for a run of `actors` actors (each fills its own share of the
    /// replay): every float finite and within ±[`crate::validate::MAX_FLOAT`], ranges where
    /// they matter; the message names the key, its value and the fix.
    pub fn validate_run(&self, actors: usize) -> Result<(), ExperimentError> {
        finite_floats(self, &Self::default()).map_err(ExperimentError::Value)?;
        self.race.validate().map_err(ExperimentError::Race)?;
        self.validate_agent()?;
        self.agent.validate().map_err(ExperimentError::Agent)?;
        self.check_bounds().map_err(ExperimentError::Value)?;
        let t = &self.train;
        if self.agent.warmup == Warmup::RandomSteps && t.env_steps <= t.prefill {
            return Err(ExperimentError::NothingAfterPrefill {
                env_steps: t.env_steps,
                prefill: t.prefill,
            });
        }
        if self.plan().gradient_steps == 0 {
            return Err(ExperimentError::NoGradientStep {
                train_ratio: t.train_ratio,
                after_prefill: t.env_steps.saturating_sub(t.prefill),
            });
        }
        if !(t.context_range.is_finite() && (0.0..=0.9).contains(&t.context_range)) {
            return Err(ExperimentError::ContextRange(t.context_range));
        }
        if t.policy_every == 0 || t.log_every == 0 || t.threads == Some(0) {
            return Err(ExperimentError::ZeroInterval);
        }
        if let Some(&step) = t.keep_best_at.iter().find(|&&s| s == 0 || s > t.env_steps) {
            return Err(ExperimentError::KeepBestAt {
                step,
                env_steps: t.env_steps,
            });
        }
        let s = &self.supervisor;
        if s.restart_window_secs == 0 || s.heartbeat_timeout_secs < 5 || s.stall_timeout_secs < 5 {
            return Err(ExperimentError::Supervisor {
                restart_window_secs: s.restart_window_secs,
                heartbeat_timeout_secs: s.heartbeat_timeout_secs,
                stall_timeout_secs: s.stall_timeout_secs,
            });
        }
        self.validate_gains()?;
        self.validate_replay(actors)?;
        // last: the keys' own checks above say more about a value they bound
        bounded_floats(self, &Self::default()).map_err(ExperimentError::Value)
    }

    /// Checks the chosen algorithm's batch sizes and learning rates (a zero rate trains
    /// nothing; zero-sized batches leave the learner waiting while the actors run unthrottled).
    fn validate_agent(&self) -> Result<(), ExperimentError> {
        let (s, d) = (&self.agent.sac, &self.agent.dreamer);
        // the DreamerV3 family's keys, cMask's mask SAC's with `mask_sac`
        let dreamer = |mask_sac: bool| {
            let mut rates = vec![("dreamer.model_lr", d.model_lr), ("dreamer.ac_lr", d.ac_lr)];
            let mut fractions = vec![
                ("dreamer.gamma", d.gamma),
                ("dreamer.lambda", d.lambda),
                ("dreamer.unimix", d.unimix),
                ("dreamer.return_decay", d.return_decay),
                ("dreamer.return_low", d.return_low),
                ("dreamer.return_high", d.return_high),
                ("dreamer.slow_critic_rate", d.slow_critic_rate),
            ];
            if mask_sac {
                rates.push(("dreamer.mask.lr", d.mask.lr));
                fractions.extend([
                    ("dreamer.mask.gamma", d.mask.gamma),
                    ("dreamer.mask.tau", d.mask.tau),
                ]);
            }
            let sizes = vec![
                ("dreamer.batch", d.batch, "the paper: 16 sequences"),
                ("dreamer.length", d.length, "the paper: 64 steps"),
            ];
            let mut positive = vec![
                ("dreamer.model_eps", d.model_eps),
                ("dreamer.ac_eps", d.ac_eps),
                ("dreamer.model_clip", d.model_clip),
                ("dreamer.ac_clip", d.ac_clip),
            ];
            if mask_sac {
                positive.push(("dreamer.mask.init_alpha", d.mask.init_alpha));
            }
            (sizes, rates, fractions, positive)
        };
        let (sizes, rates, fractions, positive) = match self.agent.algo {
            AlgoKind::Sac => (
                vec![("sac.batch_size", s.batch_size, "the paper: 100")],
                vec![
                    ("sac.actor_lr", s.actor_lr),
                    ("sac.critic_lr", s.critic_lr),
                    ("sac.alpha_lr", s.alpha_lr),
                ],
                vec![],
                vec![],
            ),
            AlgoKind::Dreamerv3 | AlgoKind::Crssm => dreamer(false),
            AlgoKind::Cmask => dreamer(true),
        };
        for (key, value) in fractions {
            in_range(
                key,
                value,
                0.0..=1.0,
                "a fraction (see DreamerConfig's defaults)",
            )
            .map_err(|e| ExperimentError::Agent(e.into()))?;
        }
        for (key, value) in positive {
            let above_zero = (Bound::Excluded(0.0), Bound::Included(MAX_POSITIVE_KNOB));
            in_range(key, value, above_zero, "see DreamerConfig's defaults")
                .map_err(|e| ExperimentError::Agent(e.into()))?;
        }
        if self.agent.algo != AlgoKind::Sac {
            for (key, value) in [("dreamer.kl_dyn", d.kl_dyn), ("dreamer.kl_rep", d.kl_rep)] {
                in_range(
                    key,
                    value,
                    0.0..=MAX_POSITIVE_KNOB,
                    "a KL loss weight (the paper: 0.5 and 0.1)",
                )
                .map_err(|e| ExperimentError::Agent(e.into()))?;
            }
        }
        let return_percentiles = match self.agent.algo {
            AlgoKind::Sac => false,
            AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => true,
        };
        if return_percentiles && d.return_low >= d.return_high {
            return Err(ExperimentError::ReturnPercentiles {
                low: d.return_low,
                high: d.return_high,
            });
        }
        for (key, size, fix) in sizes {
            in_range(key, size, 1.., fix).map_err(|e| ExperimentError::Agent(e.into()))?;
        }
        for (key, rate) in rates {
            in_range(
                key,
                rate,
                (Bound::Excluded(0.0), Bound::Included(1.0)),
                "a learning rate (the paper: 3e-5)",
            )
            .map_err(|e| ExperimentError::Agent(e.into()))?;
        }
        Ok(())
    }

    /// Checks that every context gain (the default one and each track's) keeps the rival's
    /// speed and lookahead factors `1 + λ c` positive over the training contexts.
    fn validate_gains(&self) -> Result<(), ExperimentError> {
        let r = self.train.context_range;
        let limit = if r > 0.0 { 1.0 / r } else { f64::INFINITY };
        let rival = &self.race.rival;
        let tracks = rival
            .tracks
            .iter()
            .map(|(name, g)| (format!("[race] rival.tracks.{name}"), g));
        let fix = format!(
            "1 + λ·c scales the rival over the training contexts c in [-{r}, {r}] \
             ([train] context_range) and must stay positive (the paper: 1 and 0.4)"
        );
        for (table, gains) in
            std::iter::once(("[race] rival.gains".to_string(), &rival.gains)).chain(tracks)
        {
            for (key, gain) in [
                ("lambda_v", gains.lambda_v),
                ("lambda_theta", gains.lambda_theta),
            ] {
                in_range(
                    &format!("{table}.{key}"),
                    gain,
                    (Bound::Excluded(-limit), Bound::Excluded(limit)),
                    &fix,
                )
                .map_err(ExperimentError::Value)?;
            }
        }
        Ok(())
    }

    /// Checks that the replay can serve the agent's batches with `actors` actors: each actor's
    /// ring holds a sampled window, a batch fits the payload limit, and the rate limiter's
    /// window holds one.
    fn validate_replay(&self, actors: usize) -> Result<(), ExperimentError> {
        let r = &self.replay;
        let defaults = ReplayOptions::default();
        let derived = [
            (
                "samples_per_insert",
                r.samples_per_insert,
                defaults.samples_per_insert,
                "[train] train_ratio",
            ),
            ("seed", r.seed as f64, defaults.seed as f64, "[train] seed"),
        ];
        if let Some(&(key, value, _, from)) = derived.iter().find(|(_, v, d, _)| v != d) {
            return Err(ExperimentError::ReplayKeyDerived { key, value, from });
        }
        let spec = self.agent.batch_spec();
        let window = match spec {
            BatchSpec::Sequence { length, .. } => length,
            BatchSpec::Transition { reward_delay, .. } => 2 + reward_delay,
        };
        let floats = spec.floats(self.race.lidar.beams, 2);
        let ring = self.plan().stream_capacity(actors);
        if ring < window {
            return Err(ExperimentError::ReplayRing {
                capacity: r.capacity,
                actors,
                ring,
                window,
                needed: window * actors.max(1),
            });
        }
        match floats {
            Some(n) if n <= r.max_batch_floats => {}
            _ => {
                return Err(ExperimentError::BatchTooLarge {
                    max_batch_floats: r.max_batch_floats,
                    floats,
                    spec,
                    beams: self.race.lidar.beams,
                })
            }
        }
        // the limiter samples n = B·T steps only while inserts·spi − samples stays within
        // ±spi·error_buffer_steps of its target: the window 2·spi·error_buffer_steps must hold n
        let ratio = self.train.train_ratio;
        let needed = 1.0 / (2.0 * ratio);
        if ratio > 0.0 && (r.error_buffer_steps.is_nan() || r.error_buffer_steps < needed) {
            return Err(ExperimentError::ErrorBuffer {
                error_buffer_steps: r.error_buffer_steps,
                train_ratio: ratio,
                steps: spec.steps(),
                needed,
            });
        }
        Ok(())
    }
}

impl ExperimentConfig {
    /// Checks that every size and count lies within its sane bound, and that `[replay]
    /// snapshot_path` stays inside the run folder; the error names the key, its value and the fix.
    fn check_bounds(&self) -> Result<(), ValueError> {
        let t = &self.train;
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
        let (s, d) = (&self.agent.sac, &self.agent.dreamer);
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
        if let Some(path) = &self.replay.snapshot_path {
            let inside = path.components().all(|c| matches!(c, Component::Normal(_)));
            if !inside || path.as_os_str().is_empty() {
                return Err(ValueError::OutOfRange {
                    key: "[replay] snapshot_path".into(),
                    value: format!("{path:?}"),
                    bounds: "a file inside the run folder (relative, without ..)".into(),
                    fix:
                        "name it relative to the run folder, e.g. \"replay.snapshot\", or leave it \
                          out"
                        .into(),
                });
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::agents::AlgoKind;

    /// A run directory recorded before `context_scale` existed trained with the normalised
    /// context: resuming or evaluating it reads that back; a run recorded since keeps its key.
    #[test]
    fn a_run_recorded_without_context_scale_reads_as_normalised() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("config.toml");
        let mut old = ExperimentConfig::default().to_toml().unwrap();
        old = old.replace("context_scale = \"raw\"\n", "");
        assert!(!old.contains("context_scale"));
        std::fs::write(&path, &old).unwrap();
        let saved = ExperimentConfig::load_saved(&path).unwrap();
        assert_eq!(saved.agent.context_scale, crate::ContextScale::Normalised);
        assert_eq!(
            ExperimentConfig::load(&path).unwrap().agent.context_scale,
            crate::ContextScale::Raw
        );
        std::fs::write(&path, ExperimentConfig::default().to_toml().unwrap()).unwrap();
        let now = ExperimentConfig::load_saved(&path).unwrap();
        assert_eq!(now, ExperimentConfig::default());
    }

    #[test]
    fn keep_best_at_takes_only_steps_the_run_takes() {
        let cfg = |keep: &str| {
            ExperimentConfig::from_toml(
                &format!("[train]\nenv_steps = 5000\nkeep_best_at = {keep}\n"),
                "k.toml",
            )
        };
        assert_eq!(
            cfg("[1, 2500, 5000]").unwrap().train.keep_best_at,
            [1, 2500, 5000]
        );
        for bad in ["[0]", "[2500, 5001]"] {
            let err = cfg(bad).unwrap_err().to_string();
            assert!(
                err.contains("keep_best_at") && err.contains("1..=5000"),
                "{bad}: {err}"
            );
        }
    }

    /// Values that once passed the checks and then crash-looped the learner are refused before
    /// anything starts, naming the key.
    #[test]
    fn temperatures_and_loss_weights_no_experiment_means_are_refused() {
        for (table, key, bad) in [
            ("[agent.dreamer.mask]", "init_alpha", "-1.0"),
            ("[agent.dreamer.mask]", "init_alpha", "0.0"),
            ("[agent.dreamer.mask]", "init_alpha", "1e308"),
            ("[agent.dreamer]", "kl_dyn", "-1.0"),
            ("[agent.dreamer]", "kl_rep", "1e308"),
        ] {
            let text = format!("[agent]\nalgo = \"cmask\"\n{table}\n{key} = {bad}\n");
            let err = ExperimentConfig::from_toml(&text, "t.toml")
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{key} = {bad}: {err}");
        }
        let fine = "[agent]\nalgo = \"cmask\"\n[agent.dreamer.mask]\ninit_alpha = 0.05\n";
        assert!(ExperimentConfig::from_toml(fine, "t.toml").is_ok());
    }

    #[test]
    fn the_agent_preset_reads_from_files_and_bad_keys_name_themselves() {
        let cfg = ExperimentConfig::from_toml(
            "[agent]\npreset = \"paper-code\"\nalgo = \"cmask\"\n[agent.dreamer]\nbatch = 8\n",
            "p.toml",
        )
        .unwrap();
        assert_eq!(cfg.agent.sampler, crate::Sampler::PaperCode);
        assert_eq!(cfg.agent.warmup, Warmup::Episodes);
        assert_eq!(cfg.agent.dreamer.batch, 8);
        assert_eq!(cfg.agent.algo, AlgoKind::Cmask);
        // what a run directory records reads back the same
        let again = ExperimentConfig::from_toml(&cfg.to_toml().unwrap(), "again").unwrap();
        assert_eq!(again, cfg);
        for (text, key, allowed) in [
            ("preset = \"paper\"", "preset", "paper-code"),
            ("sampler = \"numpy\"", "sampler", "paper-code"),
            ("warmup = \"laps\"", "warmup", "random-steps"),
            ("context_scale = \"scaled\"", "context_scale", "normalised"),
            (
                "preset = \"paper-code\"\nwarmup_episodes = 0",
                "warmup_episodes",
                "at least 1",
            ),
            (
                "warmup = \"episodes\"\nwarmup_episodes = 0",
                "warmup_episodes",
                "32",
            ),
            ("warmup_episodes = -1", "warmup_episodes", "u64"),
        ] {
            let err = ExperimentConfig::from_toml(&format!("[agent]\n{text}\n"), "a.toml")
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(key) && err.contains(allowed) && err.contains("a.toml"),
                "{text}: {err}"
            );
        }
    }

    #[test]
    fn a_refusal_keeps_its_table_and_its_kind() {
        let err = ExperimentConfig::from_toml("[race]\nmin_speed = 9.0", "m.toml").unwrap_err();
        assert_eq!(
            err.to_string(),
            "m.toml: [race] min_speed = 9 must be in [0, max_speed = 6)"
        );
        let ExperimentError::In { origin, error } = err else {
            panic!("{err:?}")
        };
        assert_eq!(origin, "m.toml");
        assert!(
            matches!(
                *error,
                ExperimentError::Race(RaceConfigError::MinSpeed { min_speed, .. })
                    if min_speed == 9.0
            ),
            "{error:?}"
        );
        let err = ExperimentConfig::from_toml("[agent.dreamer]\ngamma = 2.0", "g.toml")
            .unwrap_err()
            .to_string();
        assert_eq!(
            err,
            "g.toml: [agent] dreamer.gamma = 2 must be at least 0 and at most 1; a fraction (see \
             DreamerConfig's defaults)"
        );
    }

    #[test]
    fn warmup_by_episodes_waits_for_the_episodes_and_lets_the_policy_act() {
        let mut cfg = ExperimentConfig::default();
        // the default: 2,500 random steps, training after them
        assert!(!cfg.acts_by_policy(2499) && cfg.acts_by_policy(2500));
        assert_eq!(cfg.warmup_end(2500, 40), None);
        assert_eq!(cfg.warmup_end(2501, 1), Some(2500));
        assert_eq!(cfg.plan().gradient_steps, 97_500);
        cfg.agent = AgentConfig::paper_code();
        assert!(cfg.acts_by_policy(0));
        // 31 episodes, however many steps: still warming up; the 32nd's first step ends it
        assert_eq!(cfg.warmup_end(5000, 31), None);
        assert_eq!(cfg.warmup_end(812, 32), Some(811));
        cfg.agent.warmup_episodes = 3;
        assert_eq!(cfg.warmup_end(40, 2), None);
        assert_eq!(cfg.warmup_end(41, 3), Some(40));
        // the prefill no longer counts: env_steps may be below it
        cfg.train.env_steps = 1000;
        assert!(cfg.validate().is_ok());
        assert_eq!(cfg.plan().gradient_steps, 1000);
    }

    #[test]
    fn the_shipped_experiment_configs_load() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
        for (name, track) in [
            ("quick.toml", "generated:0"),
            ("brief.toml", "f1_esp"),
            ("paper.toml", "f1_esp"),
        ] {
            let cfg = ExperimentConfig::load(&dir.join(name)).unwrap();
            assert_eq!(cfg.track, track, "{name}");
        }
        // the reduced Table II races the paper-code preset as it was when its runs started
        // (docs/table2/README.md, amendment 4), pinned in its base and in a scenario file
        let table = ExperimentConfig::load(&dir.join("paper/table2-base.toml")).unwrap();
        let era = std::fs::read_to_string(dir.join("scenarios/paper-code-table-era.toml")).unwrap();
        let era = RaceConfig::from_toml(&era).unwrap();
        assert_eq!(table.race, era);
        assert_eq!(
            (era.grid_line, era.wall_contact, era.rival_contacts),
            (
                crate::GridLine::Centreline,
                crate::WallContact::Centre,
                crate::RivalContacts::PerStep
            )
        );
        assert_eq!(
            (era.rival.wheelbase, era.rival.max_steer),
            (Some(0.3302), Some(0.4189))
        );
        let now = RaceConfig::paper_code();
        assert_eq!(
            RaceConfig {
                grid_line: now.grid_line,
                wall_contact: now.wall_contact,
                rival_contacts: now.rival_contacts,
                rival: now.rival.clone(),
                ..era
            },
            now
        );
    }

    #[test]
    fn partial_files_keep_the_paper_defaults_and_errors_name_the_key() {
        let cfg = ExperimentConfig::from_toml(
            "track = \"generated:3\"\n[agent]\nalgo = \"sac\"\n[train]\nenv_steps = 500\nprefill = 100",
            "test.toml",
        )
        .unwrap();
        assert_eq!(cfg.agent.algo, AlgoKind::Sac);
        assert_eq!(cfg.train.env_steps, 500);
        assert_eq!(cfg.train.context_range, 0.15);
        assert_eq!(cfg.race, RaceConfig::default());
        let round = ExperimentConfig::from_toml(&cfg.to_toml().unwrap(), "round trip").unwrap();
        assert_eq!(round, cfg);
        let err = ExperimentConfig::from_toml("[train]\nenv_step = 5", "x.toml")
            .unwrap_err()
            .to_string();
        assert!(err.contains("x.toml") && err.contains("env_step"), "{err}");
        let err = ExperimentConfig::from_toml("[train]\ncontext_range = 2.0", "y.toml")
            .unwrap_err()
            .to_string();
        assert!(err.contains("context_range"), "{err}");
        // the replay must be able to serve the agent's batches
        for (text, key) in [
            ("[replay]\nerror_buffer_steps = 0.1", "error_buffer_steps"),
            ("[replay]\nmax_batch_floats = 1000", "max_batch_floats"),
            ("[replay]\ncapacity = 10", "capacity"),
        ] {
            let err = ExperimentConfig::from_toml(text, "r.toml")
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{text}: {err}");
        }
    }

    /// The error for `text` with `actors` actors; it must name each of `needles` (the key, the
    /// value, the fix).
    fn refused(text: &str, actors: usize, needles: &[&str]) {
        let cfg = ExperimentConfig::from_toml(text, "probe.toml");
        let err = match cfg {
            Ok(cfg) => cfg.validate_run(actors).unwrap_err(),
            Err(e) => e,
        }
        .to_string();
        for needle in needles {
            assert!(err.contains(needle), "{text}: no '{needle}' in: {err}");
        }
    }

    #[test]
    fn empty_batches_and_dead_learning_rates_are_refused() {
        refused(
            "[agent.dreamer]\nbatch = 0",
            1,
            &["dreamer.batch = 0", "at least 1", "the paper: 16"],
        );
        refused(
            "[agent.dreamer]\nlength = 0",
            1,
            &["dreamer.length = 0", "at least 1", "the paper: 64"],
        );
        refused(
            "[agent]\nalgo = \"sac\"\n[agent.sac]\nbatch_size = 0",
            1,
            &["sac.batch_size = 0", "at least 1"],
        );
        refused(
            "[agent.dreamer]\nmodel_lr = 0.0",
            1,
            &["dreamer.model_lr = 0", "above 0", "3e-5"],
        );
        refused(
            "[agent]\nalgo = \"sac\"\n[agent.sac]\ncritic_lr = -0.001",
            1,
            &["sac.critic_lr = -0.001", "above 0"],
        );
        refused(
            "[agent]\nalgo = \"cmask\"\n[agent.dreamer.mask]\nlr = 0.0",
            1,
            &["dreamer.mask.lr = 0", "above 0"],
        );
        refused(
            "[agent.dreamer]\ngamma = 1.5",
            1,
            &["dreamer.gamma = 1.5", "at most 1", "a fraction"],
        );
        refused(
            "[agent.dreamer]\nreturn_low = 0.9\nreturn_high = 0.1",
            1,
            &["dreamer.return_low = 0.9 must be below dreamer.return_high = 0.1"],
        );
        refused(
            "[agent.dreamer]\nac_eps = 0.0",
            1,
            &["dreamer.ac_eps = 0", "above 0"],
        );
    }

    #[test]
    fn a_replay_whose_actor_rings_cannot_hold_a_window_is_refused_for_that_many_actors() {
        let text = "[agent.dreamer]\nlength = 32\n[replay]\ncapacity = 40";
        let cfg = ExperimentConfig::from_toml(text, "probe.toml").unwrap();
        assert!(cfg.validate_run(1).is_ok());
        refused(
            text,
            2,
            &[
                "[replay] capacity = 40",
                "2 actors",
                "ring of 20 steps",
                "window of 32",
                "at least 64",
            ],
        );
    }

    #[test]
    fn non_finite_floats_are_refused_by_key_path_per_track_overrides_included() {
        refused(
            "[race.rival.gains]\nlambda_v = nan\nlambda_theta = 0.4",
            1,
            &[
                "race.rival.gains.lambda_v = nan",
                "finite",
                "default is 1.0",
            ],
        );
        refused(
            "[race.rival.tracks.f1_esp]\nlambda_v = 1.0\nlambda_theta = inf",
            1,
            &["race.rival.tracks.f1_esp.lambda_theta = inf", "finite"],
        );
        refused(
            "[race.rival.tracks.my_track]\nlambda_v = -inf\nlambda_theta = 0.4",
            1,
            &["race.rival.tracks.my_track.lambda_v = -inf", "finite"],
        );
        refused(
            "[agent.dreamer]\ngamma = nan",
            1,
            &["agent.dreamer.gamma = nan", "default is 0.997"],
        );
        refused(
            "[race.rival.gains]\nlambda_v = 10.0\nlambda_theta = 0.4",
            1,
            &[
                "rival.gains.lambda_v = 10",
                "below 6.6",
                "must stay positive",
            ],
        );
    }

    #[test]
    fn an_unknown_rival_driver_is_refused_naming_the_key_and_the_drivers() {
        for preset in ["", "preset = \"paper-code\"\n"] {
            refused(
                &format!("[race]\n{preset}[race.rival]\ndriver = \"wall-hugger\""),
                1,
                &["driver", "wall-hugger", "pure-pursuit", "follow-the-gap"],
            );
        }
        refused(
            "[race.rival.follow_the_gap]\nbubble_radius = -1.0",
            1,
            &["rival.follow_the_gap.bubble_radius = -1"],
        );
        let cfg =
            ExperimentConfig::from_toml("[race.rival]\ndriver = \"follow-the-gap\"", "ftg.toml")
                .unwrap();
        assert_eq!(cfg.race.rival.driver, crate::RivalDriverKind::FollowTheGap);
    }

    #[test]
    fn beams_beyond_the_wire_format_and_endless_physics_steps_are_refused() {
        refused(
            "[race.lidar]\nbeams = 300",
            1,
            &["lidar.beams = 300", "at most 256", "wire format"],
        );
        refused(
            "[race]\nphysics_steps_per_action = 1000000000",
            1,
            &["physics_steps_per_action = 1000000000", "at most 1000"],
        );
    }

    #[test]
    fn a_run_without_gradient_steps_is_refused() {
        refused(
            "[train]\nenv_steps = 2500\nprefill = 2500",
            1,
            &[
                "env_steps = 2500",
                "prefill = 2500",
                "no gradient step",
                "raise env_steps",
            ],
        );
        refused(
            "[train]\nenv_steps = 3000\nprefill = 2500\ntrain_ratio = 0.0001",
            1,
            &["train_ratio = 0.0001", "no gradient step"],
        );
        refused(
            "[replay]\nseed = 3",
            1,
            &["[replay] seed = 3", "remove it", "[train] seed"],
        );
        refused(
            "[replay]\nsamples_per_insert = 16",
            1,
            &["samples_per_insert = 16", "[train] train_ratio"],
        );
        let ok = "[train]\nenv_steps = 3000\nprefill = 2500";
        let cfg = ExperimentConfig::from_toml(ok, "ok.toml").unwrap();
        assert_eq!(cfg.plan().gradient_steps, 500);
    }

    #[test]
    fn sizes_and_counts_beyond_their_bounds_are_refused_by_key() {
        let cfg = |toml: &str| ExperimentConfig::from_toml(toml, "test").map_err(|e| e.to_string());
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
}
