//! DreamerV3's hyper-parameters (`[agent.dreamer]`): the world model, behaviour learning, how
//! the context enters (none, cRSSM, cMask) and cMask's mask SAC (`[agent.dreamer.mask]`).

use super::{
    check_target_every, validate_log_std_clamp, AgentConfigError, ContextScale, Result,
    LOG_STD_CLAMP,
};
use serde::{Deserialize, Serialize};

/// Size of the context `c` and of the mask `m`.
pub const CONTEXT_DIM: usize = 2;

/// How the race context enters the agent.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ContextMode {
    /// DreamerV3: no context.
    #[default]
    None,
    /// cRSSM: the normalised context.
    Crssm,
    /// cMask: the normalised context times a mask from a SAC actor.
    Cmask,
}

impl ContextMode {
    /// Size of the context input of the model (0 or [`CONTEXT_DIM`]).
    pub fn context_dim(self) -> usize {
        match self {
            ContextMode::None => 0,
            ContextMode::Crssm | ContextMode::Cmask => CONTEXT_DIM,
        }
    }
}

/// How cMask's mask SAC maps its actor's squashed sample `tanh u` to masks: which mask acts
/// and is stored, where the critics are evaluated, and whose density `log π` is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskSpace {
    /// ctxrace: one space throughout. The mask `m = (1 + tanh u) / 2 ∈ (0, 1)²` acts, is
    /// stored, and is the critics' input in all three losses; `log π` is the mask's density,
    /// `log π(tanh u) + 2 ln 2`. The target entropy `H̄` therefore applies to `m`: the default
    /// `−2` is `−2 + 2 ln 2 ≈ −0.614` on `tanh u` (the code's `−2` on `tanh u` is `≈ −3.386`
    /// on `m`).
    #[default]
    Unit,
    /// The paper's code (c0fd903, `Utils/cbdreamer/cbmodels.py`, `CtxMask`): the mask
    /// `sigmoid(tanh u) ∈ (0.27, 0.73)²` acts and is stored, and the critics are fitted on the
    /// stored masks; the actor's loss evaluates them at `tanh u ∈ (−1, 1)²`, the target at
    /// `clamp(tanh u', 0, 1)`; `log π` is the density of `tanh u`.
    PaperCode,
}

/// Hyper-parameters of cMask's mask SAC.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MaskConfig {
    /// Hidden units of the mask actor and critics (ReLU).
    pub units: usize,
    /// Hidden layers of the mask actor and critics.
    pub layers: usize,
    /// Adam learning rate of actor, critics and temperature.
    pub lr: f64,
    /// Polyak rate of the target critics.
    pub tau: f64,
    /// Discount of the mask critics (the paper gives none: SAC's usual 0.99).
    pub gamma: f64,
    /// Target entropy `H̄` of the mask distribution (`−|m|`), of the density [`MaskSpace`] names
    /// (with `mask_space = "unit"` the default `−2` on `m` is `≈ −0.614` on `tanh u`).
    pub target_entropy: f64,
    /// Initial temperature `α` (the paper gives none).
    pub init_alpha: f64,
    /// The masks' space ([`MaskSpace`]): `"unit"` or `"paper-code"`.
    pub mask_space: MaskSpace,
    /// Whether the critics' target bootstraps at a terminal step too (`y = r + γ V(o')` always,
    /// as the paper's code does) instead of `y = r` there.
    pub bootstrap_terminals: bool,
    /// Steps per Polyak update of the target critics (1: every step; 2: on every second step,
    /// the first included).
    pub target_every: usize,
    /// Bounds `[lower, upper]` of the mask actor's log standard deviation.
    pub log_std_clamp: [f64; 2],
    /// Steps by which a transition's reward lags its mask: 0 pairs `(o_t, m_t)` with the reward
    /// `r_{t+1}` the step earned; 1 with `r_{t+2}`, as the paper's code pairs its rows.
    pub reward_delay: usize,
    /// The context behaviour learning imagines with ([`ImaginationContext`]): `"masked"` or
    /// `"raw"`.
    pub imagination_context: ImaginationContext,
}

impl Default for MaskConfig {
    fn default() -> Self {
        Self {
            units: 256,
            layers: 2,
            lr: 3e-5,
            tau: 0.005,
            gamma: 0.99,
            target_entropy: -2.0,
            init_alpha: 1.0,
            mask_space: MaskSpace::Unit,
            bootstrap_terminals: false,
            target_every: 1,
            log_std_clamp: LOG_STD_CLAMP,
            reward_delay: 0,
            imagination_context: ImaginationContext::Masked,
        }
    }
}

