//! SAC's hyper-parameters (`[agent.sac]`), the paper's baseline by default.

use super::{check_target_every, validate_log_std_clamp, AgentConfigError, Result, LOG_STD_CLAMP};
use serde::{Deserialize, Serialize};

/// SAC's hyperparameters; the defaults are the paper's baseline.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SacConfig {
    /// Hidden layer width of the actor and the critics.
    pub hidden: usize,
    /// Number of hidden layers of the actor and the critics.
    pub layers: usize,
    /// Transitions per training batch (drawn by the caller).
    pub batch_size: usize,
    /// Actor learning rate.
    pub actor_lr: f64,
    /// Critic learning rate.
    pub critic_lr: f64,
    /// Temperature (`log α`) learning rate.
    pub alpha_lr: f64,
    /// Discount factor `γ`.
    pub gamma: f64,
    /// Polyak coefficient `τ` of the target critics.
    pub tau: f64,
    /// Initial temperature `α`.
    pub initial_alpha: f64,
    /// Target entropy `H̄`; `−|A|` when unset.
    pub target_entropy: Option<f64>,
    /// Seed of the initial weights and of the sampling noise.
    pub seed: u64,
    /// Consecutive LiDAR frames stacked into one observation (the paper's 2).
    pub frames: usize,
    /// Steps by which a transition's reward lags its action: 0 pairs `(o_t, a_t, o_{t+1})` with
    /// the reward `a_t` earned; 1 with the next action's reward (and its terminal flag), as the
    /// paper's code's windowed replay buffer does.
    pub reward_delay: usize,
    /// Standard deviation of TD3-style smoothing noise added to the target's next actions
    /// (0: none, plain SAC).
    pub target_noise: f64,
    /// Bound of the smoothing noise: it is clipped to `±target_noise_clip`, and the noisy next
    /// action to `[−1, 1]`.
    pub target_noise_clip: f64,
    /// Standard deviation of Gaussian noise the acting policy adds to its action (then clipped
    /// to `[−1, 1]`), in training and in evaluation, sampled or deterministic alike (0: none).
    pub explore_noise: f64,
    /// Whether the acting policy empties its frame stack at each episode's start (else the
    /// first observation of an episode is stacked behind the previous episode's last).
    pub reset_frame_stack: bool,
    /// Gradient steps per Polyak update of the target critics (1: every step; 2: on every
    /// second step, the first included).
    pub target_every: usize,
    /// Bounds `[lower, upper]` of the actor's log standard deviation.
    pub log_std_clamp: [f64; 2],
}

impl Default for SacConfig {
    fn default() -> Self {
        Self {
            hidden: 100,
            layers: 2,
            batch_size: 100,
            actor_lr: 3e-5,
            critic_lr: 3e-5,
            alpha_lr: 3e-5,
            gamma: 0.85,
            tau: 0.005,
            initial_alpha: 1.0,
            target_entropy: None,
            seed: 0,
            frames: 2,
            reward_delay: 0,
            target_noise: 0.0,
            target_noise_clip: 0.5,
            explore_noise: 0.0,
            reset_frame_stack: true,
            target_every: 1,
            log_std_clamp: LOG_STD_CLAMP,
        }
    }
}

impl SacConfig {
    /// Checks sizes and ranges, naming the offending key.
    pub fn validate(&self) -> Result<()> {
        if self.hidden == 0 || self.frames == 0 || self.batch_size == 0 {
            bail!(
                "SAC config: hidden, frames and batch_size must be positive (got {}, {}, {})",
                self.hidden,
                self.frames,
                self.batch_size
            );
        }
        if !(0.0..=1.0).contains(&self.gamma) || !(0.0..=1.0).contains(&self.tau) {
            bail!(
                "SAC config: gamma and tau must lie in [0, 1], got {} and {}",
                self.gamma,
                self.tau
            );
        }
        let lrs = [self.actor_lr, self.critic_lr, self.alpha_lr];
        if lrs.iter().any(|lr| !(lr.is_finite() && *lr >= 0.0))
            || !(self.initial_alpha.is_finite() && self.initial_alpha > 0.0)
        {
            bail!(
                "SAC config: learning rates must be >= 0 and initial_alpha > 0, got {lrs:?} and {}",
                self.initial_alpha
            );
        }
        if self.reward_delay > 1 {
            bail!(
                "agent.sac.reward_delay must be 0 (the reward of the transition's own action) or 1 \
                 (the next action's, as the paper's code pairs them), got {}",
                self.reward_delay
            );
        }
        let noises = [
            ("target_noise", self.target_noise),
            ("target_noise_clip", self.target_noise_clip),
            ("explore_noise", self.explore_noise),
        ];
        if let Some((key, v)) = noises.iter().find(|(_, v)| !(v.is_finite() && *v >= 0.0)) {
            bail!("agent.sac.{key} must be a finite standard deviation >= 0 (0: none), got {v}");
        }
        check_target_every("agent.sac.target_every", self.target_every)?;
        validate_log_std_clamp("agent.sac.log_std_clamp", self.log_std_clamp)?;
        Ok(())
    }

    /// This configuration with the SAC baseline as the paper's code trained it (commit c0fd903,
    /// `TrajectoryAidedLearning/Utils/SAC.py`, `Utils/Buffer.py`, `Planners/SACPlanners.py`):
    /// the reward one step late, target smoothing noise `N(0, 0.5)` clipped at `±0.5`,
    /// exploration noise `N(0, 0.1)` in training and evaluation, a frame stack never reset,
    /// the target critics updated every second step and `log σ` clamped to `[−20, 2]`.
    pub fn with_paper_code_sac(self) -> Self {
        Self {
            reward_delay: 1,
            target_noise: 0.5,
            target_noise_clip: 0.5,
            explore_noise: 0.1,
            reset_frame_stack: false,
            target_every: 2,
            log_std_clamp: [-20.0, 2.0],
            ..self
        }
    }
}
