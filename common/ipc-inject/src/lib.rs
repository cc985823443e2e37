//! Fault injection for tests: raw senders that put any header and payload on a live run's real services,
//! bypassing every check a well-behaved sender makes, so that tests (and tools probing a run)
//! can show that each kind of malformed message is rejected, counted under its reason, and
//! harms nothing else. Messages go out as they are given: seal them ([`ctxrace_ipc::wire::Sealed`])
//! with the run's key to reach the readers' checks after the tag (a faulty process of the
//! run), or with another key to play a process that can write the run's shared memory but does
//! not hold its key (`unauthenticated`).
//!
//! A message can also be kept [`Held`] after it was sent and rewritten in shared memory while
//! a receiver holds it, as a faulty or hostile process could: with the receivers' `*_observed`
//! reads (see [`ctxrace_ipc::ReadStage`]) a test rewrites it at a chosen point of the read.
//!
//! The publishers live as long as the [`Injector`]: a publisher that disappears before its
//! subscribers connected to it takes its unread messages with it. Its weights and batch
//! publishers take the slots a restarting learner and replay would use, so inject while they
//! run.
//!
//! A crate of its own, a dev-dependency only, so that no build of the run's processes compiles
//! it: they cannot send what they are not built to send.

use ctxrace_ipc::wire::MAX_CHUNK_FLOATS;
use ctxrace_ipc::{
    BatchHeader, BatchRequest, ChunkHeader, EpisodeReport, Heartbeat, IpcError, ReplayStatus,
    RunTransport, Wake, WeightsHeader,
};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::fmt::Debug;
use std::marker::PhantomData;
use std::ptr::NonNull;

/// Why an injector could not send.
#[derive(Debug, thiserror::Error)]
pub enum InjectError {
    /// The run's transport or iceoryx2 failed.
    #[error(transparent)]
    Ipc(#[from] IpcError),
    /// An iceoryx2 call failed; `what` names it.
    #[error("{what}: {source}")]
    Iceoryx {
        /// The call.
        what: &'static str,
        /// iceoryx2's error.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The run has no trajectory service of this actor.
    #[error("no trajectory service {0}")]
    NoStream(usize),
    /// A message larger than an injector sends.
    #[error("injected {what} are at most {max} {unit}")]
    TooLarge {
        /// What (`"batches"`, `"weights"`).
        what: &'static str,
        /// The most it sends.
        max: usize,
        /// The unit (`"floats"`, `"bytes"`).
        unit: &'static str,
    },
    /// An element outside a held message's payload.
    #[error("element {index} of a payload of {len} elements")]
    Element {
        /// The element asked for.
        index: usize,
        /// Elements in the payload.
        len: usize,
    },
}

/// The outcome of an injection.
pub type Result<T> = std::result::Result<T, InjectError>;

/// Maps an iceoryx2 error to [`InjectError::Iceoryx`] naming what failed.
fn ice<E: std::error::Error + Send + Sync + 'static>(
    what: &'static str,
) -> impl FnOnce(E) -> InjectError {
    move |e| InjectError::Iceoryx {
        what,
        source: Box::new(e),
    }
}

/// A publisher of plain `T` messages on `service`; `what` names it in an error.
fn publisher<T: Debug + ZeroCopySend>(
    service: std::result::Result<PubSubFactory<ipc::Service, T, ()>, IpcError>,
    what: &'static str,
) -> Result<Publisher<ipc::Service, T, ()>> {
    service?.publisher_builder().create().map_err(ice(what))
}

/// Largest weights blob an [`Injector`] sends.
const MAX_WEIGHTS: usize = 4096;
/// Largest batch an [`Injector`] sends, in floats.
const MAX_BATCH_FLOATS: usize = 1 << 16;

/// Raw publishers on every service a run's processes receive on.
pub struct Injector {
    chunks: Vec<Publisher<ipc::Service, [f32], ChunkHeader>>,
    requests: Publisher<ipc::Service, BatchRequest, ()>,
    weights: Publisher<ipc::Service, [u8], WeightsHeader>,
    batches: Publisher<ipc::Service, [f32], BatchHeader>,
    episodes: Publisher<ipc::Service, EpisodeReport, ()>,
    heartbeats: Publisher<ipc::Service, Heartbeat, ()>,
    status: Publisher<ipc::Service, ReplayStatus, ()>,
    wake_replay: Notifier<ipc::Service>,
    wake_actors: Notifier<ipc::Service>,
    wake_learner: Notifier<ipc::Service>,
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
            requests: publisher(transport.request_service(), "injected request publisher")?,
            weights: transport
                .weights_service()?
                .publisher_builder()
                .initial_max_slice_len(MAX_WEIGHTS)
                .max_loaned_samples(1)
                .create()
                .map_err(ice("injected weights publisher"))?,
            batches: transport
                .batch_service()?
                .publisher_builder()
                .initial_max_slice_len(MAX_BATCH_FLOATS)
                .max_loaned_samples(1)
                .create()
                .map_err(ice("injected batch publisher"))?,
            episodes: publisher(transport.metrics_service(), "injected metrics publisher")?,
            heartbeats: publisher(
                transport.heartbeat_service(),
                "injected heartbeat publisher",
            )?,
            status: publisher(transport.status_service(), "injected status publisher")?,
            wake_replay: transport.notifier(Wake::Replay)?,
            wake_actors: transport.notifier(Wake::Actors)?,
            wake_learner: transport.notifier(Wake::Learner)?,
        })
    }

    /// Sends `header` and `payload` (at most [`MAX_CHUNK_FLOATS`] floats) on the trajectory
    /// service of actor `stream`; returns the subscribers reached.
    pub fn chunk(&self, stream: usize, header: ChunkHeader, payload: &[f32]) -> Result<usize> {
        Ok(self.chunk_held(stream, header, payload)?.reached)
    }

    /// [`chunk`](Self::chunk), keeping the sent chunk to rewrite.
    pub fn chunk_held(
        &self,
        stream: usize,
        header: ChunkHeader,
        payload: &[f32],
    ) -> Result<Held<'_, f32, ChunkHeader>> {
        let publisher = self
            .chunks
            .get(stream)
            .ok_or(InjectError::NoStream(stream))?;
        send_slice(publisher, header, payload, &self.wake_replay)
    }

    /// Sends `header` and `payload` (at most 64 Ki floats) on the batch service, as the replay
    /// answers a request; keeps the sent batch to rewrite.
    pub fn batch_held(
        &self,
        header: BatchHeader,
        payload: &[f32],
    ) -> Result<Held<'_, f32, BatchHeader>> {
        if payload.len() > MAX_BATCH_FLOATS {
            return Err(InjectError::TooLarge {
                what: "batches",
                max: MAX_BATCH_FLOATS,
                unit: "floats",
            });
        }
        send_slice(&self.batches, header, payload, &self.wake_learner)
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
        Ok(self.weights_held(header, bytes)?.reached)
    }

    /// [`weights`](Self::weights), keeping the sent blob to rewrite.
    pub fn weights_held(
        &self,
        header: WeightsHeader,
        bytes: &[u8],
    ) -> Result<Held<'_, u8, WeightsHeader>> {
        if bytes.len() > MAX_WEIGHTS {
            return Err(InjectError::TooLarge {
                what: "weights",
                max: MAX_WEIGHTS,
                unit: "bytes",
            });
        }
        send_slice(&self.weights, header, bytes, &self.wake_actors)
    }

    /// Publishes episode metrics as they are.
    pub fn episode(&self, metrics: EpisodeReport) -> Result<usize> {
        self.episodes
            .send_copy(metrics)
            .map_err(ice("send injected metrics"))
    }

    /// Publishes a heartbeat as it is.
    pub fn heartbeat(&self, beat: Heartbeat) -> Result<usize> {
        self.heartbeats
            .send_copy(beat)
            .map_err(ice("send injected heartbeat"))
    }

    /// Publishes a replay status as it is.
    pub fn status(&self, status: ReplayStatus) -> Result<usize> {
        self.status
            .send_copy(status)
            .map_err(ice("send injected status"))
    }
}

