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
/// observation `o_t`, the action `a_{t-1}` that led to it (zero at the first step) and cMask's
/// context mask `m_{t-1}` that chose it, the reward `r_t` received on arriving, and flags;
/// `is_first` marks the start of an episode inside the sequence. With `[agent.dreamer]
/// step_alignment = "paper-code"` the actors store the paper code's rows instead
/// ([`crate::agents::StepAlignment::PaperCode`]): `o_t`, the action `a_t` chosen at it and its
/// mask `m_t`, the reward `r_{t+1}` that followed, the terminal flag on the row before the
/// episode's last observation, which is not stored.
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
    /// `[B, T, 2]`: the context mask `m_{t-1} ∈ [0, 1]²` with which the action `a_{t-1}` was
    /// chosen (cMask), zeros where `has_mask` is 0.
    pub mask: Vec<f32>,
    /// `[B, T]`: 1 where the action before step `t` was chosen through a mask (not at an
    /// episode's first step, nor for random or mask-free actions).
    pub has_mask: Vec<f32>,
}

/// Why a batch does not fit the agent that is to train on it: each names the batch's kind, the
/// sizes or the field at fault, and what was expected.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BatchError {
    /// A transition batch that is empty or of other observation/action sizes.
    #[error(
        "transition batch of {batch} with obs/action sizes {obs_dim}/{act_dim}, expected a \
         non-empty one with {want_obs}/{want_act}"
    )]
    TransitionShape {
        /// Transitions held.
        batch: usize,
        /// Its observation size.
        obs_dim: usize,
        /// Its action size.
        act_dim: usize,
        /// The observation size expected.
        want_obs: usize,
        /// The action size expected.
        want_act: usize,
    },
    /// A sequence batch that is empty or of other observation/action sizes.
    #[error(
        "sequence batch of {batch} x {length} with obs/action sizes {obs_dim}/{act_dim}, \
         expected a non-empty one with {want_obs}/{want_act}"
    )]
    SequenceShape {
        /// Sequences held.
        batch: usize,
        /// Steps per sequence.
        length: usize,
        /// Its observation size.
        obs_dim: usize,
        /// Its action size.
        act_dim: usize,
        /// The observation size expected.
        want_obs: usize,
        /// The action size expected.
        want_act: usize,
    },
    /// A buffer of another length than the batch's sizes give.
    #[error("{kind} batch field {field} holds {got} values, expected {want}")]
    FieldLength {
        /// `transition` or `sequence`.
        kind: &'static str,
        /// The field.
        field: &'static str,
        /// Values it holds.
        got: usize,
        /// Values the sizes give.
        want: usize,
    },
}

