//! One env step as an actor reports it, and its layout in a trajectory chunk: what the actors
//! send, the replay stores and the single-process trainer passes from its source to its store.

/// Floats of a step besides its observation and action: reward, the flags is_first,
/// is_terminal, is_last and has_mask, the two context values and the two mask values.
pub const STEP_EXTRA: usize = 9;
/// Floats one step takes in a chunk:
/// `obs | action | reward, is_first, is_terminal, is_last, has_mask | context | mask`.
pub fn step_stride(obs_dim: usize, act_dim: usize) -> usize {
    obs_dim + act_dim + STEP_EXTRA
}

/// One env step as an actor reports it (SequenceBatch's convention).
#[derive(Clone, Copy, Debug)]
pub struct TrajectoryStep<'a> {
    /// The observation reached: one LiDAR frame.
    pub obs: &'a [f32],
    /// The action taken before this step; zero at the episode's first step.
    pub action: &'a [f32],
    /// Reward received on arriving at this step.
    pub reward: f32,
    /// First step of an episode.
    pub is_first: bool,
    /// The episode terminated at this observation (not on truncation).
    pub is_terminal: bool,
    /// The episode ended here, terminated or truncated.
    pub is_last: bool,
    /// The episode's context.
    pub context: [f32; 2],
    /// cMask's context mask `∈ [0, 1]²` with which the action was chosen, if any.
    pub mask: Option<[f32; 2]>,
}

impl TrajectoryStep<'_> {
    /// Appends the step in the chunk layout ([`step_stride`] floats:
    /// `obs | action | reward, is_first, is_terminal, is_last, has_mask | context | mask`,
    /// the mask zero without one).
    pub fn encode(&self, out: &mut Vec<f32>) {
        let flag = |b: bool| if b { 1.0 } else { 0.0 };
        let mask = self.mask.unwrap_or([0.0; 2]);
        out.extend_from_slice(self.obs);
        out.extend_from_slice(self.action);
        out.extend_from_slice(&[
            self.reward,
            flag(self.is_first),
            flag(self.is_terminal),
            flag(self.is_last),
            flag(self.mask.is_some()),
            self.context[0],
            self.context[1],
            mask[0],
            mask[1],
        ]);
    }
}
