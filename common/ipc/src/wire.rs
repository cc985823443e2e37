//! The shared-memory wire types and their validation.
//!
//! Every type is `#[repr(C)]` with an explicit iceoryx2 type name (the default name holds the
//! module path, which differs between crates; its `_vN` suffix versions the type's own layout)
//! and carries [`FORMAT_VERSION`], which versions everything a message means, payloads included,
//! so a process built from another revision is rejected and counted rather than misread.
//! Payloads that vary in size are `[f32]` or `[u8]` slices sized statically for their maximum.
//!
//! Version history: 1, the first; 2, trajectory steps and sequence batches carry cMask's acting
//! context mask, episode metrics whether the policy drove the whole episode; 3, one trajectory
//! service per actor (a chunk on another actor's is rejected), the replay's status reports its
//! longest loop turn and the count it restored; 4, a weights checksum covers the header's
//! version and length too, and chunks jumping ahead of their stream are rejected
//! (`sequence_jump`); 5, a chunk carries a checksum over its header and payload, telemetry is
//! checked against the run's bounds and history (`backwards`, `implausible`), a batch answer
//! carries a checksum, and the replay answers a request it refuses with the reason.

use ctxrace_config::batch::{sequence_floats, transition_floats};
use iceoryx2::prelude::ZeroCopySend;

/// Version of every wire layout in this module; bump it on any change.
pub const FORMAT_VERSION: u32 = 5;
/// Largest observation (one LiDAR frame) a step may carry: the configuration's bound.
pub use ctxrace_config::MAX_OBS;
/// Largest action a step may carry.
pub const MAX_ACT: usize = 4;
/// Most steps in one trajectory chunk.
pub const MAX_CHUNK: usize = 64;
pub use ctxrace_run::steps::{step_stride, STEP_EXTRA};
/// Flags of a step: is_first, is_terminal, is_last, has_mask.
const STEP_FLAGS: usize = 4;
/// How far ahead of its stream's next expected sequence number a chunk may be: a sender drops
/// chunks only when it closes, and a chunk the replay rejected takes one number, so a real
/// stream never jumps this far; a sequence beyond it is rejected (`sequence_jump`) instead of
/// moving the stream there and making every later chunk `out_of_order`.
pub const SEQUENCE_WINDOW: u64 = 1 << 16;
/// Most batch requests waiting at the replay; more are refused.
pub const MAX_PENDING_REQUESTS: usize = 16;
/// Length of the `[f32]` slice a trajectory publisher preallocates.
pub const MAX_CHUNK_FLOATS: usize = MAX_CHUNK * (MAX_OBS + MAX_ACT + STEP_EXTRA);

/// Header of a trajectory chunk: `steps` consecutive env steps of one actor.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_ChunkHeader_v1")]
#[repr(C)]
pub struct ChunkHeader {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// The sending actor, below the run's actor count.
    pub actor_id: u32,
    /// The episode the chunk's first step belongs to.
    pub episode_id: u64,
    /// Per-actor chunk counter starting at 0; a gap means chunks were dropped.
    pub sequence: u64,
    /// Version of the weights that chose the chunk's actions.
    pub policy_version: u64,
    /// Observation size of every step.
    pub obs_dim: u32,
    /// Action size of every step.
    pub act_dim: u32,
    /// Steps in the chunk, 1 to [`MAX_CHUNK`].
    pub steps: u32,
    /// CRC-32 of the other header fields and the payload ([`chunk_checksum`]).
    pub checksum: u32,
}

impl ChunkHeader {
    /// The header of actor `actor_id`'s chunks of steps of `obs_dim` and `act_dim` values, this
    /// format's version; episode, sequence, policy version and step count still 0.
    pub fn for_actor(actor_id: u32, obs_dim: usize, act_dim: usize) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            actor_id,
            obs_dim: obs_dim as u32,
            act_dim: act_dim as u32,
            ..Self::default()
        }
    }

    /// This header with its checksum set for `payload` ([`chunk_checksum`]).
    pub fn sealed(self, payload: &[f32]) -> Self {
        Self {
            checksum: chunk_checksum(&self, payload),
            ..self
        }
    }
}

