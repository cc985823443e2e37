//! The agents' hyper-parameters, shared by the learner (training) and the actors (acting): the
//! algorithm name, [`SacConfig`] and [`DreamerConfig`], with the paper's values as defaults
//! (REFERENCE §5), read from the `[agent]` table of an experiment's TOML file.
//!
//! Like `[race]`, the `[agent]` table starts from a preset: keys a file leaves out take its
//! values. `preset = "default"` is ctxrace's learner; `preset = "paper-code"` is the learner as
//! the paper's public code trained it (lilpharaoh1/context-f110, `paper` branch c0fd903, Jun
//! 2025, `TrajectoryAidedLearning/`: cbdreamer's `dreamerv3.py` and `cbtools.py`, and
//! `TrainAgents.py`), see [`AgentConfig::paper_code`]. The presets differ in these keys
//! (docs/guides/agents.md has the full table with the reasons):
//!
//! | key | default | `paper-code` |
//! |---|---|---|
//! | `sampler` | `uniform` | `paper-code` |
//! | `warmup` | `random-steps` (`[train] prefill`) | `episodes` |
//! | `warmup_episodes` | 32 (used with `warmup = "episodes"`) | 32 |
//! | `dreamer.init` | `ctxrace` | `paper-code` ([`WeightInit`]) |
//! | `dreamer.mask.imagination_context` | `masked` | `raw` ([`ImaginationContext`]) |

use crate::batch::BatchSpec;
use crate::preset::PresetError;
use crate::validate::ValueError;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// Lower bound of the log standard deviation.
pub const LOG_STD_MIN: f64 = -5.0;
/// Upper bound of the log standard deviation.
pub const LOG_STD_MAX: f64 = 2.0;

/// The default bounds `[LOG_STD_MIN, LOG_STD_MAX]` of the log standard deviation.
pub const LOG_STD_CLAMP: [f64; 2] = [LOG_STD_MIN, LOG_STD_MAX];

/// Bounds of the log standard deviation that are not finite or not increasing, by their config
/// key.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error(
    "{key} must be two finite bounds [lower, upper] with lower < upper, got [{}, {}] \
     (ctxrace's default is [{LOG_STD_MIN}, {LOG_STD_MAX}], the paper's code's [-20, 2])",
    .bounds[0],
    .bounds[1]
)]
pub struct LogStdClampError {
    /// The config key.
    pub key: String,
    /// The bounds `[lower, upper]` given.
    pub bounds: [f64; 2],
}

/// Checks bounds of the log standard deviation (finite, lower below upper), naming the config
/// key `key` in the error.
pub fn validate_log_std_clamp(
    key: &str,
    [lo, hi]: [f64; 2],
) -> std::result::Result<(), LogStdClampError> {
    if lo.is_finite() && hi.is_finite() && lo < hi {
        Ok(())
    } else {
        Err(LogStdClampError {
            key: key.to_string(),
            bounds: [lo, hi],
        })
    }
}

