//! The model hub: the served model (every scan's listing and current pose, which
//! scans are retired, which encoded frames are in memory and which only in the
//! on-disk store), its memory budget, and a bounded queue per connected client.
//!
//! Publishing never waits: a frame is encoded once, then offered to every client
//! queue with `try_send`. A client whose queue is full is cut off from live updates
//! and told to resynchronise (see `server`). So a slow viewer never stalls ingest or
//! the other viewers, and no queue grows without bound. Queued frames are shared
//! (`Bytes`), so a queue costs references, not copies.
//!
//! Memory: the hub holds no scans, only their encoded `ScanAdded` frames, and only
//! within `memory_budget_bytes`: every frame is in the store (written by the encode
//! stage before it reaches the hub), so going over the budget drops the frames
//! requested least recently; a request reads them back. Retired scans (redundant,
//! `texel::coverage`) leave the served model and memory at once, and come back as a
//! listing when a pose revision makes them useful again. With a shelf (`shelf.rs`)
//! what the hub and retirement know of retired scans waits on disk too, so memory
//! holds the served model whatever the session's length.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use bytes::Bytes;
use texel::Pose;
use texel::coverage::{Changes, CoverageConfig, Retirement, ScanCoverage, Shelf};
use texel::model::{ScanId, ScanListing};
use texel::tile::TileId;
use texel::wire::{Message, ModelStatus, WireError};
use tokio::sync::mpsc;

mod radiance;
mod tiles;

pub use tiles::{TileChange, TileCounts};

use crate::serve_order::{REGION_M, Served, coarse_first};
use crate::shelf::{DiskShelf, ShelfFiles, ShelfTable, ShelvedListing};
use crate::store::{Store, StoreError};

/// One client's live feed.
pub struct Subscription {
    pub client_id: u64,
    /// What a newcomer learns first: `ModelReset`, one `ScanListed` per served scan
    /// in coarse-first order, `SnapshotComplete`. It then asks for the scans' data.
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
    /// Speaks protocol version 3: is sent the level-of-detail tree's tiles.
    tiles: bool,
    /// Speaks protocol version 4: is sent exposures and the response curve.
    radiance: bool,
}

/// What the hub knows of one scan.
struct Entry {
    listing: ScanListing,
    world_from_scan: Pose,
    /// Moved since its `ScanAdded` frame was made.
    revised: bool,
    retired: bool,
    /// The encoded `ScanAdded` frame, when in memory.
    frame: Option<Bytes>,
    /// Whether the store holds the frame (so it may be dropped from memory).
    stored: bool,
    /// When it was last added or requested (an LRU tick).
    used: u64,
    /// Also on the shelf (a retired scan loaded back for a change).
    on_shelf: bool,
}

/// How the hub keeps its model.
#[derive(Clone, Default)]
pub struct ModelOptions {
    /// Frames held in memory beyond this are dropped, least recently requested first
    /// (only those the store holds). `u64::MAX`: no budget.
    pub memory_budget_bytes: u64,
    /// Where frames beyond the budget (and retired ones) live.
    pub store: Option<Arc<Store>>,
    /// Retirement of redundant scans; `None` (or disabled) keeps every scan served.
    pub coverage: Option<CoverageConfig>,
    /// Where retired scans' entries wait (the hub's and retirement's); `None` keeps
    /// them in memory.
    pub shelf: Option<Arc<ShelfFiles>>,
    /// Tile frames held in memory beyond this are dropped to `tile_store` (least
    /// recently used first) and read back on request.
    pub tile_memory_budget_bytes: u64,
    /// Where tile frames live beyond the budget, keyed by revision.
    pub tile_store: Option<Arc<Store>>,
}

struct Inner {
    /// Served scans, and retired ones not on the shelf.
    entries: BTreeMap<ScanId, Entry>,
    shelf: Option<DiskShelf>,
    /// Retired scans whose entry is on the shelf.
    shelved: u64,
    retirement: Option<Retirement>,
    /// In-memory frames by last use: the eviction order.
    lru: BTreeMap<u64, ScanId>,
    tick: u64,
    frame_bytes: u64,
    /// The index's bytes (entries, retirement's signatures and offers), refreshed
    /// every `INDEX_REFRESH` scans: walking retirement's index costs a pass over it.
    index_bytes: u64,
    served: u64,
    store_reads: u64,
    store_errors: u64,
    retirement_work: RetirementWork,
    clients: Vec<ClientSlot>,
    next_client_id: u64,
    tiles: tiles::TileTable,
    radiance: radiance::Radiance,
    /// Set once the hub is closed: the reason clients are told.
    closed: Option<String>,
}