/// Header of a weights broadcast; the payload is `len` bytes.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_WeightsHeader_v1")]
#[repr(C)]
pub struct WeightsHeader {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// CRC-32 of the version, the length and the payload ([`weights_checksum`]).
    pub checksum: u32,
    /// Policy version, increasing.
    pub version: u64,
    /// Payload length in bytes.
    pub len: u64,
}

/// What kind of batch the learner asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchKind {
    /// A [`ctxrace_config::SequenceBatch`] of `B x T` steps.
    Sequence,
    /// A [`ctxrace_config::TransitionBatch`] of `B` transitions with stacked frames.
    Transition,
}

impl BatchKind {
    /// The wire code.
    pub fn code(self) -> u32 {
        match self {
            BatchKind::Sequence => 0,
            BatchKind::Transition => 1,
        }
    }

    /// The kind of a wire code, `None` if unknown.
    pub fn from_code(code: u32) -> Option<Self> {
        match code {
            0 => Some(BatchKind::Sequence),
            1 => Some(BatchKind::Transition),
            _ => None,
        }
    }
}

/// A learner's request for one batch.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_BatchRequest_v1")]
#[repr(C)]
pub struct BatchRequest {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// [`BatchKind::code`].
    pub kind: u32,
    /// Echoed in the answer's header.
    pub request_id: u64,
    /// `B`.
    pub batch: u32,
    /// `T` for sequences; for transitions the steps from the action to its reward, `1 +
    /// reward_delay` (1 or 2).
    pub length: u32,
    /// Stacked frames per transition observation; ignored for sequences.
    pub frames: u32,
    /// Explicit padding.
    pub reserved: u32,
}

/// Header of a batch answer; the `[f32]` payload holds the batch's arrays back to back in
/// the order of the fields of [`ctxrace_config::SequenceBatch`] or [`ctxrace_config::TransitionBatch`].
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_BatchHeader_v2")]
#[repr(C)]
pub struct BatchHeader {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// [`BatchKind::code`].
    pub kind: u32,
    /// The request answered.
    pub request_id: u64,
    /// `B`.
    pub batch: u32,
    /// `T` (sequences) or 1 (transitions).
    pub length: u32,
    /// Stacked frames (transitions) or 1 (sequences).
    pub frames: u32,
    /// Single-frame observation size.
    pub obs_dim: u32,
    /// Action size.
    pub act_dim: u32,
    /// 0 for a batch; for a refusal (an empty payload), 1 + the index in [`REASONS`] of why.
    pub refused: u32,
    /// CRC-32 of the other header fields and the payload ([`batch_checksum`]).
    pub checksum: u32,
    /// Explicit padding.
    pub reserved: u32,
}

impl BatchHeader {
    /// This header with its checksum set for the payload `parts` laid back to back
    /// ([`batch_checksum`]).
    pub fn sealed(self, parts: &[&[f32]]) -> Self {
        Self {
            checksum: batch_checksum(&self, parts),
            ..self
        }
    }

    /// Why the replay refused the request, if this answers one with a refusal.
    pub fn refusal(&self) -> Option<&'static str> {
        let code = self.refused.checked_sub(1)? as usize;
        Some(REASONS.get(code).copied().unwrap_or("unknown"))
    }
}

/// The CRC-32 a [`BatchHeader`] carries: over every other header field (little-endian) and
/// the payload `parts` laid back to back.
pub fn batch_checksum(header: &BatchHeader, parts: &[&[f32]]) -> u32 {
    let h = header;
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&h.format_version.to_le_bytes());
    hasher.update(&h.kind.to_le_bytes());
    hasher.update(&h.request_id.to_le_bytes());
    for word in [h.batch, h.length, h.frames, h.obs_dim, h.act_dim, h.refused] {
        hasher.update(&word.to_le_bytes());
    }
    for part in parts {
        hasher.update(float_bytes(part));
    }
    hasher.finalize()
}

/// An actor's report of one finished training episode for the launcher's logs: the simulator's
/// `EpisodeMetrics` in wire form, with the actor, the episode and its context.
#[derive(Debug, Default, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("ctxrace_EpisodeReport_v1")]
#[repr(C)]
pub struct EpisodeReport {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// The actor.
    pub actor_id: u32,
    /// The episode.
    pub episode_id: u64,
    /// The actor's env steps so far, this episode included.
    pub env_steps: u64,
    /// Steps of this episode.
    pub steps: u64,
    /// The episode's context `(c_v, c_θ)`.
    pub context: [f32; 2],
    /// Lap progress reached, in laps.
    pub progress: f32,
    /// OT: overtakes made minus times overtaken.
    pub overtakes: i32,
    /// 1 if the episode ended in a car-to-car collision.
    pub a2a: u32,
    /// 1 if the episode ended in a wall crash.
    pub wall_crash: u32,
    /// Undiscounted return.
    pub episode_return: f32,
    /// 1 if the policy chose every action of the episode (none of the random prefill).
    pub by_policy: u32,
}

