//! Learner -> actors weights broadcast: one publisher, history 1, sealed with the run's key
//! (a checksum and a tag over the version, the length and the bytes).

use super::bounds::check_version;
use super::shared::{check_readable, copy_slice_with, read_once};
use super::transport::{termination_requested, timed_wait, RunTransport, Wake};
use super::wire::{check_weights, Sealed as _, WeightsHeader, WireError};
use super::{ReadStage, RejectLog};
use crate::error::{ice, IpcError, Result};
use crate::key::RunKey;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use std::time::Duration;

/// Largest weights blob (64 MiB): a publisher allocates at most this, and receivers reject a
/// sample claiming more before copying it (its length is read from shared memory).
pub const DEFAULT_MAX_WEIGHTS_BYTES: usize = 64 << 20;
/// Weights slots a publisher preallocates: the history, the buffers and one loan share them,
/// since receivers copy out at once.
const WEIGHTS_SLOTS: usize = 4;
/// Bytes copied and hashed at a time, when publishing and when receiving.
const HASH_BLOCK: usize = 64 << 10;

/// The learner's weights broadcaster.
pub struct WeightsPublisher {
    publisher: Publisher<ipc::Service, [u8], WeightsHeader>,
    wake: Notifier<ipc::Service>,
    max_bytes: usize,
    key: RunKey,
}

impl WeightsPublisher {
    /// A publisher of blobs up to `max_bytes` (at most [`DEFAULT_MAX_WEIGHTS_BYTES`]),
    /// preallocated once ([`WEIGHTS_SLOTS`] slots).
    pub fn new(transport: &RunTransport, max_bytes: usize) -> Result<Self> {
        let max_bytes = max_bytes.min(DEFAULT_MAX_WEIGHTS_BYTES);
        let publisher = transport
            .weights_service()?
            .publisher_builder()
            .initial_max_slice_len(max_bytes)
            .allocation_strategy(AllocationStrategy::Static)
            .max_loaned_samples(1)
            .override_sample_preallocation(|n| n.min(WEIGHTS_SLOTS))
            .create()
            .map_err(ice("weights publisher"))?;
        Ok(Self {
            publisher,
            wake: transport.notifier(Wake::Actors)?,
            max_bytes,
            key: transport.key().clone(),
        })
    }

    /// Broadcasts `bytes` as policy `version`; returns the number of subscribers reached. The
    /// newest version stays available to subscribers that connect later.
    pub fn publish(&self, version: u64, bytes: &[u8]) -> Result<usize> {
        if bytes.len() > self.max_bytes {
            return Err(IpcError::WeightsTooLarge {
                len: bytes.len(),
                max: self.max_bytes,
            });
        }
        let mut sample = self
            .publisher
            .loan_slice_uninit(bytes.len())
            .map_err(ice("loan weights"))?;
        // Copy and seal block by block: the block is still in cache for the hashes.
        let header = WeightsHeader::new(version, bytes.len());
        let mut sealer = header.sealer(&self.key);
        for (dst, src) in sample
            .payload_mut()
            .chunks_mut(HASH_BLOCK)
            .zip(bytes.chunks(HASH_BLOCK))
        {
            // SAFETY: `dst` and `src` have the same length (equal-sized blocks of equal-length
            // slices), do not overlap (one is shared memory), and u8 has no invalid values.
            unsafe {
                std::ptr::copy_nonoverlapping(
                    src.as_ptr(),
                    dst.as_mut_ptr().cast::<u8>(),
                    src.len(),
                )
            };
            sealer.update(src);
        }
        *sample.user_header_mut() = header.with_seal(sealer.finish());
        // SAFETY: the loop above wrote every byte of the loaned slice (its length is bytes.len()).
        let sample = unsafe { sample.assume_init() };
        let reached = sample.send().map_err(ice("send weights"))?;
        let _ = self.wake.notify();
        Ok(reached)
    }

    /// Connects subscribers that appeared since the last publish and hands them the newest
    /// version. Call it regularly (it is cheap) so late or restarted actors get weights.
    pub fn update_connections(&self) -> Result<()> {
        self.publisher
            .update_connections()
            .map_err(ice("weights update_connections"))?;
        let _ = self.wake.notify();
        Ok(())
    }
}

/// An actor's weights receiver.
pub struct WeightsReceiver {
    subscriber: Subscriber<ipc::Service, [u8], WeightsHeader>,
    wake: Listener<ipc::Service>,
    current: Option<u64>,
    /// No version beyond it is taken: the learner's gradient-step target.
    max_version: u64,
    key: RunKey,
    rejects: RejectLog,
    /// The copy of the blob being read.
    copy: Vec<u8>,
    /// The newest verified copy.
    held: Vec<u8>,
}

