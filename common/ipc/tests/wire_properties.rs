//! Property tests of the wire validators on arbitrary input: every header and payload is either
//! accepted or rejected with a [`WireError`], never a panic, and what is accepted is what a
//! well-formed sender holding the run's key would have sent. Headers are sealed with the run's
//! key (as by a faulty process of the run), so that every other check is reached.

use ctxrace_ipc::wire::{
    step_stride, validate_chunk, validate_request, validate_weights, BatchRequest, ChunkHeader,
    Sealed as _, WeightsHeader, FORMAT_VERSION, MAX_CHUNK,
};
use ctxrace_ipc::RunKey;
use proptest::prelude::*;

/// The run's key.
fn key() -> RunKey {
    RunKey::from_bytes([4; 32])
}

/// Mostly the current version, sometimes any other.
fn version() -> impl Strategy<Value = u32> {
    prop_oneof![4 => Just(FORMAT_VERSION), 1 => any::<u32>()]
}

/// Small values near the run's, sometimes anything.
fn small() -> impl Strategy<Value = u32> {
    prop_oneof![4 => 0u32..8, 1 => any::<u32>()]
}

/// Floats with the values a broken sender produces: NaN, infinities, flags out of range.
fn float() -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => Just(0.0f32),
        4 => Just(1.0f32),
        2 => -2.0f32..2.0,
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => any::<f32>(),
    ]
}

fn chunk_header() -> impl Strategy<Value = ChunkHeader> {
    (version(), small(), small(), small(), small(), any::<u64>()).prop_map(
        |(format_version, actor_id, obs_dim, act_dim, steps, sequence)| ChunkHeader {
            format_version,
            actor_id,
            obs_dim,
            act_dim,
            steps,
            sequence,
            ..Default::default()
        },
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn chunks_are_accepted_only_when_well_formed(
        header in chunk_header(),
        payload in prop::collection::vec(float(), 0..200),
    ) {
        let (actors, obs, act) = (3, 3, 2);
        let header = header.sealed(&key(), &payload);
        if validate_chunk(&header, &payload, &key(), actors, obs, act).is_ok() {
            prop_assert_eq!(header.format_version, FORMAT_VERSION);
            prop_assert!((header.actor_id as usize) < actors);
            let steps = header.steps as usize;
            prop_assert!((1..=MAX_CHUNK).contains(&steps));
            prop_assert_eq!(payload.len(), steps * step_stride(obs, act));
            prop_assert!(payload.iter().all(|v| v.is_finite()));
        }
    }

    #[test]
    fn batch_requests_never_overflow(
        format_version in version(),
        kind in prop_oneof![0u32..3, any::<u32>()],
        batch in any::<u32>(),
        length in any::<u32>(),
        frames in any::<u32>(),
        max_floats in prop_oneof![Just(usize::MAX), 0usize..1_000_000],
    ) {
        let request = BatchRequest { format_version, kind, batch, length, frames, ..Default::default() }
            .seal_with(&key(), &[]);
        // a request the replay accepts fits in max_floats (no wrapped product lets one through)
        if validate_request(&request, &key(), 108, 2, max_floats).is_ok() {
            prop_assert!(batch > 0);
            let per = if kind == 0 { length as u128 * (108 + 2 + 8) } else { frames as u128 * 216 + 6 };
            prop_assert!(batch as u128 * per <= max_floats as u128);
            // a transition's reward lags its action by at most one step
            prop_assert!(kind == 0 || (1..=2).contains(&length));
        }
    }

    #[test]
    fn weights_are_accepted_only_with_their_seal(
        format_version in version(),
        payload in prop::collection::vec(any::<u8>(), 0..256),
        checksum in prop_oneof![Just(None), any::<u32>().prop_map(Some)],
        len_delta in prop_oneof![4 => Just(0i64), 1 => -3i64..3],
    ) {
        let len = (payload.len() as i64 + len_delta).max(0) as usize;
        let sealed = WeightsHeader { format_version, ..WeightsHeader::new(1, len) }
            .seal_with(&key(), &[&payload]);
        let header = WeightsHeader { checksum: checksum.unwrap_or(sealed.checksum), ..sealed };
        if validate_weights(&header, &payload, &key()).is_ok() {
            prop_assert_eq!(header, sealed);
            prop_assert_eq!(header.len, payload.len() as u64);
        }
    }
}
