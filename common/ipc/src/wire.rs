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
//! carries a checksum, and the replay answers a request it refuses with the reason; 6, every
//! message carries a [`Tag`] keyed with the run's key beside its CRC-32 (`unauthenticated`),
//! chunks and batch requests the [`new_epoch`] of their sender (a stream goes on only in its
//! sender's epoch or a later one: `sequence_jump` is gone), episode reports and replay statuses
//! their process id.
//!
//! # Seals
//! Every message carries two seals over every other field (little-endian) and its payload,
//! computed in one pass ([`Sealer`]): a CRC-32 (`checksum`), which tells an accident (a torn
//! write, a flipped bit) from a forgery, and a 32-byte BLAKE3 tag keyed with the run's key
//! ([`RunKey`]), whose input starts with the message kind's name ([`Sealed::KIND`]), so that
//! only a process holding the key can make a message a reader accepts. A reader checks the
//! version, then the checksum (`checksum`), then the tag (`unauthenticated`), then the rest.

use crate::key::RunKey;
use ctxrace_config::batch::{sequence_floats, transition_floats};
use iceoryx2::prelude::ZeroCopySend;

/// Version of every wire layout in this module; bump it on any change.
pub const FORMAT_VERSION: u32 = 6;
/// Largest observation (one LiDAR frame) a step may carry: the configuration's bound.
pub use ctxrace_config::MAX_OBS;
/// Largest action a step may carry.
pub const MAX_ACT: usize = 4;
/// Most steps in one trajectory chunk.
pub const MAX_CHUNK: usize = 64;
pub use ctxrace_run::steps::{step_stride, STEP_EXTRA};
/// Flags of a step: is_first, is_terminal, is_last, has_mask.
const STEP_FLAGS: usize = 4;
/// Most batch requests waiting at the replay; more are refused.
pub const MAX_PENDING_REQUESTS: usize = 16;
/// Length of the `[f32]` slice a trajectory publisher preallocates.
pub const MAX_CHUNK_FLOATS: usize = MAX_CHUNK * (MAX_OBS + MAX_ACT + STEP_EXTRA);

/// A message's authentication tag: keyed BLAKE3 under the run's key ([`Sealer`]). (Its length
/// is written out: rustc 1.95 fails on closures building wire structs whose array length is a
/// named constant, "broken MIR ... UnevaluatedConst".)
pub type Tag = [u8; 32];
/// Bytes of a message's [`Tag`].
pub const TAG_LEN: usize = std::mem::size_of::<Tag>();

/// The [`Seal`] of a message, computed in one pass over its bytes: its CRC-32 and its tag
/// under the run's key.
pub struct Sealer {
    crc: crc32fast::Hasher,
    mac: blake3::Hasher,
}

impl Sealer {
    /// A sealer of messages of kind `kind` ([`Sealed::KIND`]) under `key`: the tag's input
    /// starts with the kind's name, so that no message's tag is valid for a message of another
    /// kind.
    pub fn new(key: &RunKey, kind: &str) -> Self {
        let mut mac = blake3::Hasher::new_keyed(key.bytes());
        mac.update(kind.as_bytes());
        mac.update(&[0]);
        Self {
            crc: crc32fast::Hasher::new(),
            mac,
        }
    }

    /// Feeds `bytes` to both seals.
    pub fn update(&mut self, bytes: &[u8]) {
        self.crc.update(bytes);
        self.mac.update(bytes);
    }

    /// Feeds `words`, each little-endian.
    pub fn words32(&mut self, words: &[u32]) {
        for word in words {
            self.update(&word.to_le_bytes());
        }
    }

    /// Feeds `words`, each little-endian.
    pub fn words64(&mut self, words: &[u64]) {
        for word in words {
            self.update(&word.to_le_bytes());
        }
    }

    /// Feeds `values`, each one's bits little-endian.
    pub fn floats(&mut self, values: &[f32]) {
        for value in values {
            self.update(&value.to_bits().to_le_bytes());
        }
    }