/// Why an agent configuration cannot be trained or acted with.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AgentConfigError {
    /// A key's value lies outside what the networks or the learner accept; the message names
    /// the key, the value and the values allowed.
    #[error("{0}")]
    OutOfRange(String),
    /// The bounds of a policy's log standard deviation are not finite or not increasing.
    #[error(transparent)]
    LogStdClamp(#[from] LogStdClampError),
    /// A float that is not finite, or a value outside its range.
    #[error(transparent)]
    Value(#[from] ValueError),
    /// The table could not be read over its preset.
    #[error(transparent)]
    Preset(#[from] PresetError),
}

/// The outcome of checking an agent configuration.
type Result<T> = std::result::Result<T, AgentConfigError>;

/// Returns [`AgentConfigError::OutOfRange`] with a formatted message.
macro_rules! bail {
    ($($message:tt)*) => {
        return Err(AgentConfigError::OutOfRange(format!($($message)*)))
    };
}

mod dreamer;
mod sac;

pub use dreamer::{
    ContextMode, DreamerConfig, ImaginationContext, ImaginationLoss, InitialState, MaskConfig,
    MaskSpace, StepAlignment, WeightInit, CONTEXT_DIM,
};
pub use sac::SacConfig;

/// The training algorithms, by the names the command line and configs use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AlgoKind {
    /// Soft actor-critic on two stacked LiDAR frames (the model-free baseline).
    Sac,
    /// DreamerV3 without context.
    #[default]
    Dreamerv3,
    /// DreamerV3 with the context in the world model, actor and critic (cRSSM).
    Crssm,
    /// cRSSM with the context masked by a SAC-learned mask (the paper's cMask).
    Cmask,
}

impl AlgoKind {
    /// Worker threads the learner uses by default: one for SAC, whose products at batch 100 of
    /// a 2 × 100 network are too small to split (two threads took twice as long), two for the
    /// DreamerV3 variants, which split each batch over them.
    pub fn learner_threads(self) -> usize {
        match self {
            AlgoKind::Sac => 1,
            AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => 2,
        }
    }

    /// Every algorithm, in the paper's order.
    pub const ALL: [AlgoKind; 4] = [
        AlgoKind::Sac,
        AlgoKind::Dreamerv3,
        AlgoKind::Crssm,
        AlgoKind::Cmask,
    ];

    /// The name used on the command line and in configs.
    pub fn name(self) -> &'static str {
        match self {
            AlgoKind::Sac => "sac",
            AlgoKind::Dreamerv3 => "dreamerv3",
            AlgoKind::Crssm => "crssm",
            AlgoKind::Cmask => "cmask",
        }
    }

    /// The name the paper prints (SAC, DreamerV3, cRSSM, cMask).
    pub fn display_name(self) -> &'static str {
        match self {
            AlgoKind::Sac => "SAC",
            AlgoKind::Dreamerv3 => "DreamerV3",
            AlgoKind::Crssm => "cRSSM",
            AlgoKind::Cmask => "cMask",
        }
    }

    /// How the context enters the agent (`None` for SAC and DreamerV3).
    pub fn context_mode(self) -> ContextMode {
        match self {
            AlgoKind::Sac | AlgoKind::Dreamerv3 => ContextMode::None,
            AlgoKind::Crssm => ContextMode::Crssm,
            AlgoKind::Cmask => ContextMode::Cmask,
        }
    }
}

impl fmt::Display for AlgoKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is no algorithm's.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "unknown algorithm `{0}`; expected one of {names}",
    names = AlgoKind::ALL.map(AlgoKind::name).join(", ")
)]
pub struct UnknownAlgorithm(pub String);

impl FromStr for AlgoKind {
    type Err = UnknownAlgorithm;

    fn from_str(s: &str) -> std::result::Result<Self, UnknownAlgorithm> {
        AlgoKind::ALL
            .into_iter()
            .find(|a| a.name() == s.to_ascii_lowercase())
            .ok_or_else(|| UnknownAlgorithm(s.to_string()))
    }
}

/// A named starting point for the `[agent]` table: keys a file leaves out take the preset's
/// values.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AgentPreset {
    /// ctxrace's learner ([`AgentConfig::default`]).
    #[default]
    Default,
    /// The learner as the paper's public code trained it ([`AgentConfig::paper_code`]).
    PaperCode,
}

impl AgentPreset {
    /// The agent configuration of the preset.
    pub fn config(self) -> AgentConfig {
        match self {
            AgentPreset::Default => AgentConfig::default(),
            AgentPreset::PaperCode => AgentConfig::paper_code(),
        }
    }
}

/// How the sequences of a DreamerV3 batch are drawn from the replay.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Sampler {
    /// Each sequence a uniformly drawn window of contiguous steps of one actor, from a
    /// generator seeded once per run that advances from batch to batch.
    #[default]
    Uniform,
    /// As the paper's code drew them (cbdreamer `cbtools.sample_episodes`, rebuilt at every
    /// training step): a fresh numpy `RandomState(0)` per batch; each sequence starts in an
    /// episode chosen with probability proportional to its length, at a uniform index that is
    /// never the episode's last, and where that episode ends before `length` steps it goes on
    /// from the start of the next chosen episode, `is_first` set at each join and at the
    /// sequence's first step. The same buffer gives the same batch, whatever the seed.
    PaperCode,
}