/// An actor's periodic sign of life.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_Heartbeat_v1")]
#[repr(C)]
pub struct Heartbeat {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// The actor.
    pub actor_id: u32,
    /// Its process id.
    pub pid: u32,
    /// Explicit padding.
    pub reserved: u32,
    /// Env steps so far.
    pub env_steps: u64,
    /// Weights version in use.
    pub policy_version: u64,
    /// Steps the actor dropped because replay did not take them in time.
    pub dropped_steps: u64,
}

/// The replay process's counters, published about once a second.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_ReplayStatus_v3")]
#[repr(C)]
pub struct ReplayStatus {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// The longest turn of the replay loop so far, in µs (a snapshot's encoding included): the
    /// longest the replay kept a batch or a chunk waiting.
    pub longest_turn_us: u32,
    /// Steps inserted since the run started (snapshots included).
    pub inserted: u64,
    /// Steps sampled (a `B x T` sequence batch counts `B·T`, a transition batch `B`).
    pub sampled: u64,
    /// Steps held now.
    pub fill: u64,
    /// Steps it can hold.
    pub capacity: u64,
    /// Chunks found missing from the actors' sequence numbers (dropped on the way).
    pub dropped_chunks: u64,
    /// Chunks and requests rejected as malformed.
    pub rejected: u64,
    /// Batches sent.
    pub batches: u64,
    /// Requests waiting for the rate limiter.
    pub pending_requests: u64,
    /// Steps inserted when the last batch was sampled (the learner's train ratio is
    /// `sampled / (this − min_fill)`; steps drained at shutdown come after it).
    pub inserted_at_last_batch: u64,
    /// The inserted-steps count this replay restored from its snapshot when it started (0 on a
    /// fresh start): `inserted` continues from it.
    pub restored_inserts: u64,
    /// `rejected` by reason, indexed like [`REASONS`].
    pub rejected_by_reason: [u64; REASONS.len()],
}

/// Why a message was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WireError {
    /// Another [`FORMAT_VERSION`].
    #[error("format version {got}, expected {FORMAT_VERSION}")]
    Version {
        /// The version received.
        got: u32,
    },
    /// An actor id outside the run.
    #[error("actor id {got} is not below the run's {actors} actors")]
    UnknownActor {
        /// The id received.
        got: u32,
        /// Actors in the run.
        actors: usize,
    },
    /// A chunk on another actor's trajectory service than its own.
    #[error("chunk of actor {got} on the trajectory service of actor {stream}")]
    WrongStream {
        /// The id in the header.
        got: u32,
        /// The actor whose service carried it.
        stream: u32,
    },
    /// Dimensions that do not match the run's or the payload's.
    #[error("bad dimensions: {0}")]
    Dims(String),
    /// A NaN or infinite value, or a flag other than 0 or 1.
    #[error("bad value at float {index}: {value}")]
    Value {
        /// Index in the payload.
        index: usize,
        /// The value.
        value: f32,
    },
    /// A payload whose checksum does not match its header.
    #[error("checksum {got:#010x}, header says {expected:#010x}")]
    Checksum {
        /// Computed.
        got: u32,
        /// From the header.
        expected: u32,
    },
    /// An unknown batch kind code.
    #[error("unknown batch kind {0}")]
    Kind(u32),
    /// A chunk whose sequence number goes back within its actor's stream (a duplicate or a
    /// replay); 0 is always taken, as a restarted actor's first chunk.
    #[error("chunk sequence {got} goes back: actor's stream expects {expected} or more")]
    OutOfOrder {
        /// The sequence number received.
        got: u64,
        /// The next one expected.
        expected: u64,
    },
    /// A chunk whose sequence number is further ahead of its actor's stream than
    /// [`SEQUENCE_WINDOW`]: a value no sender writes.
    #[error(
        "chunk sequence {got} jumps ahead: actor's stream expects {expected} to {} (a window of \
         {SEQUENCE_WINDOW})",
        expected.saturating_add(SEQUENCE_WINDOW - 1)
    )]
    SequenceJump {
        /// The sequence number received.
        got: u64,
        /// The next one expected.
        expected: u64,
    },
    /// A batch request larger than the rate limiter could ever serve.
    #[error("a request for {steps} steps exceeds the rate limiter's window")]
    Unservable {
        /// Steps asked for.
        steps: u64,
    },
    /// A counter of a process that went back within the process's start.
    #[error("{what} {got} goes back: it was {last}")]
    Backwards {
        /// The counter.
        what: &'static str,
        /// The value received.
        got: u64,
        /// The last value accepted.
        last: u64,
    },
    /// A value no process of the run can have sent: beyond the run's bounds (a counter growing
    /// faster than possible, a value out of its physical range, a version ahead of the learner).
    #[error("implausible: {0}")]
    Implausible(String),
    /// A sample whose memory this process cannot read: its publisher's corrupted allocator
    /// placed it outside the segment (see the `shared` module).
    #[error("unreadable sample: {0}")]
    Unreadable(String),
}