    /// The seals of what was fed.
    pub fn finish(self) -> Seal {
        Seal {
            checksum: self.crc.finalize(),
            tag: self.mac.finalize(),
        }
    }
}

/// The checksum and the tag computed over a message ([`Sealer`]).
#[derive(Clone, Copy, Debug)]
pub struct Seal {
    /// The CRC-32.
    pub checksum: u32,
    tag: blake3::Hash,
}

impl Seal {
    /// The tag's bytes.
    pub fn tag(&self) -> Tag {
        *self.tag.as_bytes()
    }

    /// Checks a message's `checksum` and `tag` against this seal: a checksum that differs is
    /// an accident ([`WireError::Checksum`]); a matching checksum with a tag that differs (in
    /// constant time) a message that no holder of the run's key made
    /// ([`WireError::Unauthenticated`]).
    pub fn verify(&self, checksum: u32, tag: &Tag) -> Result<(), WireError> {
        if checksum != self.checksum {
            return Err(WireError::Checksum {
                got: self.checksum,
                expected: checksum,
            });
        }
        if blake3::Hash::from_bytes(*tag) != self.tag {
            return Err(WireError::Unauthenticated);
        }
        Ok(())
    }
}

/// A wire message that carries a checksum and a tag over its other fields and its payload.
pub trait Sealed: Copy {
    /// The message kind's name, the first input of its tag.
    const KIND: &'static str;

    /// Feeds every field but the checksum and the tag, in declaration order.
    fn feed(&self, sealer: &mut Sealer);

    /// Its checksum and its tag.
    fn seal_fields(&self) -> (u32, &Tag);

    /// This message carrying `seal`.
    fn with_seal(self, seal: Seal) -> Self;

    /// A sealer under `key` fed this message's fields: its payload comes next.
    fn sealer(&self, key: &RunKey) -> Sealer {
        let mut sealer = Sealer::new(key, Self::KIND);
        self.feed(&mut sealer);
        sealer
    }

    /// This message sealed under `key` with `payload`, its parts back to back.
    fn seal_with(self, key: &RunKey, payload: &[&[u8]]) -> Self {
        let mut sealer = self.sealer(key);
        for part in payload {
            sealer.update(part);
        }
        self.with_seal(sealer.finish())
    }

    /// Checks its checksum and tag against `seal`, computed over it and its payload
    /// ([`Seal::verify`]).
    fn check_seal(&self, seal: Seal) -> Result<(), WireError> {
        let (checksum, tag) = self.seal_fields();
        seal.verify(checksum, tag)
    }

    /// Checks its checksum and tag for `payload`, its parts back to back, under `key`.
    fn check_with(&self, key: &RunKey, payload: &[&[u8]]) -> Result<(), WireError> {
        let mut sealer = self.sealer(key);
        for part in payload {
            sealer.update(part);
        }
        self.check_seal(sealer.finish())
    }
}

/// A fresh epoch for a sender made now: `CLOCK_MONOTONIC` in nanoseconds, one clock for every
/// process of the machine (a run's processes share one machine), so that a sender made later, a
/// restarted actor's or learner's, has a larger epoch. A reader's stream goes on only in the
/// epoch of its last accepted message or a later one ([`check_sequence`]).
pub fn new_epoch() -> u64 {
    let mut now = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes only into `now`, a valid timespec; CLOCK_MONOTONIC exists on
    // every Linux, so it cannot fail.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut now) };
    (now.tv_sec as u64)
        .saturating_mul(1_000_000_000)
        .saturating_add(now.tv_nsec as u64)
}

/// Implements [`Sealed`] for a message whose `checksum` and `tag` fields are its seal, with
/// `feed` feeding its other fields (`|message, sealer| { ... }`).
macro_rules! sealed {
    ($t:ty, $kind:literal, |$m:ident, $s:ident| $feed:block) => {
        impl Sealed for $t {
            const KIND: &'static str = $kind;

            fn feed(&self, $s: &mut Sealer) {
                let $m = self;
                $feed
            }

            fn seal_fields(&self) -> (u32, &Tag) {
                (self.checksum, &self.tag)
            }

            fn with_seal(self, seal: Seal) -> Self {
                Self {
                    checksum: seal.checksum,
                    tag: seal.tag(),
                    ..self
                }
            }
        }
    };
}