/// When training starts and what acts before it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Warmup {
    /// `[train] prefill` steps of uniformly random actions, then training.
    #[default]
    RandomSteps,
    /// The untrained policy acts from the first step, and training starts once the replay
    /// holds `warmup_episodes` episodes, the one running included (the paper's code: its
    /// `train` returns while `len(buffer_eps) < 2 · batch_size`, 32 episodes). Only the
    /// single-process trainer (`train --inline`) runs it. It applies to every algorithm (the
    /// code's SAC baseline started at 200 stored transitions instead).
    Episodes,
}

/// How the race context `c` (each value in `[−r, r]`, `r` = `[train] context_range`) enters
/// the networks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ContextScale {
    /// `c / dreamer.context_range`, in `[−1, 1]` over the training range.
    Normalised,
    /// `c` as it is (the paper's code: ±0.15 in training, ±0.3 in evaluation).
    #[default]
    Raw,
}

impl ContextScale {
    /// What an `[agent]` table saved without `context_scale` meant: checkpoints and run
    /// directories written before the key existed (ctxrace before 2026-12-05) trained with the
    /// normalised context, whatever the default is now.
    pub const SAVED_WITHOUT_KEY: Self = Self::Normalised;

    /// Gives a saved `[agent]` table without `context_scale` the scale it was trained with
    /// ([`ContextScale::SAVED_WITHOUT_KEY`]).
    pub fn fill_saved_table(agent: &mut toml::Table) {
        agent
            .entry("context_scale")
            .or_insert_with(|| "normalised".into());
    }
}

/// Which agent to train and its hyper-parameters (the `[agent]` table).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AgentConfig {
    /// The preset the other keys start from (see [`AgentConfig::from_table`]).
    pub preset: AgentPreset,
    /// The algorithm.
    pub algo: AlgoKind,
    /// How DreamerV3 batches are drawn from the replay (`"uniform"` or `"paper-code"`; SAC's
    /// transitions are always uniform).
    pub sampler: Sampler,
    /// When training starts and what acts before (`"random-steps"` or `"episodes"`).
    pub warmup: Warmup,
    /// Episodes held before training starts with `warmup = "episodes"` (the paper's code: 32).
    pub warmup_episodes: u64,
    /// How the context enters the world model, actor, critic and (cMask) the masked context
    /// (`"normalised"` or `"raw"`), in training and acting alike.
    pub context_scale: ContextScale,
    /// SAC's hyper-parameters (used when `algo = "sac"`).
    pub sac: SacConfig,
    /// DreamerV3's hyper-parameters (the other three algorithms); its `context` follows `algo`.
    pub dreamer: DreamerConfig,
}

impl Default for AgentConfig {
    fn default() -> Self {
        Self {
            preset: AgentPreset::Default,
            algo: AlgoKind::default(),
            sampler: Sampler::Uniform,
            warmup: Warmup::RandomSteps,
            warmup_episodes: 32,
            context_scale: ContextScale::Raw,
            sac: SacConfig::default(),
            dreamer: DreamerConfig::default(),
        }
    }
}

impl AgentConfig {
    /// The learner as the paper's public code trained it (the `paper` branch, c0fd903, Jun
    /// 2025, `TrajectoryAidedLearning/`): batches drawn as cbdreamer's `sample_episodes` drew
    /// them, training from the 32nd stored episode on with the untrained policy acting until
    /// then (`dreamerv3.py` `train`, `TrainAgents.py`), the raw context in the networks, the
    /// networks' initial weights drawn as its PyTorch initialisers draw them.
    pub fn paper_code() -> Self {
        Self {
            preset: AgentPreset::PaperCode,
            sampler: Sampler::PaperCode,
            warmup: Warmup::Episodes,
            warmup_episodes: 32,
            context_scale: ContextScale::Raw,
            sac: SacConfig::default().with_paper_code_sac(),
            dreamer: DreamerConfig {
                mask: MaskConfig::default().with_paper_code_mask(),
                init: WeightInit::PaperCode,
                ..DreamerConfig::default().with_paper_code_world_model()
            },
            ..Self::default()
        }
    }