/// Checks that every buffer holds `want` values; the error names the field.
fn check_lengths(
    kind: &'static str,
    fields: &[(&'static str, usize, usize)],
) -> Result<(), BatchError> {
    for &(field, got, want) in fields {
        if got != want {
            return Err(BatchError::FieldLength {
                kind,
                field,
                got,
                want,
            });
        }
    }
    Ok(())
}

impl TransitionBatch {
    /// Its arrays in the order of its fields: the order of a batch message's payload.
    pub fn arrays(&self) -> [&[f32]; 6] {
        [
            &self.obs,
            &self.action,
            &self.reward,
            &self.next_obs,
            &self.terminal,
            &self.context,
        ]
    }

    /// Checks that the batch is non-empty, has the sizes `obs_dim`/`act_dim` and that every
    /// buffer's length matches them.
    pub fn validate(&self, obs_dim: usize, act_dim: usize) -> Result<(), BatchError> {
        let b = self.batch;
        if b == 0 || self.obs_dim != obs_dim || self.act_dim != act_dim {
            return Err(BatchError::TransitionShape {
                batch: b,
                obs_dim: self.obs_dim,
                act_dim: self.act_dim,
                want_obs: obs_dim,
                want_act: act_dim,
            });
        }
        check_lengths(
            "transition",
            &[
                ("obs", self.obs.len(), b * obs_dim),
                ("action", self.action.len(), b * act_dim),
                ("reward", self.reward.len(), b),
                ("next_obs", self.next_obs.len(), b * obs_dim),
                ("terminal", self.terminal.len(), b),
                ("context", self.context.len(), b * 2),
            ],
        )
    }
}

impl SequenceBatch {
    /// Its arrays in the order of its fields: the order of a batch message's payload.
    pub fn arrays(&self) -> [&[f32]; 8] {
        [
            &self.obs,
            &self.action,
            &self.reward,
            &self.is_first,
            &self.is_terminal,
            &self.context,
            &self.mask,
            &self.has_mask,
        ]
    }

    /// Checks that the batch is non-empty, has the sizes `obs_dim`/`act_dim` and that every
    /// buffer's length matches them.
    pub fn validate(&self, obs_dim: usize, act_dim: usize) -> Result<(), BatchError> {
        let n = self.batch * self.length;
        if n == 0 || self.obs_dim != obs_dim || self.act_dim != act_dim {
            return Err(BatchError::SequenceShape {
                batch: self.batch,
                length: self.length,
                obs_dim: self.obs_dim,
                act_dim: self.act_dim,
                want_obs: obs_dim,
                want_act: act_dim,
            });
        }
        check_lengths(
            "sequence",
            &[
                ("obs", self.obs.len(), n * obs_dim),
                ("action", self.action.len(), n * act_dim),
                ("reward", self.reward.len(), n),
                ("is_first", self.is_first.len(), n),
                ("is_terminal", self.is_terminal.len(), n),
                ("context", self.context.len(), n * 2),
                ("mask", self.mask.len(), n * 2),
                ("has_mask", self.has_mask.len(), n),
            ],
        )
    }
}

/// What batch to ask for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BatchSpec {
    /// `batch` sequences of `length` steps.
    Sequence {
        /// `B`.
        batch: usize,
        /// `T`.
        length: usize,
    },
    /// `batch` transitions whose observations stack `frames` frames.
    Transition {
        /// `B`.
        batch: usize,
        /// Frames per observation.
        frames: usize,
        /// Steps by which the reward (and terminal flag) lags the action: 0 or 1
        /// ([`crate::SacConfig::reward_delay`]).
        reward_delay: usize,
    },
}

impl BatchSpec {
    /// Steps one batch samples: `B·T` for sequences, `B` for transitions (what the rate
    /// limiter counts).
    pub fn steps(self) -> usize {
        match self {
            BatchSpec::Sequence { batch, length } => batch.saturating_mul(length),
            BatchSpec::Transition { batch, .. } => batch,
        }
    }

    /// Floats of one batch's payload for frames of `obs_dim` and actions of `act_dim`; `None`
    /// if that overflows.
    pub fn floats(self, obs_dim: usize, act_dim: usize) -> Option<usize> {
        match self {
            BatchSpec::Sequence { batch, length } => {
                sequence_floats(batch, length, obs_dim, act_dim)
            }
            BatchSpec::Transition { batch, frames, .. } => {
                transition_floats(batch, frames, obs_dim, act_dim)
            }
        }
    }
}

/// A batch as the learner receives it.
#[derive(Clone, Debug, PartialEq)]
pub enum Batch {
    /// For DreamerV3 and its context variants.
    Sequence(SequenceBatch),
    /// For SAC; `obs_dim` is the stacked size `frames x` frame size.
    Transition(TransitionBatch),
}

/// Floats of a `B x T` sequence batch payload: per step the observation, action, reward,
/// is_first, is_terminal, two context and two mask values, and has_mask; `None` if that
/// overflows (a request no buffer could hold).
pub fn sequence_floats(b: usize, t: usize, obs_dim: usize, act_dim: usize) -> Option<usize> {
    b.checked_mul(t)?
        .checked_mul(obs_dim.checked_add(act_dim)?.checked_add(8)?)
}

/// Floats of a `B`-transition payload with `frames` stacked frames; `None` if that overflows.
pub fn transition_floats(b: usize, frames: usize, obs_dim: usize, act_dim: usize) -> Option<usize> {
    let per = frames
        .checked_mul(obs_dim)?
        .checked_mul(2)?
        .checked_add(act_dim)?
        .checked_add(4)?;
    b.checked_mul(per)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_names_the_wrong_field() {
        let t = TransitionBatch {
            batch: 2,
            obs_dim: 3,
            act_dim: 1,
            obs: vec![0.0; 6],
            action: vec![0.0; 2],
            reward: vec![0.0; 2],
            next_obs: vec![0.0; 5],
            terminal: vec![0.0; 2],
            context: vec![0.0; 4],
        };
        assert!(t
            .validate(3, 1)
            .unwrap_err()
            .to_string()
            .contains("next_obs holds 5 values, expected 6"));
        assert!(t
            .validate(4, 1)
            .unwrap_err()
            .to_string()
            .contains("expected a non-empty one with 4/1"));
        let s = SequenceBatch {
            batch: 1,
            length: 2,
            obs_dim: 1,
            act_dim: 1,
            obs: vec![0.0; 2],
            action: vec![0.0; 2],
            reward: vec![0.0; 2],
            is_first: vec![1.0, 0.0],
            is_terminal: vec![0.0; 2],
            context: vec![0.0; 4],
            mask: vec![0.0; 4],
            has_mask: vec![0.0; 1],
        };
        assert_eq!(
            s.validate(1, 1),
            Err(BatchError::FieldLength {
                kind: "sequence",
                field: "has_mask",
                got: 1,
                want: 2
            })
        );
        assert!(s
            .validate(1, 1)
            .unwrap_err()
            .to_string()
            .contains("has_mask holds 1 values, expected 2"));
        let s = SequenceBatch {
            has_mask: vec![0.0; 2],
            ..s
        };
        assert_eq!(s.validate(1, 1), Ok(()));
        assert!(SequenceBatch::default().validate(0, 0).is_err());
    }
}