impl WeightsReceiver {
    /// Subscribes to the run's weights, taking versions up to `max_version` (the learner's
    /// gradient-step target, [`crate::RunBounds::max_policy_version`]).
    pub fn new(transport: &RunTransport, max_version: u64) -> Result<Self> {
        let wake = transport.listener(Wake::Actors)?;
        let subscriber = transport
            .weights_service()?
            .subscriber_builder()
            .create()
            .map_err(ice("weights subscriber"))?;
        Ok(Self {
            subscriber,
            wake,
            current: None,
            max_version,
            key: transport.key().clone(),
            rejects: RejectLog::new("weights"),
            copy: Vec::new(),
            held: Vec::new(),
        })
    }

    /// Calls `f(version, bytes)` on the newest verified weights newer than the last ones handed
    /// out; `None` if there are none. Blobs failing the checksum or the tag (a version is taken
    /// only from the holder of the run's key: the learner), or of a version beyond the run's,
    /// are counted, logged and skipped, and change nothing.
    pub fn latest_with<R>(&mut self, f: impl FnOnce(u64, &[u8]) -> R) -> Result<Option<R>> {
        self.latest_with_observed(&mut |_| {}, f)
    }

    /// [`latest_with`](Self::latest_with), calling `hook` at each [`ReadStage`] of each blob.
    /// Each blob is copied out of shared memory first (into buffers reused from blob to blob),
    /// then checked, and `f` sees only the copy: a blob changed in shared memory while it is
    /// read is at worst rejected.
    pub fn latest_with_observed<R>(
        &mut self,
        hook: &mut dyn FnMut(ReadStage),
        f: impl FnOnce(u64, &[u8]) -> R,
    ) -> Result<Option<R>> {
        let mut newest = None;
        while let Some(sample) = self.subscriber.receive().map_err(ice("receive weights"))? {
            let copied = check_readable(sample.header())
                .and_then(|()| read_once(sample.user_header()))
                .and_then(|header| {
                    let len = sample.payload().len();
                    if len > DEFAULT_MAX_WEIGHTS_BYTES {
                        return Err(WireError::Dims(format!(
                            "{len} bytes of weights, at most {DEFAULT_MAX_WEIGHTS_BYTES} are sent"
                        )));
                    }
                    // the seal of each block while it is still in cache
                    let mut sealer = header.sealer(&self.key);
                    copy_slice_with(sample.payload(), &mut self.copy, HASH_BLOCK, |block| {
                        sealer.update(block)
                    })
                    .map(|()| (header, sealer.finish()))
                });
            hook(ReadStage::Copied);
            let checked = copied.and_then(|(header, seal)| {
                check_weights(&header, self.copy.len(), seal)
                    .and_then(|()| {
                        check_version("weights version", header.version, self.max_version)
                    })
                    .map(|()| header)
            });
            let header = match checked {
                Ok(header) => header,
                Err(e) => {
                    self.rejects.reject(&e);
                    continue;
                }
            };
            hook(ReadStage::Validated);
            if self.current.max(newest).is_none_or(|v| header.version > v) {
                std::mem::swap(&mut self.copy, &mut self.held);
                newest = Some(header.version);
            }
        }
        Ok(newest.map(|version| {
            self.current = Some(version);
            f(version, &self.held)
        }))
    }

    /// The newest verified weights newer than the last ones returned, copied out.
    pub fn latest(&mut self) -> Result<Option<(u64, Vec<u8>)>> {
        self.latest_with(|v, bytes| (v, bytes.to_vec()))
    }

