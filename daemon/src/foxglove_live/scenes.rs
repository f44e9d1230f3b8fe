//! The served model and the status for Foxglove: a hub subscriber (like a viewer, with
//! the hub's own bounded queue: publishing never waits for it, and a subscriber that
//! falls behind is cut off and resynchronised from a fresh snapshot) whose frames a
//! forwarding task hands to the scene thread, which keeps every served scan's pose
//! and offers
//!
//! - `/texel/scan`: a `foxglove.SceneUpdate` per change: a new or restored scan is an
//!   entity with its model (`model.rs`), a revision the same entity again at its new
//!   pose (the same glTF bytes, so Foxglove reuses the model it loaded), a withdrawn
//!   scan a deletion. Models are built only while someone subscribes to the topic,
//!   and a new subscriber is sent the whole served model.
//! - `/texel/status`: each periodic status as JSON, with what the Foxglove server
//!   dropped (`foxglove`).
//!
//! Changes that arrive together are applied together before anything is sent, so a
//! scan revised five times while the thread was busy is sent once, at its last pose.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use bytes::Bytes;
use foxglove::SinkId;
use foxglove::messages::{SceneEntity, SceneEntityDeletion, SceneUpdate};
use texel::Pose;
use texel::model::ScanId;
use texel::wire::{Limits, Message, Status, decode_frame};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use super::LiveCounters;
use super::channels::Channels;
use super::model::{deletion, entity, scan_model};
use crate::hub::Hub;
use crate::pipeline::tap::TapCounters;

/// The hub protocol version the subscriber speaks: scans and poses, no tiles, no
/// exposures.
const HUB_VERSION: u16 = 2;

/// Inputs applied together at most, before the scene thread sends what changed.
const BATCH: usize = 64;

/// What the scene thread is handed.
pub enum Input {
    /// A fresh snapshot (the first, or after a resynchronisation).
    Snapshot(Vec<Bytes>),
    /// A live frame of the hub.
    Frame(Bytes),
    /// A new subscriber of `/texel/scan`: send it the whole served model.
    Joined(SinkId),
}

/// Subscribes to the hub and forwards its frames, and the new `/texel/scan`
/// subscribers, to the scene thread; resubscribes when the hub cut it off for being
/// slow. Ends when the hub closes, the scene thread ends or `stop` is cancelled.
pub async fn forward(
    hub: Arc<Hub>,
    tx: mpsc::Sender<Input>,
    mut joins: mpsc::Receiver<SinkId>,
    stop: CancellationToken,
    counters: Arc<LiveCounters>,
) {
    let Ok(mut sub) = hub.subscribe_version(HUB_VERSION) else {
        return;
    };
    let snapshot = std::mem::take(&mut sub.snapshot);
    if tx.send(Input::Snapshot(snapshot)).await.is_ok() {
        loop {
            let input = tokio::select! {
                biased;
                frame = sub.live.recv() => match frame {
                    Some(frame) => Input::Frame(frame),
                    None if sub.lagged.load(Ordering::Acquire) && hub.closed_reason().is_none() => {
                        counters.resyncs.fetch_add(1, Ordering::Relaxed);
                        let Ok(again) = hub.subscribe_version(HUB_VERSION) else {
                            break;
                        };
                        hub.unsubscribe(sub.client_id);
                        sub = again;
                        Input::Snapshot(std::mem::take(&mut sub.snapshot))
                    }
                    None => break,
                },
                Some(sink) = joins.recv() => Input::Joined(sink),
                () = stop.cancelled() => break,
            };
            if tx.send(input).await.is_err() {
                break;
            }
        }
    }
    hub.unsubscribe(sub.client_id);
}

/// A served scan: when it was taken and where it is.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Served {
    timestamp_ns: u64,
    world_from_scan: Pose,
}

/// What a batch of inputs changed.
#[derive(Default)]
struct Batch {
    /// Scans to send again, with their frame when it came with the change.
    dirty: BTreeMap<ScanId, Option<Bytes>>,
    /// Scans that left the served model, and their timestamps.
    withdrawn: Vec<(ScanId, u64)>,
    joined: Vec<SinkId>,
    status: Option<Box<Status>>,
}

/// The scene thread's state.
pub struct Scenes {
    pub hub: Arc<Hub>,
    pub channels: Arc<Channels>,
    pub counters: Arc<LiveCounters>,
    pub tap: Arc<TapCounters>,
    served: BTreeMap<ScanId, Served>,
}

fn decode(frame: &[u8]) -> Option<Message> {
    match decode_frame(frame, &Limits::FROM_SERVER) {
        Ok(Some((message, _))) => Some(message),
        Ok(None) => None,
        Err(e) => {
            tracing::warn!("foxglove: a hub frame does not decode: {e}");
            None
        }
    }
}

impl Scenes {
    pub fn new(
        hub: Arc<Hub>,
        channels: Arc<Channels>,
        counters: Arc<LiveCounters>,
        tap: Arc<TapCounters>,
    ) -> Self {
        Self {
            hub,
            channels,
            counters,
            tap,
            served: BTreeMap::new(),
        }
    }

    /// Runs until the forwarder ends (blocking: a thread of its own).
    pub fn run(mut self, mut rx: mpsc::Receiver<Input>) {
        while let Some(first) = rx.blocking_recv() {
            let mut batch = Batch::default();
            self.apply(first, &mut batch);
            for _ in 1..BATCH {
                match rx.try_recv() {
                    Ok(next) => self.apply(next, &mut batch),
                    Err(_) => break,
                }
            }
            self.send(batch);
        }
    }