/// Why publishing failed.
#[derive(Debug, thiserror::Error)]
pub enum HubError {
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error("scan {0} was added twice")]
    Duplicate(ScanId),
    #[error("no scan {0} (or not in the state the change needs)")]
    UnknownScan(ScanId),
    #[error("the hub is closed")]
    Closed,
}

/// Why a request for a scan cannot be answered; the text is what the client is told.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    #[error("no scan {0} in this session")]
    Unknown(ScanId),
    #[error("scan {0} is retired (redundant): it left the served model")]
    Withdrawn(ScanId),
    #[error("scan {id} cannot be read back: {source}")]
    Store { id: ScanId, source: StoreError },
    #[error("scan {0} is neither in memory nor in a store")]
    Lost(ScanId),
    #[error("tile {} is not in the served tree", .0.path())]
    UnknownTile(TileId),
    #[error("tile {} cannot be read back: {source}", .id.path())]
    TileStore { id: TileId, source: StoreError },
    #[error("cannot encode scan {id}'s pose: {source}")]
    Wire { id: ScanId, source: WireError },
    #[error("{what} cannot be read: {message}")]
    Failed { what: String, message: String },
    #[error("the hub is closed")]
    Closed,
}

/// Time the hub spent in retirement's `add` and `revise` calls: the work a scan's
/// arrival or a pose revision costs the publishing thread.
#[derive(Debug, Clone, Copy, Default)]
pub struct RetirementWork {
    pub calls: u64,
    pub total_s: f64,
    pub max_s: f64,
}

impl RetirementWork {
    fn note(&mut self, took: std::time::Duration) {
        let s = took.as_secs_f64();
        self.calls += 1;
        self.total_s += s;
        self.max_s = self.max_s.max(s);
    }

    /// Mean seconds a call (0 before the first).
    pub fn mean_s(&self) -> f64 {
        if self.calls == 0 {
            0.0
        } else {
            self.total_s / self.calls as f64
        }
    }
}

/// Scans between refreshes of the index's measured size.
const INDEX_REFRESH: usize = 256;

/// Bytes of one entry beyond its struct (the map's node overhead).
const ENTRY_OVERHEAD_BYTES: usize = 48;

/// The shared model and its subscribers.
pub struct Hub {
    inner: Mutex<Inner>,
    client_queue: usize,
    options: ModelOptions,
}

impl Hub {
    /// A hub that keeps every frame in memory and retires nothing.
    pub fn new(client_queue: usize) -> Arc<Self> {
        Self::with_model(
            client_queue,
            ModelOptions {
                memory_budget_bytes: u64::MAX,
                ..ModelOptions::default()
            },
        )
    }

    pub fn with_model(client_queue: usize, options: ModelOptions) -> Arc<Self> {
        let retirement = options.coverage.filter(|c| c.enabled).map(|c| {
            // Retired scans' signatures are read back from their frames when needed
            // (a pose revision), so the index holds offers and links alone for them.
            let mut r = Retirement::new(c);
            r.shed_retired_signatures(true);
            if let Some(db) = &options.shelf {
                r.set_shelf(
                    Box::new(DiskShelf::new(Arc::clone(db), ShelfTable::Retirement)),
                    Box::new(DiskShelf::new(Arc::clone(db), ShelfTable::Links)),
                );
            }
            r
        });
        let shelf = options
            .shelf
            .as_ref()
            .map(|db| DiskShelf::new(Arc::clone(db), ShelfTable::Hub));
        Arc::new(Self {
            inner: Mutex::new(Inner {
                entries: BTreeMap::new(),
                shelf,
                shelved: 0,
                retirement,
                lru: BTreeMap::new(),
                tick: 0,
                frame_bytes: 0,
                index_bytes: 0,
                served: 0,
                store_reads: 0,
                store_errors: 0,
                retirement_work: RetirementWork::default(),
                clients: Vec::new(),
                next_client_id: 0,
                tiles: tiles::TileTable::default(),
                radiance: radiance::Radiance::default(),
                closed: None,
            }),
            client_queue: client_queue.max(1),
            options,
        })
    }