/// The context cMask's imagined trajectories carry (`[agent.dreamer.mask] imagination_context`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ImaginationContext {
    /// The masked context `m ⊙ c` of each start state, as the world model saw it and the
    /// policy acts with.
    #[default]
    Masked,
    /// The unmasked `c` (scaled as the networks read it): the paper's code (c0fd903,
    /// `Utils/cbdreamer/dreamerv3.py` l. 239 hands behaviour learning the batch's raw
    /// `data['context']`, `cbmodels.py` l. 594-595, 651-667), while its world model and acting
    /// policy read the masked one.
    Raw,
}

impl MaskConfig {
    /// Checks the keys, naming the offending one.
    pub fn validate(&self) -> Result<()> {
        if self.units == 0 {
            bail!("agent.dreamer.mask.units must be positive");
        }
        check_target_every("agent.dreamer.mask.target_every", self.target_every)?;
        validate_log_std_clamp("agent.dreamer.mask.log_std_clamp", self.log_std_clamp)?;
        if self.reward_delay > 1 {
            bail!(
                "agent.dreamer.mask.reward_delay must be 0 (the reward the mask's step earned) or 1 \
                 (the next step's, as the paper's code pairs them), got {}",
                self.reward_delay
            );
        }
        if !self.target_entropy.is_finite() {
            bail!(
                "agent.dreamer.mask.target_entropy must be finite, got {}",
                self.target_entropy
            );
        }
        Ok(())
    }

    /// This configuration with the mask SAC as the paper's code trained it (commit c0fd903,
    /// `TrajectoryAidedLearning/Utils/cbdreamer/cbmodels.py`, `CtxMask`): the code's mask
    /// spaces, bootstrapping at terminals, the target critics updated every second step,
    /// `log σ` clamped to `[−20, 2]` and the reward one step late. The code's entropy target
    /// `−2` (on `tanh u` there) is `target_entropy`'s default, which `mask_space` applies to
    /// `tanh u`; its other values (`units` 256, `layers` 2, `lr` 3e-5, `tau` 0.005, `gamma` 0.99)
    /// are the defaults too.
    pub fn with_paper_code_mask(self) -> Self {
        Self {
            mask_space: MaskSpace::PaperCode,
            bootstrap_terminals: true,
            target_every: 2,
            log_std_clamp: [-20.0, 2.0],
            reward_delay: 1,
            imagination_context: ImaginationContext::Raw,
            ..self
        }
    }
}

/// What behaviour learning differentiates, and over how many imagined steps: the paper's code
/// (dreamerv3-torch, which produced its tables) or the form ctxrace used before it followed the
/// code (DreamerV3's horizon count and danijar/dreamerv3's weights).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ImaginationLoss {
    /// The paper's code: `H` states from the start (`H − 1` imagined steps and returns),
    /// weights `w_0 = 1`, `w_t = w_{t−1} γ c(s_{t−1})`, and the actor's gradient through
    /// everything the imagined states feed: the returns' rewards, continue probabilities and
    /// values, the baseline `v(s_t)`, and the entropy term `−η H[π(·|s_t)]` (not weighted).
    #[default]
    PaperCode,
    /// `H` imagined steps (`H + 1` states), `w_0 = 1 − terminal` of the start and
    /// `w_t = w_{t−1} γ c(s_t)`; the actor's gradient through the returns' rewards and values
    /// only (stop-gradient baseline and continue probabilities), its entropy term weighted by
    /// `w_t` and taken on stop-gradient states.
    Dreamerv3,
}

/// What a stored step holds and what the world model reads from it (`[agent.dreamer]
/// step_alignment`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StepAlignment {
    /// DreamerV3's rows: `(o_t, a_{t−1}, r_t)`, the reset observation stored with a zero action,
    /// the terminal flag on the last observation; the sequence model reads `a_{t−1}` before the
    /// posterior of `o_t`, in training as in acting; the encoder reads `symlog o_t` and the
    /// decoder reconstructs it.
    #[default]
    Ctxrace,
    /// The paper's code (c0fd903, `Planners/*DreamerPlanners.py` `add_memory_entry` and
    /// `Utils/dreamerv3/networks.py` `MultiEncoder`/`MultiDecoder`): rows `(o_t, a_t, r_{t+1})`
    /// (the action chosen after seeing `o_t`), the last observation of an episode never
    /// stored and the terminal flag on the row before it; training feeds the row's action `a_t`
    /// to the sequence model before the posterior of `o_t` (zero where a sequence starts), while
    /// acting feeds `a_{t−1}`; the encoder reads `symlog [o_t, a]` (the row's action in training,
    /// the previous one in acting) and the decoder reconstructs `symlog [o_t, a_t]` (its action
    /// target zeroed where an episode starts inside a sequence, as the code's in-place
    /// `prev_action *= 1 − is_first` leaves it).
    PaperCode,
}