    fn apply(&mut self, input: Input, batch: &mut Batch) {
        match input {
            Input::Snapshot(frames) => self.resync(&frames, batch),
            Input::Joined(sink) => batch.joined.push(sink),
            Input::Frame(frame) => match decode(&frame) {
                Some(Message::ScanAdded(wire)) => {
                    let served = Served {
                        timestamp_ns: wire.timestamp_ns,
                        world_from_scan: wire.world_from_scan,
                    };
                    self.served.insert(wire.id, served);
                    batch.dirty.insert(wire.id, Some(frame));
                }
                Some(Message::ScanListed {
                    id,
                    listing,
                    world_from_scan,
                }) => {
                    let served = Served {
                        timestamp_ns: listing.timestamp_ns,
                        world_from_scan,
                    };
                    self.served.insert(id, served);
                    batch.dirty.entry(id).or_insert(None);
                }
                Some(Message::PoseRevised {
                    id,
                    world_from_scan,
                }) => {
                    if let Some(s) = self.served.get_mut(&id) {
                        s.world_from_scan = world_from_scan;
                        batch.dirty.entry(id).or_insert(None);
                    }
                }
                Some(Message::ScanWithdrawn { id }) => {
                    batch.dirty.remove(&id);
                    if let Some(s) = self.served.remove(&id) {
                        batch.withdrawn.push((id, s.timestamp_ns));
                    }
                }
                Some(Message::Status(status)) => batch.status = Some(status),
                _ => {}
            },
        }
    }

    /// Takes a fresh snapshot as the served model: what left it is withdrawn, what
    /// is new or moved is sent again.
    fn resync(&mut self, frames: &[Bytes], batch: &mut Batch) {
        let mut now = BTreeMap::new();
        for frame in frames {
            if let Some(Message::ScanListed {
                id,
                listing,
                world_from_scan,
            }) = decode(frame)
            {
                let served = Served {
                    timestamp_ns: listing.timestamp_ns,
                    world_from_scan,
                };
                now.insert(id, served);
            }
        }
        for (&id, s) in &self.served {
            if !now.contains_key(&id) {
                batch.dirty.remove(&id);
                batch.withdrawn.push((id, s.timestamp_ns));
            }
        }
        for (&id, s) in &now {
            if self.served.get(&id) != Some(s) {
                batch.dirty.entry(id).or_insert(None);
            }
        }
        self.served = now;
    }

    fn send(&self, batch: Batch) {
        let channels = &self.channels;
        if channels.scan.has_sinks() {
            for (id, frame) in batch.dirty {
                if let Some(entity) = self.entity(id, frame) {
                    channels.scan.log(&one(entity));
                }
            }
            // Last, so a subscriber sees every change that came before a withdrawal
            // before it.
            if !batch.withdrawn.is_empty() {
                let deletions: Vec<SceneEntityDeletion> = batch
                    .withdrawn
                    .iter()
                    // Entities stamped before this are deleted: the scan's own time.
                    .map(|&(id, t)| deletion(id, t.saturating_add(1)))
                    .collect();
                channels.scan.log(&SceneUpdate {
                    deletions,
                    entities: Vec::new(),
                });
            }
        }
        for sink in batch.joined {
            let ids: Vec<ScanId> = self.served.keys().copied().collect();
            for id in ids {
                if let Some(entity) = self.entity(id, None) {
                    channels.scan.log_to_sink(&one(entity), Some(sink));
                }
            }
        }
        if let Some(status) = batch.status.filter(|_| channels.status.has_sinks()) {
            self.send_status(&status);
        }
    }

    /// Scan `id`'s entity at its current pose: its model built from `frame`, else
    /// from the hub's frame (read back from the store when need be). Nothing is
    /// kept: memory holds one model at a time, whatever the model's size.
    fn entity(&self, id: ScanId, frame: Option<Bytes>) -> Option<SceneEntity> {
        let served = self.served.get(&id)?;
        let started = Instant::now();
        let frame = match frame {
            Some(frame) => frame,
            None => match self.hub.fetch_scan(id) {
                Ok(frame) => frame,
                Err(e) => {
                    // Withdrawn meanwhile (its withdrawal follows), or unreadable.
                    tracing::debug!("foxglove: scan {id} not sent: {e}");
                    return None;
                }
            },
        };
        match scan_model(id, &frame) {
            Ok(model) => {
                let c = &self.counters;
                c.scan_models.fetch_add(1, Ordering::Relaxed);
                let micros = u64::try_from(started.elapsed().as_micros()).unwrap_or(u64::MAX);
                c.scan_model_micros.fetch_add(micros, Ordering::Relaxed);
                c.scan_model_bytes
                    .fetch_add(model.glb.len() as u64, Ordering::Relaxed);
                Some(entity(&model, &served.world_from_scan))
            }
            Err(e) => {
                if self
                    .counters
                    .scan_model_errors
                    .fetch_add(1, Ordering::Relaxed)
                    == 0
                {
                    tracing::warn!("foxglove: {e} (counted as scan_model_errors)");
                }
                None
            }
        }
    }

    fn send_status(&self, status: &Status) {
        let mut json = match serde_json::to_value(status) {
            Ok(json) => json,
            Err(e) => {
                tracing::debug!("foxglove: status not sent: {e}");
                return;
            }
        };
        if let Some(object) = json.as_object_mut() {
            object.insert("foxglove".into(), self.counters.to_json(&self.tap));
        }
        match serde_json::to_vec(&json) {
            Ok(bytes) => self.channels.status.log(&bytes),
            Err(e) => tracing::debug!("foxglove: status not sent: {e}"),
        }
    }
}

fn one(entity: SceneEntity) -> SceneUpdate {
    SceneUpdate {
        deletions: Vec::new(),
        entities: vec![entity],
    }
}