    /// The store frames are written to, if any (the encode stage writes there first).
    pub fn store(&self) -> Option<&Arc<Store>> {
        self.options.store.as_ref()
    }

    /// Whether new scans are tested for redundancy (so the encode stage computes
    /// their coverage).
    pub fn retires(&self) -> bool {
        self.lock().retirement.is_some()
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Offers a frame to every client; cuts off those whose queues are full.
    fn broadcast(inner: &mut Inner, frame: &Bytes) {
        Self::broadcast_where(inner, frame, |_| true);
    }

    /// Offers a frame to the clients `to` picks; cuts off those whose queues are full.
    fn broadcast_where(inner: &mut Inner, frame: &Bytes, to: impl Fn(&ClientSlot) -> bool) {
        inner.clients.retain(|c| {
            if !to(c) {
                return true;
            }
            match c.tx.try_send(frame.clone()) {
                Ok(()) => true,
                Err(mpsc::error::TrySendError::Full(_)) => {
                    c.lagged.store(true, Ordering::Release);
                    false
                }
                Err(mpsc::error::TrySendError::Closed(_)) => false,
            }
        });
    }

    /// Adds a scan, encoded as a `ScanAdded` frame with id `id` (already in the store
    /// when `stored`). A scan retirement finds redundant is kept out of the served
    /// model at once; scans it makes redundant are withdrawn.
    pub fn add_scan(
        &self,
        id: ScanId,
        listing: ScanListing,
        world_from_scan: Pose,
        frame: Bytes,
        stored: bool,
        coverage: Option<ScanCoverage>,
    ) -> Result<(), HubError> {
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        if Self::retired_state(&inner, id).is_some() {
            return Err(HubError::Duplicate(id));
        }
        inner.tick += 1;
        let used = inner.tick;
        inner.entries.insert(
            id,
            Entry {
                listing,
                world_from_scan,
                revised: false,
                retired: false,
                frame: None,
                stored,
                used,
                on_shelf: false,
            },
        );
        inner.served += 1;
        let started = std::time::Instant::now();
        let changes = match (inner.retirement.as_mut(), coverage) {
            (Some(r), Some(c)) => r.add(id, c, &world_from_scan),
            _ => Changes::default(),
        };
        inner.retirement_work.note(started.elapsed());
        let retired_now = changes.retired.contains(&id);
        if retired_now {
            inner.served -= 1;
            if let Some(e) = inner.entries.get_mut(&id) {
                e.retired = true;
            }
            if stored {
                Self::shelve(&mut inner, id);
            } else {
                // Without a store a retired frame could never come back: keep it.
                Self::hold_frame(&mut inner, id, frame);
            }
        } else {
            Self::hold_frame(&mut inner, id, frame.clone());
            if let Some(exposure) = inner.radiance.exposure(id).cloned() {
                Self::broadcast_where(&mut inner, &exposure, |c| c.radiance);
            }
            Self::broadcast(&mut inner, &frame);
        }
        self.apply_changes(&mut inner, &changes, Some(id))?;
        if inner.entries.len() % INDEX_REFRESH == 1 {
            inner.index_bytes = Self::measure_index(&inner) as u64;
        }
        self.enforce_budget(&mut inner);
        Ok(())
    }

    /// The index's bytes: entries, and retirement's signatures, offers and links.
    fn measure_index(inner: &Inner) -> usize {
        inner.entries.len() * (std::mem::size_of::<Entry>() + ENTRY_OVERHEAD_BYTES)
            + inner.retirement.as_ref().map_or(0, Retirement::heap_bytes)
            + inner.shelf.as_ref().map_or(0, Shelf::heap_bytes)
    }

    /// Whether scan `id` is known, and if so whether it is retired (`Some(true)`),
    /// in memory or on the shelf.
    fn retired_state(inner: &Inner, id: ScanId) -> Option<bool> {
        if let Some(e) = inner.entries.get(&id) {
            return Some(e.retired);
        }
        let shelf = inner.shelf.as_ref()?;
        match shelf.get(&[id]).into_iter().next()? {
            Ok(found) => found.map(|_| true),
            // Held but unreadable: it is known, and was retired.
            Err(_) => Some(true),
        }
    }

    /// Moves retired scan `id`'s entry to the shelf (its frame is in the store). On a
    /// shelf error the entry stays in memory: nothing is lost.
    fn shelve(inner: &mut Inner, id: ScanId) {
        let Some(shelf) = inner.shelf.as_mut() else {
            return;
        };
        let Some(e) = inner.entries.get(&id) else {
            return;
        };
        if !e.retired || !e.stored || e.frame.is_some() {
            return;
        }
        let bytes = ShelvedListing {
            listing: e.listing,
            world_from_scan: e.world_from_scan,
            revised: e.revised,
        }
        .to_bytes();
        let was_on_shelf = e.on_shelf;
        match shelf.commit(&[(id, bytes)], &[]) {
            Ok(()) => {
                inner.entries.remove(&id);
                if !was_on_shelf {
                    inner.shelved += 1;
                }
            }
            Err(e) => Self::shelf_failed(inner, &e.to_string()),
        }
    }

    /// Brings shelved scan `id`'s entry into memory (it stays on the shelf until it
    /// is served again). False when the shelf does not hold it or cannot give it back.
    fn unshelve(inner: &mut Inner, id: ScanId) -> bool {
        if inner.entries.contains_key(&id) {
            return true;
        }
        let Some(shelf) = inner.shelf.as_ref() else {
            return false;
        };
        let found = match shelf.get(&[id]).into_iter().next() {
            Some(Ok(found)) => found,
            None => None,
            Some(Err(e)) => {
                Self::shelf_failed(inner, &e.to_string());
                return false;
            }
        };
        let Some(bytes) = found else {
            return false;
        };
        match ShelvedListing::from_bytes(&bytes) {
            Ok(s) => {
                inner.tick += 1;
                let used = inner.tick;
                inner.entries.insert(
                    id,
                    Entry {
                        listing: s.listing,
                        world_from_scan: s.world_from_scan,
                        revised: s.revised,
                        retired: true,
                        frame: None,
                        stored: true,
                        used,
                        on_shelf: true,
                    },
                );
                true
            }
            Err(message) => {
                Self::shelf_failed(inner, &format!("scan {id}: {message}"));
                false
            }
        }
    }

    /// Takes scan `id` (served again, in memory) off the shelf.
    fn unshelf_served(inner: &mut Inner, id: ScanId) {
        let Some(shelf) = inner.shelf.as_mut() else {
            return;
        };
        if !inner.entries.get(&id).is_some_and(|e| e.on_shelf) {
            return;
        }
        match shelf.commit(&[], &[id]) {
            Ok(()) => {
                inner.shelved = inner.shelved.saturating_sub(1);
                if let Some(e) = inner.entries.get_mut(&id) {
                    e.on_shelf = false;
                }
            }
            Err(e) => Self::shelf_failed(inner, &e.to_string()),
        }
    }

    fn shelf_failed(inner: &mut Inner, message: &str) {
        inner.store_errors += 1;
        if inner.store_errors == 1 {
            tracing::error!("model shelf: {message}");
        }
    }

    /// Revises a scan's pose (retired scans too: they keep their place in the graph).
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
        Self::unshelve(&mut inner, id);
        let entry = inner
            .entries
            .get_mut(&id)
            .ok_or(HubError::UnknownScan(id))?;
        entry.world_from_scan = world_from_scan;
        entry.revised = true;
        if !entry.retired {
            Self::broadcast(&mut inner, &frame);
        }
        let held = inner.entries.get(&id).and_then(|e| e.frame.clone());
        let store = self.options.store.as_ref();
        let started = std::time::Instant::now();
        let changes = match inner.retirement.as_mut() {
            Some(r) => {
                let config = *r.config();
                r.revise_with(id, &world_from_scan, || {
                    signature_of(id, held, store, &config)
                })
            }
            None => Changes::default(),
        };
        inner.retirement_work.note(started.elapsed());
        self.apply_changes(&mut inner, &changes, None)?;
        Self::shelve(&mut inner, id);
        Ok(())
    }