/// The reasons a message is rejected for, in the order of the counters that
/// [`WireError::reason`] indexes ([`ReplayStatus::rejected_by_reason`]).
pub const REASONS: [&str; 13] = [
    "version",
    "unknown_actor",
    "wrong_stream",
    "out_of_order",
    "dims",
    "value",
    "checksum",
    "kind",
    "unservable",
    "sequence_jump",
    "backwards",
    "implausible",
    "unreadable",
];

/// The nonzero counters of a by-reason array ([`REASONS`]), by name.
pub fn named_reasons(
    by_reason: &[u64; REASONS.len()],
) -> std::collections::BTreeMap<&'static str, u64> {
    REASONS
        .iter()
        .zip(by_reason)
        .filter(|(_, &n)| n > 0)
        .map(|(&name, &n)| (name, n))
        .collect()
}

impl WireError {
    /// The index of this error's reason in [`REASONS`].
    pub fn reason(&self) -> usize {
        match self {
            WireError::Version { .. } => 0,
            WireError::UnknownActor { .. } => 1,
            WireError::WrongStream { .. } => 2,
            WireError::OutOfOrder { .. } => 3,
            WireError::Dims(_) => 4,
            WireError::Value { .. } => 5,
            WireError::Checksum { .. } => 6,
            WireError::Kind(_) => 7,
            WireError::Unservable { .. } => 8,
            WireError::SequenceJump { .. } => 9,
            WireError::Backwards { .. } => 10,
            WireError::Implausible(_) => 11,
            WireError::Unreadable(_) => 12,
        }
    }
}

/// The bytes of `values` (native order: every process of a run runs on one machine).
pub(crate) fn float_bytes(values: &[f32]) -> &[u8] {
    // SAFETY: an f32 has no padding and every bit pattern is a valid u8; u8 needs no alignment;
    // the slice covers exactly the floats' memory, borrowed as long as `values`.
    unsafe {
        std::slice::from_raw_parts(values.as_ptr().cast::<u8>(), std::mem::size_of_val(values))
    }
}

/// The CRC-32 a [`ChunkHeader`] carries: over every other header field (little-endian) and the
/// payload, so that a header or payload changed in shared memory fails it.
pub fn chunk_checksum(header: &ChunkHeader, payload: &[f32]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    for word in [header.format_version, header.actor_id] {
        hasher.update(&word.to_le_bytes());
    }
    for word in [header.episode_id, header.sequence, header.policy_version] {
        hasher.update(&word.to_le_bytes());
    }
    for word in [header.obs_dim, header.act_dim, header.steps] {
        hasher.update(&word.to_le_bytes());
    }
    hasher.update(float_bytes(payload));
    hasher.finalize()
}

