//! Training batches as plain row-major `f32` buffers, so that the replay process can build them
//! without a tensor library and the learner can turn them into tensors without copying twice.

/// `B` transitions `(o, a, r, o', terminal, c)`: the input of SAC.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TransitionBatch {
    /// Batch size `B`.
    pub batch: usize,
    /// Observation size `O`.
    pub obs_dim: usize,
    /// Action size `A`.
    pub act_dim: usize,
    /// `[B, O]` observations.
    pub obs: Vec<f32>,
    /// `[B, A]` actions in `[-1, 1]`.
    pub action: Vec<f32>,
    /// `[B]` rewards.
    pub reward: Vec<f32>,
    /// `[B, O]` next observations.
    pub next_obs: Vec<f32>,
    /// `[B]` 1 where the episode terminated at the next observation (not on truncation).
    pub terminal: Vec<f32>,
    /// `[B, 2]` episode contexts.
    pub context: Vec<f32>,
}

/// `B` sequences of `T` steps: the input of DreamerV3, cRSSM and cMask. Step `t` holds the
/// observation `o_t`, the action `a_{t-1}` that led to it (zero at the first step), the reward
/// `r_t` received on arriving, and flags; `is_first` marks the start of an episode inside the
/// sequence.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SequenceBatch {
    /// Batch size `B`.
    pub batch: usize,
    /// Sequence length `T`.
    pub length: usize,
    /// Observation size `O`.
    pub obs_dim: usize,
    /// Action size `A`.
    pub act_dim: usize,
    /// `[B, T, O]`.
    pub obs: Vec<f32>,
    /// `[B, T, A]`: the action taken before step `t`.
    pub action: Vec<f32>,
    /// `[B, T]`.
    pub reward: Vec<f32>,
    /// `[B, T]`.
    pub is_first: Vec<f32>,
    /// `[B, T]`.
    pub is_terminal: Vec<f32>,
    /// `[B, T, 2]` the episode's context at each step.
    pub context: Vec<f32>,
}