    /// Takes a scan out of the served model by hand (as retirement would): viewers are
    /// told to forget it, requests for it are refused, it stays in the store.
    pub fn withdraw(&self, id: ScanId) -> Result<(), HubError> {
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        if inner.entries.get(&id).is_none_or(|e| e.retired) {
            return Err(HubError::UnknownScan(id));
        }
        let changes = Changes {
            retired: vec![id],
            restored: Vec::new(),
        };
        self.apply_changes(&mut inner, &changes, None)
    }

    /// A served scan's `ScanListed` frame as a late joiner's snapshot would hold it
    /// (its current pose); `None` when it is not served.
    pub fn listing_frame(&self, id: ScanId) -> Option<Bytes> {
        let inner = self.lock();
        let e = inner.entries.get(&id).filter(|e| !e.retired)?;
        Message::ScanListed {
            id,
            listing: e.listing,
            world_from_scan: e.world_from_scan,
        }
        .encode()
        .ok()
        .map(Bytes::from)
    }

    /// Brings a withdrawn scan back into the served model: viewers are sent its
    /// listing.
    pub fn relist(&self, id: ScanId) -> Result<(), HubError> {
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        if Self::retired_state(&inner, id) != Some(true) {
            return Err(HubError::UnknownScan(id));
        }
        let changes = Changes {
            retired: Vec::new(),
            restored: vec![id],
        };
        self.apply_changes(&mut inner, &changes, None)
    }

