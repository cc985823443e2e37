//! Fault injection: raw senders that put any header and payload on a live run's real services,
//! bypassing every check a well-behaved sender makes, so that tests (and tools probing a run)
//! can show that each kind of malformed message is rejected, counted under its reason, and
//! harms nothing else.
//!
//! The publishers live as long as the [`Injector`]: a publisher that disappears before its
//! subscribers connected to it takes its unread messages with it. Its weights publisher takes
//! the slot a restarting learner would use, so inject while the learner runs.

use super::transport::{ice, RunTransport, Wake};
use super::wire::{BatchRequest, ChunkHeader, EpisodeReport, WeightsHeader, MAX_CHUNK_FLOATS};
use anyhow::{anyhow, Result};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;

/// Largest weights blob an [`Injector`] sends.
const MAX_WEIGHTS: usize = 4096;

/// Raw publishers on every service a run's processes receive on.
pub struct Injector {
    chunks: Vec<Publisher<ipc::Service, [f32], ChunkHeader>>,
    requests: Publisher<ipc::Service, BatchRequest, ()>,
    weights: Publisher<ipc::Service, [u8], WeightsHeader>,
    episodes: Publisher<ipc::Service, EpisodeReport, ()>,
    wake_replay: Notifier<ipc::Service>,
    wake_actors: Notifier<ipc::Service>,
}

impl Injector {
    /// Publishers on the services of the run `transport` joined.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        let chunks = (0..transport.actors())
            .map(|id| {
                transport
                    .trajectory_service(id)?
                    .publisher_builder()
                    .initial_max_slice_len(MAX_CHUNK_FLOATS)
                    .max_loaned_samples(1)
                    .create()
                    .map_err(ice("injected chunk publisher"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            chunks,
            requests: transport
                .request_service()?
                .publisher_builder()
                .create()
                .map_err(ice("injected request publisher"))?,
            weights: transport
                .weights_service()?
                .publisher_builder()
                .initial_max_slice_len(MAX_WEIGHTS)
                .max_loaned_samples(1)
                .create()
                .map_err(ice("injected weights publisher"))?,
            episodes: transport
                .metrics_service()?
                .publisher_builder()
                .create()
                .map_err(ice("injected metrics publisher"))?,
            wake_replay: transport.notifier(Wake::Replay)?,
            wake_actors: transport.notifier(Wake::Actors)?,
        })
    }

    /// Sends `header` and `payload` (at most [`MAX_CHUNK_FLOATS`] floats) on the trajectory
    /// service of actor `stream`; returns the subscribers reached.
    pub fn chunk(&self, stream: usize, header: ChunkHeader, payload: &[f32]) -> Result<usize> {
        let publisher = self
            .chunks
            .get(stream)
            .ok_or_else(|| anyhow!("no trajectory service {stream}"))?;
        send_slice(publisher, header, payload, &self.wake_replay)
    }

    /// Sends a batch request as it is.
    pub fn request(&self, request: BatchRequest) -> Result<usize> {
        let reached = self
            .requests
            .send_copy(request)
            .map_err(ice("send injected request"))?;
        let _ = self.wake_replay.notify();
        Ok(reached)
    }

    /// Broadcasts `header` with `bytes` (at most 4 KiB) on the weights service.
    pub fn weights(&self, header: WeightsHeader, bytes: &[u8]) -> Result<usize> {
        if bytes.len() > MAX_WEIGHTS {
            return Err(anyhow!("injected weights are at most {MAX_WEIGHTS} bytes"));
        }
        send_slice(&self.weights, header, bytes, &self.wake_actors)
    }

    /// Publishes episode metrics as they are.
    pub fn episode(&self, metrics: EpisodeReport) -> Result<usize> {
        self.episodes
            .send_copy(metrics)
            .map_err(ice("send injected metrics"))
    }
}

/// Sends one sample of `header` and `payload` and wakes whoever `wake` wakes; returns the
/// subscribers reached.
fn send_slice<T, H>(
    publisher: &Publisher<ipc::Service, [T], H>,
    header: H,
    payload: &[T],
    wake: &Notifier<ipc::Service>,
) -> Result<usize>
where
    T: std::fmt::Debug + ZeroCopySend + Copy + 'static,
    H: std::fmt::Debug + ZeroCopySend + Default + 'static,
{
    let mut sample = publisher
        .loan_slice_uninit(payload.len())
        .map_err(ice("loan injected sample"))?;
    *sample.user_header_mut() = header;
    let reached = sample
        .write_from_slice(payload)
        .send()
        .map_err(ice("send injected sample"))?;
    let _ = wake.notify();
    Ok(reached)
}