/// Header of a trajectory chunk: `steps` consecutive env steps of one actor.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_ChunkHeader_v2")]
#[repr(C)]
pub struct ChunkHeader {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// The sending actor, below the run's actor count.
    pub actor_id: u32,
    /// The episode the chunk's first step belongs to.
    pub episode_id: u64,
    /// Per-sender chunk counter starting at 0; a gap means chunks were dropped.
    pub sequence: u64,
    /// Version of the weights that chose the chunk's actions.
    pub policy_version: u64,
    /// Observation size of every step.
    pub obs_dim: u32,
    /// Action size of every step.
    pub act_dim: u32,
    /// Steps in the chunk, 1 to [`MAX_CHUNK`].
    pub steps: u32,
    /// CRC-32 of the other fields (the tag aside) and the payload ([`Sealer`]).
    pub checksum: u32,
    /// The sender's [`new_epoch`]: a restarted actor's chunks start a new stream.
    pub epoch: u64,
    /// Tag of the other fields (the checksum aside) and the payload ([`Sealer`]).
    pub tag: Tag,
}

sealed!(ChunkHeader, "ctxrace chunk", |h, s| {
    s.words32(&[h.format_version, h.actor_id]);
    s.words64(&[h.episode_id, h.sequence, h.policy_version]);
    s.words32(&[h.obs_dim, h.act_dim, h.steps]);
    s.words64(&[h.epoch]);
});

impl ChunkHeader {
    /// The header of actor `actor_id`'s chunks of steps of `obs_dim` and `act_dim` values, this
    /// format's version; episode, sequence, policy version, step count and epoch still 0.
    pub fn for_actor(actor_id: u32, obs_dim: usize, act_dim: usize) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            actor_id,
            obs_dim: obs_dim as u32,
            act_dim: act_dim as u32,
            ..Self::default()
        }
    }

    /// This header sealed under `key` for `payload`.
    pub fn sealed(self, key: &RunKey, payload: &[f32]) -> Self {
        self.seal_with(key, &[float_bytes(payload)])
    }
}

/// Header of a weights broadcast; the payload is `len` bytes.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_WeightsHeader_v2")]
#[repr(C)]
pub struct WeightsHeader {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// CRC-32 of the version, the length and the payload ([`Sealer`]).
    pub checksum: u32,
    /// Policy version, increasing.
    pub version: u64,
    /// Payload length in bytes.
    pub len: u64,
    /// Tag of the version, the length and the payload ([`Sealer`]).
    pub tag: Tag,
}

sealed!(WeightsHeader, "ctxrace weights", |h, s| {
    s.words32(&[h.format_version]);
    s.words64(&[h.version, h.len]);
});

impl WeightsHeader {
    /// The header of weights `version` of `len` bytes, this format's version, not sealed yet.
    pub fn new(version: u64, len: usize) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            version,
            len: len as u64,
            ..Self::default()
        }
    }
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
#[type_name("ctxrace_BatchRequest_v2")]
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
    /// CRC-32 of the other fields (the tag aside) ([`Sealer`]).
    pub checksum: u32,
    /// The requesting client's [`new_epoch`], echoed in the answer's header: a restarted
    /// learner takes no answer to its predecessor's requests.
    pub client: u64,
    /// Tag of the other fields (the checksum aside) ([`Sealer`]).
    pub tag: Tag,
}

sealed!(BatchRequest, "ctxrace batch request", |r, s| {
    s.words32(&[r.format_version, r.kind]);
    s.words64(&[r.request_id]);
    s.words32(&[r.batch, r.length, r.frames]);
    s.words64(&[r.client]);
});