    /// Withdraws the scans retirement retired (but `skip`, handled by the caller)
    /// and lists the ones it restored.
    fn apply_changes(
        &self,
        inner: &mut Inner,
        changes: &Changes,
        skip: Option<ScanId>,
    ) -> Result<(), HubError> {
        for &id in changes.retired.iter().filter(|&&id| Some(id) != skip) {
            let Some(e) = inner.entries.get_mut(&id) else {
                continue;
            };
            if e.retired {
                continue;
            }
            e.retired = true;
            if e.stored
                && let Some(f) = e.frame.take()
            {
                let used = e.used;
                inner.frame_bytes -= f.len() as u64;
                inner.lru.remove(&used);
            }
            inner.served -= 1;
            let frame = Bytes::from(Message::ScanWithdrawn { id }.encode()?);
            Self::broadcast(inner, &frame);
            Self::shelve(inner, id);
        }
        for &id in &changes.restored {
            Self::unshelve(inner, id);
            Self::unshelf_served(inner, id);
            let Some(e) = inner.entries.get_mut(&id) else {
                continue;
            };
            if !e.retired {
                continue;
            }
            e.retired = false;
            inner.served += 1;
            let frame = Bytes::from(
                Message::ScanListed {
                    id,
                    listing: e.listing,
                    world_from_scan: e.world_from_scan,
                }
                .encode()?,
            );
            Self::broadcast(inner, &frame);
        }
        Ok(())
    }

    /// Keeps a frame in memory as the most recently used.
    fn hold_frame(inner: &mut Inner, id: ScanId, frame: Bytes) {
        inner.tick += 1;
        let tick = inner.tick;
        let Some(e) = inner.entries.get_mut(&id) else {
            return;
        };
        let old_used = e.used;
        e.used = tick;
        let added = frame.len() as u64;
        if let Some(old) = e.frame.replace(frame) {
            inner.frame_bytes -= old.len() as u64;
            inner.lru.remove(&old_used);
        }
        inner.frame_bytes += added;
        inner.lru.insert(tick, id);
    }

    /// Drops the least recently used stored frames until memory (frames and index)
    /// is within budget.
    fn enforce_budget(&self, inner: &mut Inner) {
        let budget = self
            .options
            .memory_budget_bytes
            .saturating_sub(inner.index_bytes);
        let mut kept = Vec::new();
        while inner.frame_bytes > budget {
            let Some((tick, id)) = inner.lru.pop_first() else {
                break;
            };
            let Some(e) = inner.entries.get_mut(&id) else {
                continue;
            };
            if !e.stored {
                // Not in the store: it cannot leave memory.
                kept.push((tick, id));
                continue;
            }
            if let Some(f) = e.frame.take() {
                inner.frame_bytes -= f.len() as u64;
            }
        }
        inner.lru.extend(kept);
    }