/// A message an [`Injector`] sent, still writable in its publisher's shared memory: the
/// receivers see every rewrite of a message they have not released yet. It lives no longer than
/// its injector, whose publisher keeps the memory mapped.
pub struct Held<'a, T, H> {
    /// Subscribers the message reached.
    pub reached: usize,
    header: NonNull<H>,
    payload: NonNull<T>,
    len: usize,
    injector: PhantomData<&'a Injector>,
}

impl<T: Copy, H: Copy> Held<'_, T, H> {
    /// Rewrites the header.
    pub fn set_header(&self, header: H) {
        // SAFETY: `header` points at the header of a sample of a publisher that lives as long as
        // the injector this borrows: the memory stays mapped, writable by this process and
        // aligned for H, whose every bit pattern a plain wire struct accepts.
        unsafe { std::ptr::write_volatile(self.header.as_ptr(), header) }
    }

    /// Rewrites the payload's element `index`.
    pub fn set(&self, index: usize, value: T) -> Result<()> {
        if index >= self.len {
            return Err(InjectError::Element {
                index,
                len: self.len,
            });
        }
        // SAFETY: as in `set_header`; `index` is within the sample's `len` elements.
        unsafe { std::ptr::write_volatile(self.payload.as_ptr().add(index), value) };
        Ok(())
    }
}

/// Sends one sample of `header` and `payload` and wakes whoever `wake` wakes; returns it held.
fn send_slice<'a, T, H>(
    publisher: &'a Publisher<ipc::Service, [T], H>,
    header: H,
    payload: &[T],
    wake: &Notifier<ipc::Service>,
) -> Result<Held<'a, T, H>>
where
    T: std::fmt::Debug + ZeroCopySend + Copy + 'static,
    H: std::fmt::Debug + ZeroCopySend + Default + 'static,
{
    let len = payload.len();
    let mut sample = publisher
        .loan_slice_uninit(len)
        .map_err(ice("loan injected sample"))?;
    *sample.user_header_mut() = header;
    let header = NonNull::from(sample.user_header_mut());
    let mut sample = sample.write_from_slice(payload);
    let payload = NonNull::from(sample.payload_mut()).cast::<T>();
    let reached = sample.send().map_err(ice("send injected sample"))?;
    let _ = wake.notify();
    Ok(Held {
        reached,
        header,
        payload,
        len,
        injector: PhantomData,
    })
}