/// Checks a trajectory chunk against the run's actor count and dimensions: version, checksum,
/// actor id, dims, payload length, finite values, 0/1 flags and masks in `[0, 1]`.
pub fn validate_chunk(
    header: &ChunkHeader,
    payload: &[f32],
    actors: usize,
    obs_dim: usize,
    act_dim: usize,
) -> Result<(), WireError> {
    if header.format_version != FORMAT_VERSION {
        return Err(WireError::Version {
            got: header.format_version,
        });
    }
    let got = chunk_checksum(header, payload);
    if got != header.checksum {
        return Err(WireError::Checksum {
            got,
            expected: header.checksum,
        });
    }
    if header.actor_id as usize >= actors {
        return Err(WireError::UnknownActor {
            got: header.actor_id,
            actors,
        });
    }
    if header.obs_dim as usize != obs_dim || header.act_dim as usize != act_dim {
        return Err(WireError::Dims(format!(
            "obs_dim {} act_dim {}, run has {obs_dim} and {act_dim}",
            header.obs_dim, header.act_dim
        )));
    }
    let steps = header.steps as usize;
    let stride = step_stride(obs_dim, act_dim);
    if steps == 0 || steps > MAX_CHUNK || payload.len() != steps * stride {
        return Err(WireError::Dims(format!(
            "{steps} steps in {} floats (stride {stride}, at most {MAX_CHUNK} steps)",
            payload.len()
        )));
    }
    check_finite(payload)?;
    for s in 0..steps {
        let flags = s * stride + obs_dim + act_dim + 1;
        let mask = flags + STEP_FLAGS + 2;
        let bad_flag =
            (flags..flags + STEP_FLAGS).find(|&i| payload[i] != 0.0 && payload[i] != 1.0);
        let bad_mask = (mask..mask + 2).find(|&i| !(0.0..=1.0).contains(&payload[i]));
        if let Some(index) = bad_flag.or(bad_mask) {
            return Err(WireError::Value {
                index,
                value: payload[index],
            });
        }
    }
    Ok(())
}

/// Checks that every value is finite.
pub fn check_finite(values: &[f32]) -> Result<(), WireError> {
    // A branch-free pass first: this runs on every received float.
    if values.iter().all(|v| v.is_finite()) {
        return Ok(());
    }
    let index = values.iter().position(|v| !v.is_finite()).unwrap_or(0);
    Err(WireError::Value {
        index,
        value: values[index],
    })
}

/// Where a chunk of sequence number `got` stands in a stream that expects `expected` next
/// (`None`: no chunk of it seen yet): 0 always starts the stream again (a restarted actor's
/// first chunk); otherwise it must not go back, nor jump further ahead than
/// [`SEQUENCE_WINDOW`].
pub fn check_sequence(got: u64, expected: Option<u64>) -> Result<(), WireError> {
    match expected {
        Some(_) if got == 0 => Ok(()),
        Some(next) if got < next => Err(WireError::OutOfOrder {
            got,
            expected: next,
        }),
        Some(next) if got - next >= SEQUENCE_WINDOW => Err(WireError::SequenceJump {
            got,
            expected: next,
        }),
        _ => Ok(()),
    }
}

/// The CRC-32 a [`WeightsHeader`] carries, as a hasher to feed the payload to: it starts with
/// the header's `version` and `len` (little-endian), so a header rewritten in shared memory
/// fails the checksum like a payload does.
pub fn weights_hasher(version: u64, len: u64) -> crc32fast::Hasher {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&version.to_le_bytes());
    hasher.update(&len.to_le_bytes());
    hasher
}

/// The checksum of weights `payload` published as `version` ([`weights_hasher`]).
pub fn weights_checksum(version: u64, payload: &[u8]) -> u32 {
    let mut hasher = weights_hasher(version, payload.len() as u64);
    hasher.update(payload);
    hasher.finalize()
}

/// Checks a weights broadcast: version, length and checksum (over version, length and payload).
pub fn validate_weights(header: &WeightsHeader, payload: &[u8]) -> Result<(), WireError> {
    check_weights(
        header,
        payload.len(),
        weights_checksum(header.version, payload),
    )
}

/// [`validate_weights`] of a payload of `len` bytes whose checksum, `got`, was computed while
/// it was copied ([`weights_hasher`] over `header.version` and `len`).
pub fn check_weights(header: &WeightsHeader, len: usize, got: u32) -> Result<(), WireError> {
    if header.format_version != FORMAT_VERSION {
        return Err(WireError::Version {
            got: header.format_version,
        });
    }
    if header.len != len as u64 {
        return Err(WireError::Dims(format!(
            "header says {} bytes, payload has {len}",
            header.len
        )));
    }
    if got != header.checksum {
        return Err(WireError::Checksum {
            got,
            expected: header.checksum,
        });
    }
    Ok(())
}