    /// The encoded `ScanAdded` frame of a served scan, from memory or read back from
    /// the store (which blocks: call from a blocking thread). A frame read back is
    /// held in memory again as the most recently requested.
    pub fn fetch_scan(&self, id: ScanId) -> Result<Bytes, FetchError> {
        {
            let mut inner = self.lock();
            if inner.closed.is_some() {
                return Err(FetchError::Closed);
            }
            let Some(e) = inner.entries.get(&id) else {
                return Err(Self::absent(&inner, id));
            };
            if e.retired {
                return Err(FetchError::Withdrawn(id));
            }
            if let Some(frame) = e.frame.clone() {
                Self::hold_frame(&mut inner, id, frame.clone());
                return Ok(frame);
            }
        }
        let store = self.options.store.as_ref().ok_or(FetchError::Lost(id))?;
        let read = store.read(id);
        let mut inner = self.lock();
        match read {
            Ok(frame) => {
                inner.store_reads += 1;
                if inner.entries.get(&id).is_some_and(|e| !e.retired) {
                    Self::hold_frame(&mut inner, id, frame.clone());
                    self.enforce_budget(&mut inner);
                }
                Ok(frame)
            }
            Err(source) => {
                inner.store_errors += 1;
                if inner.store_errors == 1 {
                    tracing::error!("model store: {source}");
                }
                Err(FetchError::Store { id, source })
            }
        }
    }

    /// What to send for a fetched frame, decided at the moment of sending (in the task
    /// that also sends live frames): nothing if the scan left the served model in the
    /// meantime, else the frame and, if it moved since it was encoded, its current pose.
    pub fn finish_fetch(&self, id: ScanId, frame: Bytes) -> Result<Vec<Bytes>, FetchError> {
        self.finish_fetch_for(id, frame, false)
    }

    /// [`Hub::finish_fetch`] for a client that speaks version 4 (`radiance`): the
    /// scan's exposure, when it has one, goes before its data.
    pub fn finish_fetch_for(
        &self,
        id: ScanId,
        frame: Bytes,
        radiance: bool,
    ) -> Result<Vec<Bytes>, FetchError> {
        let inner = self.lock();
        if inner.closed.is_some() {
            return Err(FetchError::Closed);
        }
        let Some(e) = inner.entries.get(&id) else {
            return Err(Self::absent(&inner, id));
        };
        if e.retired {
            return Err(FetchError::Withdrawn(id));
        }
        let mut frames = Vec::with_capacity(3);
        if let Some(exposure) = inner.radiance.exposure(id).filter(|_| radiance) {
            frames.push(exposure.clone());
        }
        frames.push(frame);
        if e.revised {
            let pose = Message::PoseRevised {
                id,
                world_from_scan: e.world_from_scan,
            }
            .encode()
            .map_err(|source| FetchError::Wire { id, source })?;
            frames.push(Bytes::from(pose));
        }
        Ok(frames)
    }

    /// Why scan `id`, not in memory, cannot be fetched: retired (on the shelf) or
    /// never seen.
    fn absent(inner: &Inner, id: ScanId) -> FetchError {
        match Self::retired_state(inner, id) {
            Some(_) => FetchError::Withdrawn(id),
            None => FetchError::Unknown(id),
        }
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
        self.subscribe_version(texel::wire::PROTOCOL_VERSION)
    }

    /// Subscribes a client that is (`tiles`) or is not sent the level-of-detail tree
    /// (protocol version 3 or 2).
    pub fn subscribe_with(&self, tiles: bool) -> Result<Subscription, HubError> {
        self.subscribe_version(if tiles { 3 } else { 2 })
    }

