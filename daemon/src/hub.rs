//! The model hub: the daemon's model (`texel::model`), the encoded frames a newcomer
//! needs to rebuild it, and a bounded queue per connected client.
//!
//! Publishing never waits: a frame is encoded once, then offered to every client
//! queue with `try_send`. A client whose queue is full is cut off from live updates
//! and told to resynchronise: its connection task drops what is queued and sends a
//! fresh snapshot (or, by policy or after too many resyncs, disconnects it). So a
//! slow viewer never stalls ingest or the other viewers, and no queue grows without
//! bound. Queued frames are shared (`Bytes`), so a queue costs references, not copies.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use bytes::Bytes;
use texel::Pose;
use texel::model::{Model, ModelError, ModelEvent, ModelScan, ScanId, ScanListing};
use texel::wire::{Message, WireError};
use tokio::sync::mpsc;

use texel::TexelScan;

/// One client's live feed.
pub struct Subscription {
    pub client_id: u64,
    /// The frames that rebuild the model as it was when subscribing: `ModelReset`,
    /// one `ScanListed` per served scan (with its current pose), `SnapshotComplete`;
    /// the client fetches the data it needs by id.
    pub snapshot: Vec<Bytes>,
    /// Live frames after the snapshot.
    pub live: mpsc::Receiver<Bytes>,
    /// Set when the hub cut this client off because its queue overflowed.
    pub lagged: Arc<AtomicBool>,
}

struct ClientSlot {
    id: u64,
    tx: mpsc::Sender<Bytes>,
    lagged: Arc<AtomicBool>,
}

struct Inner {
    model: Model,
    /// The `ScanAdded` frame of each scan as first published.
    scan_frames: Vec<Bytes>,
    /// The `PoseRevised` frame of the latest revision of each scan, if any.
    revision_frames: Vec<Option<Bytes>>,
    clients: Vec<ClientSlot>,
    /// Scans withdrawn from the served model, kept to be listed again.
    withdrawn: std::collections::BTreeMap<ScanId, texel::model::ModelScan>,
    next_client_id: u64,
    /// Set once the hub is closed: the reason clients are told.
    closed: Option<String>,
}

/// Why publishing failed.
#[derive(Debug, thiserror::Error)]
pub enum HubError {
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error("the hub is closed")]
    Closed,
}

/// The shared model and its subscribers.
pub struct Hub {
    inner: Mutex<Inner>,
    client_queue: usize,
}