/// Header of a batch answer; the `[f32]` payload holds the batch's arrays back to back in
/// the order of the fields of [`ctxrace_config::SequenceBatch`] or [`ctxrace_config::TransitionBatch`].
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_BatchHeader_v3")]
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
    /// CRC-32 of the other fields (the tag aside) and the payload ([`Sealer`]).
    pub checksum: u32,
    /// Explicit padding.
    pub reserved: u32,
    /// The epoch of the client whose request this answers ([`BatchRequest::client`]).
    pub client: u64,
    /// Tag of the other fields (the checksum aside) and the payload ([`Sealer`]).
    pub tag: Tag,
}

sealed!(BatchHeader, "ctxrace batch", |h, s| {
    s.words32(&[h.format_version, h.kind]);
    s.words64(&[h.request_id]);
    s.words32(&[
        h.batch, h.length, h.frames, h.obs_dim, h.act_dim, h.refused, h.reserved,
    ]);
    s.words64(&[h.client]);
});

impl BatchHeader {
    /// The header of an answer to `request`, this format's version; the batch's sizes still 0.
    pub fn answering(request: &BatchRequest) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            request_id: request.request_id,
            client: request.client,
            ..Self::default()
        }
    }

    /// This header sealed under `key` for the payload `parts` laid back to back.
    pub fn sealed(self, key: &RunKey, parts: &[&[f32]]) -> Self {
        let parts: Vec<&[u8]> = parts.iter().map(|p| float_bytes(p)).collect();
        self.seal_with(key, &parts)
    }

    /// Why the replay refused the request, if this answers one with a refusal.
    pub fn refusal(&self) -> Option<&'static str> {
        let code = self.refused.checked_sub(1)? as usize;
        Some(REASONS.get(code).copied().unwrap_or("unknown"))
    }
}

/// An actor's report of one finished training episode for the launcher's logs: the simulator's
/// `EpisodeMetrics` in wire form, with the actor, the episode and its context.
#[derive(Debug, Default, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("ctxrace_EpisodeReport_v2")]
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
    /// The actor's process id: the launcher takes reports of the actor's current process only.
    pub pid: u32,
    /// CRC-32 of the other fields (the tag aside) ([`Sealer`]).
    pub checksum: u32,
    /// Tag of the other fields (the checksum aside) ([`Sealer`]).
    pub tag: Tag,
}

sealed!(EpisodeReport, "ctxrace episode", |m, s| {
    s.words32(&[m.format_version, m.actor_id]);
    s.words64(&[m.episode_id, m.env_steps, m.steps]);
    s.floats(&[m.context[0], m.context[1], m.progress]);
    s.words32(&[m.overtakes as u32, m.a2a, m.wall_crash]);
    s.floats(&[m.episode_return]);
    s.words32(&[m.by_policy, m.pid]);
});

/// An actor's periodic sign of life.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_Heartbeat_v2")]
#[repr(C)]
pub struct Heartbeat {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// The actor.
    pub actor_id: u32,
    /// Its process id.
    pub pid: u32,
    /// CRC-32 of the other fields (the tag aside) ([`Sealer`]).
    pub checksum: u32,
    /// Env steps so far.
    pub env_steps: u64,
    /// Weights version in use.
    pub policy_version: u64,
    /// Steps the actor dropped because replay did not take them in time.
    pub dropped_steps: u64,
    /// Tag of the other fields (the checksum aside) ([`Sealer`]).
    pub tag: Tag,
}

sealed!(Heartbeat, "ctxrace heartbeat", |b, s| {
    s.words32(&[b.format_version, b.actor_id, b.pid]);
    s.words64(&[b.env_steps, b.policy_version, b.dropped_steps]);
});

/// The replay process's counters, published about once a second.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ctxrace_ReplayStatus_v4")]
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
    /// The replay's process id: the launcher takes statuses of the replay's current process
    /// only.
    pub pid: u32,
    /// CRC-32 of the other fields (the tag aside) ([`Sealer`]).
    pub checksum: u32,
    /// Tag of the other fields (the checksum aside) ([`Sealer`]).
    pub tag: Tag,
}