/// The RSSM state a sequence starts from (`[agent.dreamer] initial_state`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InitialState {
    /// `h = 0`, `z = 0`.
    #[default]
    Zeros,
    /// The paper's code (`initial: learned`, `networks.py` `RSSM.initial`): `h = tanh(w)` for a
    /// learned `w` (starting at zero, the parameter `rssm.initial_state.w`), `z` the mode of the
    /// prior `p(z | h)` (one-hot of the most likely class, its gradient straight through the
    /// log-probabilities).
    Learned,
}

/// How the DreamerV3 networks' initial weights are drawn (`[agent.dreamer] init`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WeightInit {
    /// Every matrix uniform in `±1/√fan_in`, biases zero (`ctxrace_nn::parameters::ctxrace_draw`).
    #[default]
    Ctxrace,
    /// The paper's code (c0fd903, `Utils/dreamerv3/tools.py` `weight_init` and
    /// `uniform_weight_init`, cbmodels.py `weights_init_`): hidden layers a truncated normal of
    /// variance `1/fan_avg`, output layers uniform of variance `outscale/fan_avg` (outscale 1
    /// for the latent logits, the decoder, the continue head and the actor, each joined part
    /// by its own fan; 0 for the reward head and the critic), the mask SAC's layers Xavier
    /// uniform; `fan_avg = (fan_in + fan_out) / 2` (`ctxrace_nn::parameters::fan_avg_draw`).
    PaperCode,
}

/// DreamerV3's hyper-parameters; the defaults are the paper's (REFERENCE §5).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DreamerConfig {
    /// Context mode: DreamerV3, cRSSM or cMask (not read from files: [`AgentConfig::algo`]
    /// decides it).
    #[serde(skip)]
    pub context: ContextMode,
    /// How the context is scaled for the networks (not read from files:
    /// [`AgentConfig::context_scale`] decides it).
    #[serde(skip)]
    pub context_scale: ContextScale,
    /// Encoder and decoder width (the embedding size too).
    pub units: usize,
    /// Encoder and decoder depth.
    pub layers: usize,
    /// GRU state size.
    pub deter: usize,
    /// RSSM hidden size.
    pub hidden: usize,
    /// Number of categorical latent variables.
    pub stoch: usize,
    /// Classes per latent variable.
    pub classes: usize,
    /// Uniform mixture of the latent distributions.
    pub unimix: f64,
    /// Width of the reward, continue, actor and critic heads.
    pub head_units: usize,
    /// Depth of the reward, continue, actor and critic heads.
    pub head_layers: usize,
    /// Two-hot bins of the reward and critic heads.
    pub bins: usize,
    /// Free nats of each KL term.
    pub free_nats: f64,
    /// Weight of the dynamics KL `KL(sg q ‖ p)`.
    pub kl_dyn: f64,
    /// Weight of the representation KL `KL(q ‖ sg p)`.
    pub kl_rep: f64,
    /// Weight of the prediction losses.
    pub pred_scale: f64,
    /// World-model learning rate.
    pub model_lr: f64,
    /// World-model Adam ε.
    pub model_eps: f64,
    /// World-model gradient-norm limit.
    pub model_clip: f64,
    /// Actor and critic learning rate.
    pub ac_lr: f64,
    /// Actor and critic Adam ε.
    pub ac_eps: f64,
    /// Actor and critic gradient-norm limit.
    pub ac_clip: f64,
    /// Imagination horizon `H`.
    pub horizon: usize,
    /// The imagination losses' form ([`ImaginationLoss`]): `"paper-code"` or `"dreamerv3"`.
    pub imagination: ImaginationLoss,
    /// Discount `γ`.
    pub gamma: f64,
    /// Return mixing `λ`.
    pub lambda: f64,
    /// Actor entropy bonus `η`.
    pub entropy: f64,
    /// EMA decay of the return percentiles.
    pub return_decay: f64,
    /// Low return percentile (fraction).
    pub return_low: f64,
    /// High return percentile (fraction).
    pub return_high: f64,
    /// Slow critic EMA rate (per step).
    pub slow_critic_rate: f64,
    /// Weight of the slow-critic regulariser.
    pub slow_critic_reg: f64,
    /// Smallest actor standard deviation.
    pub min_std: f64,
    /// Largest actor standard deviation.
    pub max_std: f64,
    /// Sequences per batch (for the replay sampler).
    pub batch: usize,
    /// Steps per sequence (for the replay sampler).
    pub length: usize,
    /// Training context range: `c` is divided by it (with `context_scale = "normalised"`).
    pub context_range: f64,
    /// cMask's mask SAC.
    pub mask: MaskConfig,
    /// What a stored step holds and what the world model reads from it ([`StepAlignment`]):
    /// `"ctxrace"` or `"paper-code"`.
    pub step_alignment: StepAlignment,
    /// The RSSM state sequences start from ([`InitialState`]): `"zeros"` or `"learned"`.
    pub initial_state: InitialState,
    /// How the initial weights are drawn ([`WeightInit`]): `"ctxrace"` or `"paper-code"`.
    pub init: WeightInit,
    /// Seed of initialisation and noise.
    pub seed: u64,
}