    /// Reads an `[agent]` table: keys it leaves out take the values of its `preset` (the
    /// default learner when it names none). Unknown keys and bad values are errors naming the
    /// key.
    pub fn from_table(table: toml::Table) -> Result<Self> {
        let cfg = crate::preset::resolve(table, AgentPreset::config)?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads an `[agent]` table a checkpoint saved (`agent.toml`): as [`AgentConfig::from_table`],
    /// a table saved before `context_scale` existed reading as the scale it trained with.
    pub fn from_saved_table(mut table: toml::Table) -> Result<Self> {
        ContextScale::fill_saved_table(&mut table);
        Self::from_table(table)
    }

    /// The DreamerV3 configuration with the context mode of [`AgentConfig::algo`] and the
    /// context scale of [`AgentConfig::context_scale`].
    pub fn dreamer(&self) -> DreamerConfig {
        DreamerConfig {
            context: self.algo.context_mode(),
            context_scale: self.context_scale,
            ..self.dreamer.clone()
        }
    }

    /// Sets the seed of whichever algorithm is chosen.
    pub fn set_seed(&mut self, seed: u64) {
        self.sac.seed = seed;
        self.dreamer.seed = seed;
    }

    /// The seed of the chosen algorithm.
    pub fn seed(&self) -> u64 {
        match self.algo {
            AlgoKind::Sac => self.sac.seed,
            AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => self.dreamer.seed,
        }
    }

    /// The batches the chosen algorithm trains on.
    pub fn batch_spec(&self) -> BatchSpec {
        match self.algo {
            AlgoKind::Sac => BatchSpec::Transition {
                batch: self.sac.batch_size,
                frames: self.sac.frames,
                reward_delay: self.sac.reward_delay,
            },
            AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => BatchSpec::Sequence {
                batch: self.dreamer.batch,
                length: self.dreamer.length,
            },
        }
    }

    /// Whether actors store steps as the paper's code does ([`StepAlignment::PaperCode`]):
    /// a DreamerV3 variant with `step_alignment = "paper-code"`.
    pub fn stores_paper_code_rows(&self) -> bool {
        match self.algo {
            AlgoKind::Sac => false,
            AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => {
                self.dreamer.step_alignment == StepAlignment::PaperCode
            }
        }
    }

    /// Checks the chosen algorithm's configuration.
    pub fn validate(&self) -> Result<()> {
        if self.warmup == Warmup::Episodes && self.warmup_episodes == 0 {
            bail!(
                "warmup_episodes = 0 must be at least 1 with warmup = \"episodes\" (the paper's \
                 code: 32)"
            );
        }
        // both families' keys, whichever algorithm runs: a key is bounded whether or not
        // this run reads it
        self.sac.validate()?;
        self.dreamer().validate()
    }
}

/// Checks a `target_every` key (named `key` in the error).
pub(crate) fn check_target_every(key: &str, every: usize) -> Result<()> {
    if every == 0 {
        bail!("{key} must be at least 1 (1: a Polyak update every step, 2: every second step)");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_std_bounds_are_checked() {
        assert!(validate_log_std_clamp("sac.log_std_clamp", [-20.0, 2.0]).is_ok());
        for bad in [[2.0, -20.0], [1.0, 1.0], [f64::NAN, 2.0]] {
            let err = validate_log_std_clamp("sac.log_std_clamp", bad)
                .unwrap_err()
                .to_string();
            assert!(err.contains("sac.log_std_clamp must be"), "{err}");
        }
    }

    #[test]
    fn a_table_that_its_preset_cannot_read_names_the_preset_or_the_key() {
        let table = |text: &str| toml::from_str::<toml::Table>(text).unwrap();
        let err = AgentConfig::from_table(table("preset = \"paper\"")).unwrap_err();
        assert!(
            matches!(err, AgentConfigError::Preset(PresetError::Unknown(_))),
            "{err:?}"
        );
        assert!(
            err.to_string().starts_with("preset: ")
                && err
                    .to_string()
                    .ends_with("(use \"default\" or \"paper-code\")"),
            "{err}"
        );
        let err =
            AgentConfig::from_table(table("preset = \"paper-code\"\nalgoo = \"sac\"")).unwrap_err();
        assert!(
            matches!(err, AgentConfigError::Preset(PresetError::Value(_))),
            "{err:?}"
        );
        assert!(err.to_string().contains("unknown field `algoo`"), "{err}");
        let err = AgentConfig::from_table(table(
            "preset = \"paper-code\"\nalgo = \"sac\"\n[sac]\nlog_std_clamp = [2.0, -20.0]",
        ))
        .unwrap_err();
        assert_eq!(
            err,
            AgentConfigError::LogStdClamp(LogStdClampError {
                key: "agent.sac.log_std_clamp".into(),
                bounds: [2.0, -20.0]
            })
        );
    }

    #[test]
    fn agent_tables_parse_with_defaults_and_reject_unknown_keys() {
        let agent: AgentConfig =
            toml::from_str("algo = \"cmask\"\n[dreamer]\nhorizon = 5\n[dreamer.mask]\ntau = 0.01")
                .unwrap();
        let cfg = agent.dreamer();
        assert_eq!(
            (cfg.context, cfg.horizon, cfg.mask.tau, cfg.gamma),
            (ContextMode::Cmask, 5, 0.01, 0.997)
        );
        assert_eq!(agent.sac, SacConfig::default());
        assert_eq!(cfg.imagination, ImaginationLoss::PaperCode);
        let form = |text: &str| toml::from_str::<AgentConfig>(text).map(|a| a.dreamer());
        let cfg = form("[dreamer]\nimagination = \"dreamerv3\"\nhorizon = 1").unwrap();
        assert_eq!(cfg.imagination, ImaginationLoss::Dreamerv3);
        assert!(cfg.validate().is_ok());
        let err = form("[dreamer]\nhorizon = 1")
            .unwrap()
            .validate()
            .unwrap_err();
        assert!(
            err.to_string().contains("horizon must be at least 2"),
            "{err}"
        );
        for bad in [
            "[dreamer]\nimagination = \"danijar\"",
            "[dreamer]\nhorizn = 5",
            "[dreamer]\ncontext = \"crssm\"",
            "algo = \"ppo\"",
            "algo = \"sac\"\n[sac]\nframes = 0",
        ] {
            let parsed = toml::from_str::<AgentConfig>(bad);
            assert!(
                parsed.is_err() || parsed.unwrap().validate().is_err(),
                "{bad:?} accepted"
            );
        }
        assert_eq!("CMask".parse::<AlgoKind>(), Ok(AlgoKind::Cmask));
        assert_eq!(
            AgentConfig::from_table(toml::Table::new()).unwrap(),
            AgentConfig::default()
        );
        let cfg = form("algo = \"cmask\"\n[dreamer.mask]\nmask_space = \"paper-code\"").unwrap();
        assert_eq!(cfg.mask.mask_space, MaskSpace::PaperCode);
        let err = "ppo".parse::<AlgoKind>().unwrap_err();
        assert_eq!(err, UnknownAlgorithm("ppo".into()));
        assert!(err.to_string().contains("expected one of"));
    }

    #[test]
    fn the_paper_code_preset_fills_what_a_file_leaves_out() {
        let table = |text: &str| toml::from_str::<toml::Table>(text).unwrap();
        let a = AgentConfig::from_table(table(
            "preset = \"paper-code\"\nalgo = \"crssm\"\ncontext_scale = \"normalised\"\n\
             [dreamer]\nhorizon = 5",
        ))
        .unwrap();
        assert_eq!(
            (a.preset, a.algo, a.sampler, a.warmup, a.warmup_episodes),
            (
                AgentPreset::PaperCode,
                AlgoKind::Crssm,
                Sampler::PaperCode,
                Warmup::Episodes,
                32
            )
        );
        // the file's key overrides the preset's
        assert_eq!(a.context_scale, ContextScale::Normalised);
        assert_eq!(a.dreamer.horizon, 5);
        let p = AgentConfig::paper_code();
        assert_eq!(p.context_scale, ContextScale::Raw);
        assert_eq!(p.dreamer().context_divisor(), 1.0);
        assert_eq!(AgentConfig::default().dreamer().context_divisor(), 1.0);
        // a resolved configuration round-trips, preset included
        let text = toml::to_string(&a).unwrap();
        assert_eq!(AgentConfig::from_table(table(&text)).unwrap(), a);
        let d = AgentConfig::default();
        assert_eq!(
            (d.sampler, d.warmup, d.context_scale),
            (Sampler::Uniform, Warmup::RandomSteps, ContextScale::Raw)
        );
    }

    /// A checkpoint's `agent.toml` written before `context_scale` existed trained with the
    /// normalised context and still acts with it; one written since keeps its own key.
    #[test]
    fn a_saved_table_without_context_scale_reads_as_normalised() {
        let table = |text: &str| toml::from_str::<toml::Table>(text).unwrap();
        let old = AgentConfig::from_saved_table(table("algo = \"cmask\"")).unwrap();
        assert_eq!(old.context_scale, ContextScale::Normalised);
        assert_eq!(old.dreamer().context_divisor(), 0.15);
        let saved = toml::to_string(&AgentConfig::default()).unwrap();
        let new = AgentConfig::from_saved_table(table(&saved)).unwrap();
        assert_eq!(new.context_scale, ContextScale::Raw);
        // a user's file without the key takes today's default
        let user = AgentConfig::from_table(table("algo = \"cmask\"")).unwrap();
        assert_eq!(user.context_scale, ContextScale::Raw);
    }

    #[test]
    fn world_model_keys_default_to_ctxrace_and_name_themselves_when_wrong() {
        let cfg = DreamerConfig::default();
        assert_eq!(
            (cfg.step_alignment, cfg.initial_state),
            (StepAlignment::Ctxrace, InitialState::Zeros)
        );
        let code = cfg.clone().with_paper_code_world_model();
        assert_eq!(
            (code.step_alignment, code.initial_state),
            (StepAlignment::PaperCode, InitialState::Learned)
        );
        assert_eq!(
            DreamerConfig {
                step_alignment: StepAlignment::Ctxrace,
                initial_state: InitialState::Zeros,
                ..code.clone()
            },
            cfg
        );
        assert_eq!(
            (cfg.encoder_inputs(108, 2), code.encoder_inputs(108, 2)),
            (108, 110)
        );
        let agent: AgentConfig = toml::from_str(
            "[dreamer]\nstep_alignment = \"paper-code\"\ninitial_state = \"learned\"",
        )
        .unwrap();
        assert_eq!(agent.dreamer(), code);
        assert!(agent.stores_paper_code_rows());
        let sac = AgentConfig {
            algo: AlgoKind::Sac,
            ..agent
        };
        assert!(!sac.stores_paper_code_rows());
        for (key, bad) in [("step_alignment", "paper"), ("initial_state", "random")] {
            let err = toml::from_str::<AgentConfig>(&format!("[dreamer]\n{key} = \"{bad}\""))
                .unwrap_err()
                .to_string();
            assert!(err.contains(key) && err.contains(bad), "{err}");
        }
    }

    /// The paper-code methods set the code's values and only the keys they own; ctxrace's
    /// defaults are the present behaviour.
    #[test]
    fn the_paper_code_methods_set_the_codes_values() {
        let sac = SacConfig::default();
        assert_eq!(
            (sac.reward_delay, sac.target_noise, sac.explore_noise),
            (0, 0.0, 0.0)
        );
        assert!(sac.reset_frame_stack && sac.target_every == 1);
        let code = sac.clone().with_paper_code_sac();
        assert_eq!(
            (code.reward_delay, code.target_noise, code.target_noise_clip),
            (1, 0.5, 0.5)
        );
        assert_eq!((code.explore_noise, code.target_every), (0.1, 2));
        assert!(!code.reset_frame_stack);
        assert_eq!(code.log_std_clamp, [-20.0, 2.0]);
        assert_eq!((code.gamma, code.hidden, code.frames), (sac.gamma, 100, 2));
        assert!(code.validate().is_ok());
        let mask = MaskConfig::default();
        assert_eq!(mask.mask_space, MaskSpace::Unit);
        assert!(!mask.bootstrap_terminals);
        let code = mask.clone().with_paper_code_mask();
        assert_eq!(code.mask_space, MaskSpace::PaperCode);
        assert!(code.bootstrap_terminals);
        assert_eq!((code.target_every, code.reward_delay), (2, 1));
        assert_eq!(
            (code.log_std_clamp, code.target_entropy),
            ([-20.0, 2.0], -2.0)
        );
        assert_eq!((code.units, code.lr, code.gamma), (256, 3e-5, 0.99));
        assert!(code.validate().is_ok());
    }

    /// Every key of the paper-code variants rejects a bad value with an error naming it.
    #[test]
    fn the_paper_code_keys_reject_bad_values_by_name() {
        for (text, key) in [
            (
                "algo = \"sac\"\n[sac]\nreward_delay = 2",
                "agent.sac.reward_delay",
            ),
            (
                "algo = \"sac\"\n[sac]\ntarget_noise = -0.5",
                "agent.sac.target_noise ",
            ),
            (
                "algo = \"sac\"\n[sac]\ntarget_noise_clip = nan",
                "agent.sac.target_noise_clip",
            ),
            (
                "algo = \"sac\"\n[sac]\nexplore_noise = inf",
                "agent.sac.explore_noise",
            ),
            (
                "algo = \"sac\"\n[sac]\ntarget_every = 0",
                "agent.sac.target_every",
            ),
            (
                "algo = \"sac\"\n[sac]\nlog_std_clamp = [2.0, -20.0]",
                "agent.sac.log_std_clamp",
            ),
            (
                "algo = \"cmask\"\n[dreamer.mask]\ntarget_every = 0",
                "agent.dreamer.mask.target_every",
            ),
            (
                "algo = \"cmask\"\n[dreamer.mask]\nreward_delay = 3",
                "agent.dreamer.mask.reward_delay",
            ),
            (
                "algo = \"cmask\"\n[dreamer.mask]\nlog_std_clamp = [1.0, 1.0]",
                "agent.dreamer.mask.log_std_clamp",
            ),
            (
                "algo = \"cmask\"\n[dreamer.mask]\ntarget_entropy = nan",
                "agent.dreamer.mask.target_entropy",
            ),
            (
                "algo = \"cmask\"\n[dreamer.mask]\nunits = 0",
                "agent.dreamer.mask.units",
            ),
        ] {
            let agent: AgentConfig = toml::from_str(text).unwrap();
            let err = agent.validate().unwrap_err().to_string();
            assert!(err.contains(key), "{text:?}: {err}");
        }
        for text in [
            "[dreamer.mask]\nmask_space = \"sigmoid\"",
            "[dreamer.mask]\nbootstrap_terminals = 1",
            "[sac]\nreset_frame_stack = \"no\"",
            "[sac]\nlog_std_clamp = [-20.0]",
        ] {
            let err = toml::from_str::<AgentConfig>(text).unwrap_err().to_string();
            let key = text.split(['\n', ' ']).nth(1).unwrap();
            assert!(err.contains(key), "{text:?}: {err}");
        }
    }
}