sealed!(ReplayStatus, "ctxrace replay status", |r, s| {
    s.words32(&[r.format_version, r.longest_turn_us]);
    s.words64(&[r.inserted, r.sampled, r.fill, r.capacity, r.dropped_chunks]);
    s.words64(&[r.rejected, r.batches, r.pending_requests]);
    s.words64(&[r.inserted_at_last_batch, r.restored_inserts]);
    s.words64(&r.rejected_by_reason);
    s.words32(&[r.pid]);
});

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
    /// A chunk whose place, its sender's epoch and its sequence number, goes back within its
    /// actor's stream: a duplicate, a replayed copy of an earlier chunk, or a chunk of an
    /// earlier sender than the stream's.
    #[error(
        "chunk (epoch {}, sequence {}) goes back: actor's stream expects epoch {} from sequence \
         {} on, or a later epoch",
        got.0, got.1, expected.0, expected.1
    )]
    OutOfOrder {
        /// The epoch and sequence number received.
        got: (u64, u64),
        /// The next place expected.
        expected: (u64, u64),
    },
    /// A message whose checksum matches but whose tag is not the run key's: made by a process
    /// that does not hold the run's key.
    #[error("unauthenticated: a valid checksum, but a tag not made with the run's key")]
    Unauthenticated,
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
    "unauthenticated",
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
            WireError::Unauthenticated => 9,
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

/// Checks a message's format version, then its checksum and tag under `key` for `payload`
/// ([`Sealed::check_with`]).
pub fn check_sealed<T: Sealed>(
    message: &T,
    format_version: u32,
    key: &RunKey,
    payload: &[&[u8]],
) -> Result<(), WireError> {
    if format_version != FORMAT_VERSION {
        return Err(WireError::Version {
            got: format_version,
        });
    }
    message.check_with(key, payload)
}