    /// Subscribes a client of protocol `version`: from 3 it is sent the
    /// level-of-detail tree (the snapshot lists the tiles, coarsest first, before the
    /// scans: a late joiner can ask for an overview at once), from 4 the response
    /// curve (in the snapshot) and the scans' exposures.
    pub fn subscribe_version(&self, version: u16) -> Result<Subscription, HubError> {
        let (tiles, radiance) = (version >= 3, version >= 4);
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        let served: Vec<Served<'_>> = inner
            .entries
            .iter()
            .filter(|(_, e)| !e.retired)
            .map(|(&id, e)| Served {
                id,
                listing: &e.listing,
                world_from_scan: &e.world_from_scan,
            })
            .collect();
        let scan_count = served.len() as u64;
        let order = coarse_first(&served, REGION_M);
        let mut snapshot = Vec::with_capacity(order.len() + 2);
        snapshot.push(Bytes::from(Message::ModelReset { scan_count }.encode()?));
        if let Some(response) = inner.radiance.response().filter(|_| radiance) {
            snapshot.push(response.clone());
        }
        if tiles {
            snapshot.extend(Self::tile_snapshot(&inner)?);
        }
        for id in order {
            if let Some(e) = inner.entries.get(&id) {
                snapshot.push(Bytes::from(
                    Message::ScanListed {
                        id,
                        listing: e.listing,
                        world_from_scan: e.world_from_scan,
                    }
                    .encode()?,
                ));
            }
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
            tiles,
            radiance,
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

    /// Every scan added this session (served or retired).
    pub fn scan_count(&self) -> usize {
        let inner = self.lock();
        inner.entries.len() + inner.shelved as usize
    }

    /// Retired scans whose entries are on the shelf, the hub's and retirement's.
    pub fn shelved(&self) -> (u64, u64) {
        let inner = self.lock();
        let retirement = inner.retirement.as_ref().map_or(0, |r| r.shelved() as u64);
        (inner.shelved, retirement)
    }

    /// The store tile data is written to, if any.
    pub fn tile_store(&self) -> Option<&Arc<Store>> {
        self.options.tile_store.as_ref()
    }

    /// Whether scan `id` is in the served model.
    pub fn is_served(&self, id: ScanId) -> bool {
        self.lock().entries.get(&id).is_some_and(|e| !e.retired)
    }

    /// Bytes the model holds in memory: encoded frames, and the index (entries,
    /// coverage signatures).
    pub fn memory_bytes(&self) -> (usize, usize) {
        let inner = self.lock();
        (Self::measure_index(&inner), inner.frame_bytes as usize)
    }

    /// Retirement's decisions so far by cause (`None` without retirement).
    pub fn retirement_counts(&self) -> Option<texel::coverage::RetirementCounts> {
        self.lock().retirement.as_ref().map(Retirement::counts)
    }

    /// Time spent in retirement's calls so far (signature reads included).
    pub fn retirement_work(&self) -> RetirementWork {
        self.lock().retirement_work
    }

    /// The model's part of the status.
    pub fn status(&self) -> ModelStatus {
        let inner = self.lock();
        let (mut in_memory, mut on_disk) = (0u64, inner.shelved);
        for e in inner.entries.values() {
            match (&e.frame, e.retired) {
                (Some(_), false) => in_memory += 1,
                (None, _) => on_disk += 1,
                (Some(_), true) => {}
            }
        }
        let scans = inner.entries.len() as u64 + inner.shelved;
        ModelStatus {
            scans,
            served: inner.served,
            retired: scans - inner.served,
            in_memory,
            on_disk,
            // The index as last measured: walking retirement's index for every status
            // would cost a pass over every scan each second.
            memory_bytes: inner.index_bytes + inner.frame_bytes,
            memory_budget_bytes: self.options.memory_budget_bytes,
            store_bytes: self.options.store.as_ref().map_or(0, |s| s.len_bytes()),
            store_reads: inner.store_reads,
            store_errors: inner.store_errors,
        }
    }
}

/// Scan `id`'s coverage signature, from its frame held in memory or read back from
/// the store (a positional read of one entry). `None`, logged, when neither has it
/// or it does not decode: retirement then serves the scan again.
fn signature_of(
    id: ScanId,
    held: Option<Bytes>,
    store: Option<&Arc<Store>>,
    config: &CoverageConfig,
) -> Option<ScanCoverage> {
    let frame = match (held, store) {
        (Some(frame), _) => frame,
        (None, Some(store)) => match store.read(id) {
            Ok(frame) => frame,
            Err(e) => {
                tracing::warn!("scan {id}: signature not read back: {e}");
                return None;
            }
        },
        (None, None) => return None,
    };
    match texel::wire::decode_frame(&frame, &texel::wire::Limits::FROM_SERVER) {
        Ok(Some((Message::ScanAdded(wire), _))) => {
            // The signature is geometric: the texture stays encoded.
            let (_, scan, _) = wire.into_geometry();
            Some(ScanCoverage::of(&scan, config))
        }
        Ok(_) => {
            tracing::warn!("scan {id}: stored frame is not a whole ScanAdded");
            None
        }
        Err(e) => {
            tracing::warn!("scan {id}: stored frame does not decode: {e}");
            None
        }
    }
}
