//! Property tests of the snapshot reader: a snapshot with any byte changed, cut short or
//! extended, and any file that is not a snapshot, is refused with an error naming the file;
//! never a panic, never a buffer sized from a damaged header.

use ctxrace_ipc::TrajectoryStep;
use ctxrace_replay::{read_snapshot, write_snapshot, LimiterCounts, ReplayBuffer, SnapshotShape};
use proptest::prelude::*;
use std::path::Path;

const OBS: usize = 3;
const ACT: usize = 2;

/// The shape of the buffer [`valid_snapshot`] saves.
fn shape() -> SnapshotShape {
    SnapshotShape::of(&ReplayBuffer::new(64, 2, OBS, ACT))
}

/// The bytes of a valid snapshot of two actors' steps.
fn valid_snapshot(dir: &Path) -> Vec<u8> {
    let mut buffer = ReplayBuffer::new(64, 2, OBS, ACT);
    for actor in 0..2 {
        let mut payload = Vec::new();
        for k in 0..10 {
            TrajectoryStep {
                obs: &[k as f32, 0.5, -0.5],
                action: &[0.1, -0.1],
                reward: 1.0,
                is_first: k == 0,
                is_terminal: false,
                is_last: k == 9,
                context: [0.1, -0.2],
                mask: Some([0.5, 1.0]),
            }
            .encode(&mut payload);
        }
        buffer.insert_chunk(actor, &payload, true);
    }
    let path = dir.join("valid.snapshot");
    let counts = LimiterCounts {
        inserts: 20,
        samples: 7,
    };
    write_snapshot(&path, &buffer, counts).unwrap();
    std::fs::read(&path).unwrap()
}

/// How a test damages a valid snapshot.
#[derive(Debug, Clone)]
enum Damage {
    Flip { at: usize, bits: u8 },
    Truncate { to: usize },
    Append { bytes: Vec<u8> },
    Garbage { bytes: Vec<u8> },
}

fn damage() -> impl Strategy<Value = Damage> {
    prop_oneof![
        (any::<usize>(), 1u8..=255).prop_map(|(at, bits)| Damage::Flip { at, bits }),
        any::<usize>().prop_map(|to| Damage::Truncate { to }),
        prop::collection::vec(any::<u8>(), 1..64).prop_map(|bytes| Damage::Append { bytes }),
        prop::collection::vec(any::<u8>(), 0..512).prop_map(|bytes| Damage::Garbage { bytes }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn a_damaged_snapshot_is_an_error_not_a_panic(damage in damage()) {
        let dir = tempfile::tempdir().unwrap();
        let mut bytes = valid_snapshot(dir.path());
        match &damage {
            Damage::Flip { at, bits } => {
                let at = at % bytes.len();
                bytes[at] ^= bits;
            }
            Damage::Truncate { to } => bytes.truncate(to % bytes.len()),
            Damage::Append { bytes: more } => bytes.extend_from_slice(more),
            Damage::Garbage { bytes: garbage } => bytes = garbage.clone(),
        }
        let path = dir.path().join("damaged.snapshot");
        std::fs::write(&path, &bytes).unwrap();
        let err = read_snapshot(&path, shape()).err();
        prop_assert!(err.is_some(), "{damage:?} was accepted");
        let message = format!("{:#}", err.unwrap());
        prop_assert!(message.contains("damaged.snapshot"), "{}", message);
    }
}

#[test]
fn the_undamaged_snapshot_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = valid_snapshot(dir.path());
    let path = dir.path().join("copy.snapshot");
    std::fs::write(&path, bytes).unwrap();
    let (buffer, counts) = read_snapshot(&path, shape()).unwrap();
    assert_eq!(buffer.len(), 20);
    assert_eq!((counts.inserts, counts.samples), (20, 7));
}