    /// Like [`Self::latest_with`], waiting up to `timeout` for a broadcast if none is there.
    pub fn wait_with<R>(
        &mut self,
        timeout: Duration,
        f: impl FnOnce(u64, &[u8]) -> R,
    ) -> Result<Option<R>> {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            if self.subscriber.has_samples().unwrap_or(false) {
                return self.latest_with(f);
            }
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() || termination_requested() {
                return Ok(None);
            }
            timed_wait(&self.wake, left, "wait for weights")?;
        }
    }

    /// The version of the last weights handed out.
    pub fn current_version(&self) -> Option<u64> {
        self.current
    }

    /// Blobs rejected (bad version, length, checksum or tag, or a version beyond the run's).
    pub fn rejected(&self) -> u64 {
        self.rejects.count()
    }

    /// Blobs rejected, by reason ([`super::wire::REASONS`]).
    pub fn rejected_by_reason(&self) -> [u64; super::wire::REASONS.len()] {
        self.rejects.by_reason()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{cleanup, Isolated};

    /// Two actors and the launcher, each a node of its own, subscribed before and after the
    /// publisher's first broadcast: every one of them gets every broadcast's version, whoever
    /// reads first (the lag of issue 34 was not in delivery: see actor::process).
    #[test]
    fn every_receiver_gets_each_new_version() {
        let isolated = Isolated::new("weights-all");
        let prefix = isolated.0.clone();
        let nodes: Vec<RunTransport> = ["launcher", "learner", "actor-0", "actor-1"]
            .iter()
            .map(|role| RunTransport::open(&prefix, 2, role, &crate::test_key()).unwrap())
            .collect();
        let mut launcher = WeightsReceiver::new(&nodes[0], 1000).unwrap();
        let publisher = WeightsPublisher::new(&nodes[1], 1 << 16).unwrap();
        let blob = vec![3u8; 5000];
        publisher.publish(0, &blob).unwrap();
        let mut actors: Vec<WeightsReceiver> = nodes[2..]
            .iter()
            .map(|t| WeightsReceiver::new(t, 1000).unwrap())
            .collect();
        for version in (0..100).step_by(10) {
            publisher.update_connections().unwrap();
            if version > 0 {
                assert_eq!(publisher.publish(version, &blob).unwrap(), 3);
            }
            // readers take turns at being first
            let mut readers: Vec<&mut WeightsReceiver> = actors
                .iter_mut()
                .chain(std::iter::once(&mut launcher))
                .collect();
            readers.rotate_left(version as usize / 10 % 3);
            let got: Vec<Option<u64>> = readers
                .into_iter()
                .map(|r| r.latest_with(|v, _| v).unwrap())
                .collect();
            assert_eq!(got, vec![Some(version); 3], "after version {version}");
        }
    }

    #[test]
    fn late_subscriber_gets_the_newest_and_bad_checksums_are_rejected() {
        let isolated = Isolated::new("weights");
        let prefix = isolated.0.clone();
        {
            let t = RunTransport::open(&prefix, 2, "learner", &crate::test_key()).unwrap();
            let publisher = WeightsPublisher::new(&t, 1 << 20).unwrap();
            let v1 = vec![1u8; 1000];
            let v2: Vec<u8> = (0..5000).map(|i| i as u8).collect();
            publisher.publish(1, &v1).unwrap();
            publisher.publish(2, &v2).unwrap();
            assert!(publisher.publish(3, &vec![0; 2 << 20]).is_err());

            let mut late = WeightsReceiver::new(&t, 1000).unwrap();
            publisher.update_connections().unwrap();
            assert_eq!(late.latest().unwrap(), Some((2, v2.clone())));
            assert_eq!(late.latest().unwrap(), None);

            // A blob whose checksum does not match is rejected, counted, and never handed out.
            let raw = t
                .weights_service()
                .unwrap()
                .publisher_builder()
                .initial_max_slice_len(64)
                .allocation_strategy(AllocationStrategy::Static)
                .create()
                .unwrap();
            let mut sample = raw.loan_slice_uninit(16).unwrap();
            *sample.user_header_mut() = WeightsHeader {
                checksum: 12345,
                ..WeightsHeader::new(3, 16)
            };
            sample.write_from_slice(&[7u8; 16]).send().unwrap();
            assert_eq!(late.latest().unwrap(), None);
            assert_eq!(late.rejected(), 1);
            publisher.publish(4, &v1).unwrap();
            let got = late
                .wait_with(Duration::from_secs(5), |v, b| (v, b.len()))
                .unwrap();
            assert_eq!(got, Some((4, 1000)));
            assert_eq!(late.current_version(), Some(4));

            // A broadcast that arrives while the newest is held (between two receives of
            // `latest_with`) is a second borrow from the same publisher: it is taken.
            let held = t
                .weights_service()
                .unwrap()
                .subscriber_builder()
                .create()
                .unwrap();
            publisher.update_connections().unwrap();
            publisher.publish(5, &v1).unwrap();
            let first = held.receive().unwrap().unwrap();
            publisher.publish(6, &v2).unwrap();
            let second = held.receive().unwrap().unwrap();
            assert_eq!(
                (first.user_header().version, second.user_header().version),
                (5, 6)
            );
        }
        let report = cleanup(&prefix).unwrap();
        assert_eq!(report.alive_nodes, 0);
        assert!(report.files_removed > 0, "{report:?}");
        assert!(!std::fs::read_dir("/dev/shm")
            .unwrap()
            .flatten()
            .any(|e| e.file_name().to_string_lossy().starts_with(&prefix)));
    }
}
