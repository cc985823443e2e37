//! Actor and replay telemetry for the launcher: episode metrics, heartbeats, replay status.

use super::transport::RunTransport;
use super::wire::{EpisodeReport, Heartbeat, ReplayStatus, WireError, FORMAT_VERSION};
use super::{read_once, RejectLog};
use crate::error::{ice, Result};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::fmt::Debug;

/// A publisher of plain `T` messages on `service`, one of the run's telemetry services (or its
/// batch requests); `what` names it in an error.
pub(crate) fn publisher<T: Debug + ZeroCopySend>(
    service: Result<PubSubFactory<ipc::Service, T, ()>>,
    what: &'static str,
) -> Result<Publisher<ipc::Service, T, ()>> {
    service?.publisher_builder().create().map_err(ice(what))
}

/// A subscriber to plain `T` messages on `service`; `what` names it in an error.
fn subscriber<T: Debug + ZeroCopySend>(
    service: Result<PubSubFactory<ipc::Service, T, ()>>,
    what: &'static str,
) -> Result<Subscriber<ipc::Service, T, ()>> {
    service?.subscriber_builder().create().map_err(ice(what))
}

/// An actor's metrics and heartbeat publisher.
pub struct MetricsPublisher {
    metrics: Publisher<ipc::Service, EpisodeReport, ()>,
    heartbeat: Publisher<ipc::Service, Heartbeat, ()>,
}

impl MetricsPublisher {
    /// Publishers on the run's metrics and heartbeat services.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        Ok(Self {
            metrics: publisher(transport.metrics_service(), "metrics publisher")?,
            heartbeat: publisher(transport.heartbeat_service(), "heartbeat publisher")?,
        })
    }

    /// Publishes one finished episode (its `format_version` is set here).
    pub fn episode(&self, metrics: EpisodeReport) -> Result<()> {
        let m = EpisodeReport {
            format_version: FORMAT_VERSION,
            ..metrics
        };
        self.metrics.send_copy(m).map_err(ice("send metrics"))?;
        Ok(())
    }

    /// Publishes a heartbeat (its `format_version` is set here).
    pub fn heartbeat(&self, beat: Heartbeat) -> Result<()> {
        let b = Heartbeat {
            format_version: FORMAT_VERSION,
            ..beat
        };
        self.heartbeat.send_copy(b).map_err(ice("send heartbeat"))?;
        Ok(())
    }
}

/// The replay's status publisher (history 1: a late launcher gets the last one).
pub struct StatusPublisher {
    status: Publisher<ipc::Service, ReplayStatus, ()>,
}

impl StatusPublisher {
    /// A publisher on the run's status service.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        Ok(Self {
            status: publisher(transport.status_service(), "status publisher")?,
        })
    }

    /// Publishes the counters (its `format_version` is set here).
    pub fn publish(&self, status: ReplayStatus) -> Result<()> {
        let s = ReplayStatus {
            format_version: FORMAT_VERSION,
            ..status
        };
        self.status.send_copy(s).map_err(ice("send status"))?;
        Ok(())
    }
}

/// A subscriber to the actors' finished episodes (the launcher logs them, the learner smooths
/// their returns).
pub struct EpisodeSubscriber {
    metrics: Subscriber<ipc::Service, EpisodeReport, ()>,
    actors: usize,
    rejects: RejectLog,
}

impl EpisodeSubscriber {
    /// Subscribes to the run's episode metrics.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        Ok(Self {
            metrics: subscriber(transport.metrics_service(), "metrics subscriber")?,
            actors: transport.actors(),
            rejects: RejectLog::new("episode metrics"),
        })
    }

    /// Episode metrics received since the last call; malformed ones are counted and skipped.
    pub fn episodes(&mut self) -> Result<Vec<EpisodeReport>> {
        let mut out = Vec::new();
        while let Some(s) = self.metrics.receive().map_err(ice("receive metrics"))? {
            let m = read_once(s.payload());
            let values = [m.context[0], m.context[1], m.progress, m.episode_return];
            match check(m.format_version, m.actor_id, self.actors)
                .and_then(|()| super::wire::check_finite(&values))
                .and_then(|()| check_flags(&[m.a2a, m.wall_crash, m.by_policy]))
            {
                Ok(()) => out.push(m),
                Err(e) => self.rejects.reject(&e),
            }
        }
        Ok(out)
    }

    /// Messages rejected as malformed.
    pub fn rejected(&self) -> u64 {
        self.rejects.count()
    }
}

/// The launcher's view: episode metrics, heartbeats and replay status, validated.
pub struct TelemetrySubscriber {
    episodes: EpisodeSubscriber,
    heartbeat: Subscriber<ipc::Service, Heartbeat, ()>,
    status: Subscriber<ipc::Service, ReplayStatus, ()>,
    actors: usize,
    rejects: RejectLog,
}

impl TelemetrySubscriber {
    /// Subscribes to the run's telemetry.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        Ok(Self {
            episodes: EpisodeSubscriber::new(transport)?,
            heartbeat: subscriber(transport.heartbeat_service(), "heartbeat subscriber")?,
            status: subscriber(transport.status_service(), "status subscriber")?,
            actors: transport.actors(),
            rejects: RejectLog::new("telemetry"),
        })
    }

    /// Episode metrics received since the last call; malformed ones are counted and skipped.
    pub fn episodes(&mut self) -> Result<Vec<EpisodeReport>> {
        self.episodes.episodes()
    }

    /// Heartbeats received since the last call.
    pub fn heartbeats(&mut self) -> Result<Vec<Heartbeat>> {
        let mut out = Vec::new();
        while let Some(s) = self.heartbeat.receive().map_err(ice("receive heartbeat"))? {
            let b = read_once(s.payload());
            match check(b.format_version, b.actor_id, self.actors) {
                Ok(()) => out.push(b),
                Err(e) => self.rejects.reject(&e),
            }
        }
        Ok(out)
    }

    /// The newest replay status received since the last call.
    pub fn replay_status(&mut self) -> Result<Option<ReplayStatus>> {
        let mut newest = None;
        while let Some(s) = self.status.receive().map_err(ice("receive status"))? {
            let st = read_once(s.payload());
            if st.format_version == FORMAT_VERSION {
                newest = Some(st);
            } else {
                self.rejects.reject(&WireError::Version {
                    got: st.format_version,
                });
            }
        }
        Ok(newest)
    }

    /// Messages rejected as malformed.
    pub fn rejected(&self) -> u64 {
        self.rejects.count() + self.episodes.rejected()
    }
}

/// Checks that every flag is 0 or 1.
fn check_flags(flags: &[u32]) -> Result<(), WireError> {
    match flags.iter().position(|&f| f > 1) {
        Some(index) => Err(WireError::Value {
            index,
            value: flags[index] as f32,
        }),
        None => Ok(()),
    }
}

fn check(version: u32, actor_id: u32, actors: usize) -> Result<(), WireError> {
    if version != FORMAT_VERSION {
        return Err(WireError::Version { got: version });
    }
    if actor_id as usize >= actors {
        return Err(WireError::UnknownActor {
            got: actor_id,
            actors,
        });
    }
    Ok(())
}