/// Checks a trajectory chunk against the run's key, actor count and dimensions: version,
/// checksum, tag, actor id, dims, payload length, finite values, 0/1 flags and masks in
/// `[0, 1]`.
pub fn validate_chunk(
    header: &ChunkHeader,
    payload: &[f32],
    key: &RunKey,
    actors: usize,
    obs_dim: usize,
    act_dim: usize,
) -> Result<(), WireError> {
    check_sealed(header, header.format_version, key, &[float_bytes(payload)])?;
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

/// Where a chunk at place `got` (its sender's epoch, its sequence number) stands in a stream
/// that expects `expected` next (`None`: no chunk of it accepted yet): it must not go back.
/// Places compare by epoch first: a later epoch (a restarted actor) starts the stream again at
/// whatever sequence number; an earlier one, or an earlier number of the same epoch, goes back.
/// Only an accepted chunk moves the stream, and no chunk is ahead of its real sender but a
/// forged one, which the tag rejects first: so no chunk can hold a stream up.
pub fn check_sequence(got: (u64, u64), expected: Option<(u64, u64)>) -> Result<(), WireError> {
    match expected {
        Some(next) if got < next => Err(WireError::OutOfOrder {
            got,
            expected: next,
        }),
        _ => Ok(()),
    }
}

/// Checks a weights broadcast under `key`: version, length, checksum and tag (over version,
/// length and payload).
pub fn validate_weights(
    header: &WeightsHeader,
    payload: &[u8],
    key: &RunKey,
) -> Result<(), WireError> {
    let mut sealer = header.sealer(key);
    sealer.update(payload);
    check_weights(header, payload.len(), sealer.finish())
}

/// [`validate_weights`] of a payload of `len` bytes whose seal was computed while it was
/// copied (a [`Sealed::sealer`] of the header fed the payload).
pub fn check_weights(header: &WeightsHeader, len: usize, seal: Seal) -> Result<(), WireError> {
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
    header.check_seal(seal)
}

/// Checks a batch request under `key`: version, checksum, tag, kind and sizes (the batch must
/// fit in `max_floats`).
pub fn validate_request(
    request: &BatchRequest,
    key: &RunKey,
    obs_dim: usize,
    act_dim: usize,
    max_floats: usize,
) -> Result<BatchKind, WireError> {
    check_sealed(request, request.format_version, key, &[])?;
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

    fn key() -> RunKey {
        RunKey::from_bytes([1; 32])
    }

    /// A key other than the run's: a forger's, whose seals carry a valid CRC-32.
    fn forger() -> RunKey {
        RunKey::from_bytes([2; 32])
    }

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

    /// Validates chunks of 2 actors of 3 + 2 values under the run's key.
    fn valid(h: &ChunkHeader, p: &[f32]) -> Result<(), WireError> {
        validate_chunk(h, p, &key(), 2, 3, 2)
    }

    #[test]
    fn chunk_validation_rejects_bad_version_dims_values_and_actor() {
        let k = key();
        let (h, mut p) = chunk(4);
        let stride = step_stride(3, 2);
        for s in 0..4 {
            p[s * stride + 6..s * stride + 10].fill(0.0);
        }
        assert_eq!(valid(&h.sealed(&k, &p), &p), Ok(()));
        let bad = ChunkHeader {
            format_version: 99,
            ..h
        };
        assert!(matches!(
            valid(&bad.sealed(&k, &p), &p),
            Err(WireError::Version { got: 99 })
        ));
        assert!(matches!(
            validate_chunk(&h.sealed(&k, &p), &p, &k, 1, 3, 2),
            Err(WireError::UnknownActor { .. })
        ));
        assert!(matches!(
            validate_chunk(&h.sealed(&k, &p), &p, &k, 2, 4, 2),
            Err(WireError::Dims(_))
        ));
        assert!(matches!(
            valid(&h.sealed(&k, &p[1..]), &p[1..]),
            Err(WireError::Dims(_))
        ));
        let mut nan = p.clone();
        nan[2] = f32::NAN;
        assert!(matches!(
            valid(&h.sealed(&k, &nan), &nan),
            Err(WireError::Value { index: 2, .. })
        ));
        let mut inf = p.clone();
        inf[stride] = f32::INFINITY;
        assert!(valid(&h.sealed(&k, &inf), &inf).is_err());
        let mut flag = p.clone();
        flag[6] = 0.5;
        assert!(matches!(
            valid(&h.sealed(&k, &flag), &flag),
            Err(WireError::Value { index: 6, .. })
        ));
        let mut mask = p.clone();
        mask[stride + 13] = 1.5;
        assert!(matches!(
            valid(&h.sealed(&k, &mask), &mask),
            Err(WireError::Value { index, .. }) if index == stride + 13
        ));
        let empty = ChunkHeader { steps: 0, ..h };
        assert!(valid(&empty.sealed(&k, &[]), &[]).is_err());
        // a header or a payload changed after sealing fails the checksum
        let sealed = h.sealed(&k, &p);
        let moved = ChunkHeader {
            sequence: 1 << 63,
            ..sealed
        };
        let mut flipped = p.clone();
        flipped[0] = f32::from_bits(flipped[0].to_bits() ^ 1);
        for (header, payload) in [(moved, &p), (sealed, &flipped)] {
            let e = valid(&header, payload).unwrap_err();
            assert_eq!(REASONS[e.reason()], "checksum", "{e}");
        }
    }

    /// What the CRC-32 alone accepted: `genuine`, sealed under the run's key, with a field
    /// rewritten by `rewrite` and its checksum computed again, by a process without the key
    /// (under another key: its CRC-32 is right), keeping the old tag or writing its own. Both
    /// are refused by `check` as `unauthenticated`, and the genuine message is taken.
    fn forged_is_unauthenticated<T: Sealed + std::fmt::Debug>(
        genuine: T,
        payload: &[&[u8]],
        rewrite: impl Fn(T) -> T,
        check: impl Fn(&T) -> Result<(), WireError>,
    ) {
        let genuine = genuine.seal_with(&key(), payload);
        assert_eq!(check(&genuine), Ok(()), "{genuine:?}");
        let rewritten = rewrite(genuine);
        let own_tag = rewritten.seal_with(&forger(), payload);
        let (checksum, _) = own_tag.seal_fields();
        let (_, tag) = genuine.seal_fields();
        let old_tag = rewritten.with_seal(Seal {
            checksum,
            tag: blake3::Hash::from_bytes(*tag),
        });
        for forged in [own_tag, old_tag] {
            assert_eq!(
                check(&forged),
                Err(WireError::Unauthenticated),
                "{forged:?}"
            );
            assert_eq!(
                REASONS[WireError::Unauthenticated.reason()],
                "unauthenticated"
            );
        }
        // a message sealed under the run's key for another kind of message is refused too
        let mut other = Sealer::new(&key(), "ctxrace another kind");
        genuine.feed(&mut other);
        payload.iter().for_each(|part| other.update(part));
        assert_eq!(
            check(&genuine.with_seal(other.finish())),
            Err(WireError::Unauthenticated)
        );
    }

    #[test]
    fn every_kind_rewritten_with_a_recomputed_crc_is_unauthenticated() {
        let k = key();
        // a chunk moved to sequence 2^63 (issue 47's first poisoned value)
        let (h, p) = chunk(2);
        let p = vec![0.0; p.len()];
        let bytes = float_bytes(&p);
        forged_is_unauthenticated(
            h,
            &[bytes],
            |h| ChunkHeader {
                sequence: 1 << 63,
                ..h
            },
            |h| validate_chunk(h, &p, &k, 2, 3, 2),
        );
        // weights locked onto a plausible version (the probe that held both actors)
        let weights = b"some weights".to_vec();
        forged_is_unauthenticated(
            WeightsHeader::new(3, weights.len()),
            &[&weights],
            |h| WeightsHeader { version: 900, ..h },
            |h| validate_weights(h, &weights, &k),
        );
        let request = BatchRequest {
            format_version: FORMAT_VERSION,
            batch: 2,
            length: 4,
            ..Default::default()
        };
        forged_is_unauthenticated(
            request,
            &[],
            |r| BatchRequest { batch: 3, ..r },
            |r| validate_request(r, &k, 3, 2, 1000).map(|_| ()),
        );
        let answer = BatchHeader {
            batch: 1,
            ..BatchHeader::answering(&request)
        };
        let floats = [0.25f32, 0.5];
        forged_is_unauthenticated(
            answer,
            &[float_bytes(&floats)],
            |h| BatchHeader { refused: 9, ..h },
            |h| check_sealed(h, h.format_version, &k, &[float_bytes(&floats)]),
        );
        let episode = EpisodeReport {
            format_version: FORMAT_VERSION,
            env_steps: 100,
            steps: 100,
            ..Default::default()
        };
        forged_is_unauthenticated(
            episode,
            &[],
            |m| EpisodeReport {
                env_steps: 9_200_000_000_000_000_000,
                ..m
            },
            |m| check_sealed(m, m.format_version, &k, &[]),
        );
        let beat = Heartbeat {
            format_version: FORMAT_VERSION,
            pid: 42,
            ..Default::default()
        };
        forged_is_unauthenticated(
            beat,
            &[],
            |b| Heartbeat {
                policy_version: u64::MAX,
                ..b
            },
            |b| check_sealed(b, b.format_version, &k, &[]),
        );
        let status = ReplayStatus {
            format_version: FORMAT_VERSION,
            ..Default::default()
        };
        forged_is_unauthenticated(
            status,
            &[],
            |s| ReplayStatus {
                dropped_chunks: 4_300_000_000,
                ..s
            },
            |s| check_sealed(s, s.format_version, &k, &[]),
        );
    }

    #[test]
    fn a_stream_goes_on_in_its_epoch_or_a_later_one_only() {
        assert_eq!(check_sequence((3, 1 << 63), None), Ok(()));
        assert_eq!(check_sequence((3, 5), Some((3, 5))), Ok(()));
        // chunks a sender dropped: a gap, no rejection
        assert_eq!(check_sequence((3, 5 + (1 << 40)), Some((3, 5))), Ok(()));
        // a restarted actor: a later epoch, from its own sequence numbers
        assert_eq!(check_sequence((4, 0), Some((3, 5))), Ok(()));
        for got in [(3, 4), (3, 0), (2, 9), (2, u64::MAX)] {
            let e = check_sequence(got, Some((3, 5))).unwrap_err();
            assert_eq!(REASONS[e.reason()], "out_of_order", "{got:?}: {e}");
        }
        assert!(new_epoch() <= new_epoch());
    }

    #[test]
    fn weights_and_request_validation() {
        let k = key();
        let bytes = b"some weights".to_vec();
        let h = WeightsHeader::new(3, bytes.len()).seal_with(&k, &[&bytes]);
        assert_eq!(validate_weights(&h, &bytes, &k), Ok(()));
        let mut flipped = bytes.clone();
        flipped[0] ^= 1;
        assert!(matches!(
            validate_weights(&h, &flipped, &k),
            Err(WireError::Checksum { .. })
        ));
        assert!(validate_weights(&h, &bytes[1..], &k).is_err());
        // the header is covered too: a version rewritten to the largest one is refused
        let absurd = WeightsHeader {
            version: u64::MAX,
            ..h
        };
        assert!(matches!(
            validate_weights(&absurd, &bytes, &k),
            Err(WireError::Checksum { .. })
        ));
        // a batch answer's seal covers its header, its refusal code and every float
        let request = BatchRequest {
            format_version: FORMAT_VERSION,
            kind: 0,
            request_id: 4,
            batch: 2,
            length: 4,
            client: 77,
            ..Default::default()
        };
        let answer = BatchHeader {
            batch: 1,
            ..BatchHeader::answering(&request)
        };
        assert_eq!((answer.request_id, answer.client), (4, 77));
        let (obs, reward) = ([0.25f32, 0.5], [1.0f32]);
        let sealed = answer.sealed(&k, &[&obs, &reward]);
        let parts = |a: &[f32]| [float_bytes(a).to_vec(), float_bytes(&reward).to_vec()];
        let check = |h: &BatchHeader, a: &[f32]| {
            let [x, y] = parts(a);
            h.check_with(&k, &[&x, &y])
        };
        assert_eq!(check(&sealed, &obs), Ok(()));
        let flipped = [f32::from_bits(0.25f32.to_bits() ^ 1), 0.5];
        assert!(matches!(
            check(&sealed, &flipped),
            Err(WireError::Checksum { .. })
        ));
        let refusal = BatchHeader {
            refused: 1 + 8,
            ..sealed
        };
        assert!(matches!(
            check(&refusal, &obs),
            Err(WireError::Checksum { .. })
        ));
        assert_eq!(refusal.refusal(), Some("unservable"));
        assert_eq!(sealed.refusal(), None);
        let r = request.seal_with(&k, &[]);
        let valid = |r: BatchRequest, max| validate_request(&r.seal_with(&k, &[]), &k, 3, 2, max);
        assert_eq!(
            validate_request(&r, &k, 3, 2, 1000),
            Ok(BatchKind::Sequence)
        );
        assert!(valid(r, 10).is_err());
        assert!(valid(BatchRequest { kind: 7, ..r }, 1000).is_err());
        assert!(valid(BatchRequest { batch: 0, ..r }, 1000).is_err());
        // sizes whose product overflows are rejected, not wrapped into a small number
        let huge = BatchRequest {
            batch: u32::MAX,
            length: u32::MAX,
            ..r
        };
        let huge = huge.seal_with(&k, &[]);
        assert!(validate_request(&huge, &k, usize::MAX / 4, 2, usize::MAX).is_err());
        // a transition request's length is 1 + its reward delay: 1 or 2
        let transitions = |length| BatchRequest {
            kind: BatchKind::Transition.code(),
            frames: 2,
            length,
            ..r
        };
        for (length, ok) in [(0, false), (1, true), (2, true), (3, false)] {
            let got = valid(transitions(length), 1000);
            assert_eq!(got.is_ok(), ok, "length {length}: {got:?}");
        }
        assert_eq!(sequence_floats(usize::MAX, 2, 1, 1), None);
        assert_eq!(transition_floats(2, usize::MAX, 1, 1), None);
    }
}