/// Checks a batch request: version, kind and sizes (the batch must fit in `max_floats`).
pub fn validate_request(
    request: &BatchRequest,
    obs_dim: usize,
    act_dim: usize,
    max_floats: usize,
) -> Result<BatchKind, WireError> {
    if request.format_version != FORMAT_VERSION {
        return Err(WireError::Version {
            got: request.format_version,
        });
    }
    let kind = BatchKind::from_code(request.kind).ok_or(WireError::Kind(request.kind))?;
    let (b, t, f) = (
        request.batch as usize,
        request.length as usize,
        request.frames as usize,
    );
    let floats = match kind {
        BatchKind::Sequence => (b > 0 && t > 0).then(|| sequence_floats(b, t, obs_dim, act_dim)),
        BatchKind::Transition => (b > 0 && f > 0 && (1..=2).contains(&t))
            .then(|| transition_floats(b, f, obs_dim, act_dim)),
    };
    match floats {
        Some(Some(n)) if n <= max_floats => Ok(kind),
        _ => Err(WireError::Dims(format!(
            "batch {b} length {t} frames {f} is empty, exceeds {max_floats} floats, or asks \
             transitions whose reward lags by more than one step (length above 2)"
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(steps: usize) -> (ChunkHeader, Vec<f32>) {
        let h = ChunkHeader {
            format_version: FORMAT_VERSION,
            actor_id: 1,
            steps: steps as u32,
            obs_dim: 3,
            act_dim: 2,
            ..Default::default()
        };
        (h, vec![0.5; steps * step_stride(3, 2)])
    }

    #[test]
    fn chunk_validation_rejects_bad_version_dims_values_and_actor() {
        let (h, mut p) = chunk(4);
        let stride = step_stride(3, 2);
        for s in 0..4 {
            p[s * stride + 6..s * stride + 10].fill(0.0);
        }
        assert_eq!(validate_chunk(&h.sealed(&p), &p, 2, 3, 2), Ok(()));
        let bad = ChunkHeader {
            format_version: 99,
            ..h
        };
        assert!(matches!(
            validate_chunk(&bad.sealed(&p), &p, 2, 3, 2),
            Err(WireError::Version { got: 99 })
        ));
        assert!(matches!(
            validate_chunk(&h.sealed(&p), &p, 1, 3, 2),
            Err(WireError::UnknownActor { .. })
        ));
        assert!(matches!(
            validate_chunk(&h.sealed(&p), &p, 2, 4, 2),
            Err(WireError::Dims(_))
        ));
        assert!(matches!(
            validate_chunk(&h.sealed(&p[1..]), &p[1..], 2, 3, 2),
            Err(WireError::Dims(_))
        ));
        let mut nan = p.clone();
        nan[2] = f32::NAN;
        assert!(matches!(
            validate_chunk(&h.sealed(&nan), &nan, 2, 3, 2),
            Err(WireError::Value { index: 2, .. })
        ));
        let mut inf = p.clone();
        inf[stride] = f32::INFINITY;
        assert!(validate_chunk(&h.sealed(&inf), &inf, 2, 3, 2).is_err());
        let mut flag = p.clone();
        flag[6] = 0.5;
        assert!(matches!(
            validate_chunk(&h.sealed(&flag), &flag, 2, 3, 2),
            Err(WireError::Value { index: 6, .. })
        ));
        let mut mask = p.clone();
        mask[stride + 13] = 1.5;
        assert!(matches!(
            validate_chunk(&h.sealed(&mask), &mask, 2, 3, 2),
            Err(WireError::Value { index, .. }) if index == stride + 13
        ));
        let empty = ChunkHeader { steps: 0, ..h };
        assert!(validate_chunk(&empty.sealed(&[]), &[], 2, 3, 2).is_err());
        // a header or a payload changed after sealing fails the checksum
        let sealed = h.sealed(&p);
        let moved = ChunkHeader {
            sequence: 1 << 63,
            ..sealed
        };
        let mut flipped = p.clone();
        flipped[0] = f32::from_bits(flipped[0].to_bits() ^ 1);
        for (header, payload) in [(moved, &p), (sealed, &flipped)] {
            let e = validate_chunk(&header, payload, 2, 3, 2).unwrap_err();
            assert_eq!(REASONS[e.reason()], "checksum", "{e}");
        }
    }

    #[test]
    fn sequences_within_the_window_are_taken_and_jumps_rejected() {
        assert_eq!(check_sequence(1 << 63, None), Ok(()));
        assert_eq!(check_sequence(5, Some(5)), Ok(()));
        assert_eq!(check_sequence(0, Some(5)), Ok(()));
        assert_eq!(check_sequence(5 + SEQUENCE_WINDOW - 1, Some(5)), Ok(()));
        let jump = check_sequence(5 + SEQUENCE_WINDOW, Some(5)).unwrap_err();
        assert_eq!(REASONS[jump.reason()], "sequence_jump");
        for got in [1 << 63, u64::MAX] {
            assert!(matches!(
                check_sequence(got, Some(7)),
                Err(WireError::SequenceJump { .. })
            ));
        }
        assert!(matches!(
            check_sequence(4, Some(5)),
            Err(WireError::OutOfOrder { .. })
        ));
    }

    #[test]
    fn weights_and_request_validation() {
        let bytes = b"some weights".to_vec();
        let h = WeightsHeader {
            format_version: FORMAT_VERSION,
            checksum: weights_checksum(3, &bytes),
            version: 3,
            len: bytes.len() as u64,
        };
        assert_eq!(validate_weights(&h, &bytes), Ok(()));
        let mut flipped = bytes.clone();
        flipped[0] ^= 1;
        assert!(matches!(
            validate_weights(&h, &flipped),
            Err(WireError::Checksum { .. })
        ));
        assert!(validate_weights(&h, &bytes[1..]).is_err());
        // the header is covered too: a version rewritten to the largest one is refused
        let absurd = WeightsHeader {
            version: u64::MAX,
            ..h
        };
        assert!(matches!(
            validate_weights(&absurd, &bytes),
            Err(WireError::Checksum { .. })
        ));
        // a batch answer's checksum covers its header, its refusal code and every float
        let answer = BatchHeader {
            format_version: FORMAT_VERSION,
            request_id: 4,
            batch: 1,
            ..Default::default()
        };
        let (obs, reward) = ([0.25f32, 0.5], [1.0f32]);
        let sealed = answer.sealed(&[&obs, &reward]);
        assert_eq!(batch_checksum(&sealed, &[&obs, &reward]), sealed.checksum);
        let flipped = [f32::from_bits(0.25f32.to_bits() ^ 1), 0.5];
        assert_ne!(
            batch_checksum(&sealed, &[&flipped, &reward]),
            sealed.checksum
        );
        let refusal = BatchHeader {
            refused: 1 + 8,
            ..sealed
        };
        assert_ne!(batch_checksum(&refusal, &[&obs, &reward]), sealed.checksum);
        assert_eq!(refusal.refusal(), Some("unservable"));
        assert_eq!(sealed.refusal(), None);
        let r = BatchRequest {
            format_version: FORMAT_VERSION,
            kind: 0,
            batch: 2,
            length: 4,
            ..Default::default()
        };
        assert_eq!(validate_request(&r, 3, 2, 1000), Ok(BatchKind::Sequence));
        assert!(validate_request(&r, 3, 2, 10).is_err());
        assert!(validate_request(&BatchRequest { kind: 7, ..r }, 3, 2, 1000).is_err());
        assert!(validate_request(&BatchRequest { batch: 0, ..r }, 3, 2, 1000).is_err());
        // sizes whose product overflows are rejected, not wrapped into a small number
        let huge = BatchRequest {
            batch: u32::MAX,
            length: u32::MAX,
            ..r
        };
        assert!(validate_request(&huge, usize::MAX / 4, 2, usize::MAX).is_err());
        // a transition request's length is 1 + its reward delay: 1 or 2
        let transitions = |length| BatchRequest {
            kind: BatchKind::Transition.code(),
            frames: 2,
            length,
            ..r
        };
        for (length, ok) in [(0, false), (1, true), (2, true), (3, false)] {
            let got = validate_request(&transitions(length), 3, 2, 1000);
            assert_eq!(got.is_ok(), ok, "length {length}: {got:?}");
        }
        assert_eq!(sequence_floats(usize::MAX, 2, 1, 1), None);
        assert_eq!(transition_floats(2, usize::MAX, 1, 1), None);
    }
}