impl Default for DreamerConfig {
    fn default() -> Self {
        Self {
            context: ContextMode::None,
            context_scale: ContextScale::default(),
            units: 256,
            layers: 3,
            deter: 256,
            hidden: 256,
            stoch: 16,
            classes: 16,
            unimix: 0.01,
            head_units: 256,
            head_layers: 2,
            bins: 255,
            free_nats: 1.0,
            kl_dyn: 0.5,
            kl_rep: 0.1,
            pred_scale: 1.0,
            model_lr: 3e-5,
            model_eps: 1e-8,
            model_clip: 1000.0,
            ac_lr: 3e-5,
            ac_eps: 1e-5,
            ac_clip: 100.0,
            horizon: 10,
            imagination: ImaginationLoss::PaperCode,
            gamma: 0.997,
            lambda: 0.95,
            entropy: 3e-4,
            return_decay: 0.99,
            return_low: 0.05,
            return_high: 0.95,
            slow_critic_rate: 0.02,
            slow_critic_reg: 1.0,
            min_std: 0.1,
            max_std: 1.0,
            batch: 16,
            length: 64,
            context_range: 0.15,
            mask: MaskConfig::default(),
            step_alignment: StepAlignment::Ctxrace,
            initial_state: InitialState::Zeros,
            init: WeightInit::Ctxrace,
            seed: 0,
        }
    }
}

impl DreamerConfig {
    /// What the raw context is divided by before it enters the networks:
    /// [`DreamerConfig::context_range`], or 1 with [`ContextScale::Raw`].
    pub fn context_divisor(&self) -> f64 {
        match self.context_scale {
            ContextScale::Normalised => self.context_range,
            ContextScale::Raw => 1.0,
        }
    }

    /// The world model as the paper's code (c0fd903) trains it: `step_alignment = "paper-code"`
    /// and `initial_state = "learned"`; every other key as it was.
    pub fn with_paper_code_world_model(self) -> Self {
        Self {
            step_alignment: StepAlignment::PaperCode,
            initial_state: InitialState::Learned,
            ..self
        }
    }

    /// Width of the encoder's input for observations of `obs_dim` and actions of `act_dim`:
    /// the observation, and the action too with `step_alignment = "paper-code"`.
    pub fn encoder_inputs(&self, obs_dim: usize, act_dim: usize) -> usize {
        match self.step_alignment {
            StepAlignment::Ctxrace => obs_dim,
            StepAlignment::PaperCode => obs_dim + act_dim,
        }
    }

    /// Checks sizes and ranges, naming the offending key.
    pub fn validate(&self) -> Result<()> {
        let sizes = [
            ("units", self.units),
            ("deter", self.deter),
            ("hidden", self.hidden),
            ("stoch", self.stoch),
            ("classes", self.classes),
            ("head_units", self.head_units),
            ("horizon", self.horizon),
        ];
        if let Some((name, _)) = sizes.iter().find(|(_, v)| *v == 0) {
            bail!("DreamerV3 config: {name} must be positive");
        }
        if self.bins < 2 {
            bail!("DreamerV3 config: bins must be at least 2");
        }
        if self.imagination == ImaginationLoss::PaperCode && self.horizon < 2 {
            bail!(
                "DreamerV3 config: horizon must be at least 2 with imagination = \"paper-code\" \
                 (its H states include the start), got {}",
                self.horizon
            );
        }
        if self.context_range.is_nan() || self.context_range <= 0.0 {
            bail!("DreamerV3 config: context_range must be positive");
        }
        if !(0.0 < self.min_std && self.min_std < self.max_std) {
            bail!("DreamerV3 config: need 0 < min_std < max_std");
        }
        self.mask.validate()
    }
}