impl Hub {
    pub fn new(client_queue: usize) -> Arc<Self> {
        Arc::new(Self {
            inner: Mutex::new(Inner {
                model: Model::new(),
                scan_frames: Vec::new(),
                revision_frames: Vec::new(),
                clients: Vec::new(),
                withdrawn: std::collections::BTreeMap::new(),
                next_client_id: 0,
                closed: None,
            }),
            client_queue: client_queue.max(1),
        })
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Offers a frame to every client; cuts off those whose queues are full.
    fn broadcast(inner: &mut Inner, frame: &Bytes) {
        inner
            .clients
            .retain(|c| match c.tx.try_send(frame.clone()) {
                Ok(()) => true,
                Err(mpsc::error::TrySendError::Full(_)) => {
                    c.lagged.store(true, Ordering::Release);
                    false
                }
                Err(mpsc::error::TrySendError::Closed(_)) => false,
            });
    }

    /// Adds a scan, already encoded as a `ScanAdded` frame with id `id`.
    pub fn add_scan(
        &self,
        id: ScanId,
        scan: Arc<TexelScan>,
        world_from_scan: Pose,
        frame: Bytes,
    ) -> Result<(), HubError> {
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        inner.model.apply(ModelEvent::ScanAdded {
            id,
            scan,
            world_from_scan,
        })?;
        inner.scan_frames.push(frame.clone());
        inner.revision_frames.push(None);
        Self::broadcast(&mut inner, &frame);
        Ok(())
    }

    /// Revises a scan's pose.
    pub fn revise_pose(&self, id: ScanId, world_from_scan: Pose) -> Result<(), HubError> {
        let frame = Bytes::from(
            Message::PoseRevised {
                id,
                world_from_scan,
            }
            .encode()?,
        );
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        inner.model.apply(ModelEvent::PoseRevised {
            id,
            world_from_scan,
        })?;
        if let Some(slot) = usize::try_from(id)
            .ok()
            .and_then(|i| inner.revision_frames.get_mut(i))
        {
            *slot = Some(frame.clone());
        }
        Self::broadcast(&mut inner, &frame);
        Ok(())
    }

    /// Offers a status frame; a client with a full queue simply misses it (statuses
    /// are periodic and superseded, so missing one is not a reason to resync).
    pub fn publish_status(&self, frame: &Bytes) {
        let inner = self.lock();
        for c in &inner.clients {
            let _ = c.tx.try_send(frame.clone());
        }
    }

    /// Subscribes a client: the snapshot and the live queue start at the same point,
    /// under one lock, so nothing is missed or seen twice.
    pub fn subscribe(&self) -> Result<Subscription, HubError> {
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        let scan_count = inner.model.len() as u64;
        let mut snapshot = Vec::with_capacity(2 + inner.model.len());
        snapshot.push(Bytes::from(Message::ModelReset { scan_count }.encode()?));
        for frame in Self::listings(&inner) {
            snapshot.push(frame?);
        }
        snapshot.push(Bytes::from(
            Message::SnapshotComplete { scan_count }.encode()?,
        ));
        let (tx, live) = mpsc::channel(self.client_queue);
        let lagged = Arc::new(AtomicBool::new(false));
        let client_id = inner.next_client_id;
        inner.next_client_id += 1;
        inner.clients.push(ClientSlot {
            id: client_id,
            tx,
            lagged: Arc::clone(&lagged),
        });
        Ok(Subscription {
            client_id,
            snapshot,
            live,
            lagged,
        })
    }

    /// Stops a client's feed (it disconnected).
    pub fn unsubscribe(&self, client_id: u64) {
        self.lock().clients.retain(|c| c.id != client_id);
    }

    /// Closes the hub: every live feed ends, and clients are told `reason`.
    pub fn close(&self, reason: &str) {
        let mut inner = self.lock();
        inner.closed = Some(reason.to_string());
        inner.clients.clear();
    }

    /// The reason the hub was closed, if it was.
    pub fn closed_reason(&self) -> Option<String> {
        self.lock().closed.clone()
    }

    /// A copy of the model (scans are shared, not copied).
    pub fn model(&self) -> Model {
        self.lock().model.clone()
    }

    pub fn scan_count(&self) -> usize {
        self.lock().model.len()
    }

    /// Bytes held by the model's scans and their encoded frames.
    pub fn memory_bytes(&self) -> (usize, usize) {
        let inner = self.lock();
        let scans = inner
            .model
            .scans()
            .iter()
            .filter_map(|s| s.scan.as_ref().map(|scan| scan.heap_bytes()))
            .sum();
        let frames = inner.scan_frames.iter().map(Bytes::len).sum::<usize>()
            + inner
                .revision_frames
                .iter()
                .flatten()
                .map(Bytes::len)
                .sum::<usize>();
        (scans, frames)
    }
}

// Fetching scans by id (protocol version 2): listings, withdrawals and the two steps
// of answering a request.

/// Why a requested scan cannot be sent; the Display is the reason the viewer is told
/// in `ScanUnavailable`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FetchError {
    #[error("scan {0} is not in the served model")]
    Unknown(ScanId),
    #[error("scan {0} was withdrawn from the served model")]
    Withdrawn(ScanId),
    #[error("scan {id} cannot be read from the store: {message}")]
    Store { id: ScanId, message: String },
    #[error("the hub is closed")]
    Closed,
}

impl Hub {
    /// A `ScanListed` frame per served scan, by id, each with its current pose.
    fn listings(inner: &Inner) -> impl Iterator<Item = Result<Bytes, HubError>> + '_ {
        inner
            .model
            .scans()
            .iter()
            .map(|s| Self::listing_frame(inner, s))
    }

    /// A scan's `ScanListed` frame (its listing from its data and frame size).
    fn listing_frame(inner: &Inner, s: &ModelScan) -> Result<Bytes, HubError> {
        let encoded_bytes = usize::try_from(s.id)
            .ok()
            .and_then(|i| inner.scan_frames.get(i))
            .map_or(0, |f| f.len() as u64);
        // The model listed the scan from its data when it was added
        // (`ScanListing::of_scan(scan, 0, 0.0)`): only the frame's size is new.
        let listing = ScanListing {
            encoded_bytes,
            ..s.listing
        };
        let message = Message::ScanListed {
            id: s.id,
            listing,
            world_from_scan: s.world_from_scan,
        };
        Ok(Bytes::from(message.encode()?))
    }

    fn unavailable(inner: &Inner, id: ScanId) -> FetchError {
        if inner.closed.is_some() {
            FetchError::Closed
        } else if inner.withdrawn.contains_key(&id) {
            FetchError::Withdrawn(id)
        } else {
            FetchError::Unknown(id)
        }
    }

    /// The `ScanAdded` frame of a served scan, as first published. Blocking (a store
    /// may read it from disk): call it off the async threads.
    pub fn fetch_scan(&self, id: ScanId) -> Result<Bytes, FetchError> {
        let inner = self.lock();
        if inner.closed.is_none() && inner.model.get(id).is_some() {
            let frame = usize::try_from(id)
                .ok()
                .and_then(|i| inner.scan_frames.get(i));
            if let Some(frame) = frame {
                return Ok(frame.clone());
            }
        }
        Err(Self::unavailable(&inner, id))
    }

    /// The frames that answer a request with `frame` (from [`Self::fetch_scan`]), to
    /// be written at once by the task that writes the live frames: the scan must
    /// still be served, and a `PoseRevised` with its current pose follows the frame
    /// if it was revised. Checked under the hub lock, so every live frame queued
    /// after this call is newer.
    pub fn finish_fetch(&self, id: ScanId, frame: Bytes) -> Result<Vec<Bytes>, FetchError> {
        let inner = self.lock();
        if inner.closed.is_some() || inner.model.get(id).is_none() {
            return Err(Self::unavailable(&inner, id));
        }
        let revision = usize::try_from(id)
            .ok()
            .and_then(|i| inner.revision_frames.get(i))
            .and_then(Option::clone);
        Ok(std::iter::once(frame).chain(revision).collect())
    }

    /// Withdraws a scan from the served model and tells every client.
    pub fn withdraw(&self, id: ScanId) -> Result<(), HubError> {
        let frame = Bytes::from(Message::ScanWithdrawn { id }.encode()?);
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        let Some(scan) = inner.model.get(id).cloned() else {
            return Err(ModelError::UnknownScan {
                id,
                what: "withdrawal",
            }
            .into());
        };
        inner.model.apply(ModelEvent::ScanWithdrawn { id })?;
        inner.withdrawn.insert(id, scan);
        Self::broadcast(&mut inner, &frame);
        Ok(())
    }

    /// Serves a withdrawn scan again and lists it to every client.
    pub fn relist(&self, id: ScanId) -> Result<(), HubError> {
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        let Some(scan) = inner.withdrawn.remove(&id) else {
            return Err(ModelError::UnknownScan {
                id,
                what: "relisting",
            }
            .into());
        };
        let frame = Self::listing_frame(&inner, &scan)?;
        if let Some(data) = scan.scan {
            inner.model.apply(ModelEvent::ScanAdded {
                id,
                scan: data,
                world_from_scan: scan.world_from_scan,
            })?;
        }
        Self::broadcast(&mut inner, &frame);
        Ok(())
    }
}
