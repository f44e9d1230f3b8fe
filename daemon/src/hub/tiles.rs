//! The hub's level-of-detail tree (protocol version 3): every tile's listing and its
//! `TileData` frame, offered to the clients that speak version 3 and served on
//! request like scans.
//!
//! Memory: tile frames are held within `tile_memory_budget_bytes`; beyond it the least
//! recently used ones that the tile store holds are dropped and read back on request,
//! so a city's tree lives on disk like its scans. The store is keyed by revision (a
//! rebuilt tile is a new entry; the old one is garbage in an append-only file that
//! lives as long as the session).

use std::collections::BTreeMap;

use bytes::Bytes;
use texel::tile::{TileId, TileListing};
use texel::wire::Message;

use super::{FetchError, Hub, HubError, Inner};

/// A change the level-of-detail stage publishes.
#[derive(Debug, Clone)]
pub enum TileChange {
    /// A tile built or rebuilt: its listing (with a new revision) and its `TileData`
    /// frame, already in the tile store when `stored`.
    Built {
        id: TileId,
        listing: TileListing,
        frame: Bytes,
        stored: bool,
    },
    /// Same data, new bounds or error (a child changed under it).
    Relisted { id: TileId, listing: TileListing },
    /// The tile holds no surface any more.
    Withdrawn { id: TileId },
}

struct TileEntry {
    listing: TileListing,
    frame: Option<Bytes>,
    stored: bool,
    used: u64,
}

/// The tiles the hub serves.
#[derive(Default)]
pub(super) struct TileTable {
    entries: BTreeMap<TileId, TileEntry>,
    lru: BTreeMap<u64, TileId>,
    frame_bytes: u64,
    store_reads: u64,
    /// Frames of tile data written to clients, and their bytes.
    sent: u64,
    sent_bytes: u64,
}

/// What the tiles cost, for the status.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TileCounts {
    pub tiles: u64,
    /// Mean bytes of a tile's `TileData` frame over the listed tiles.
    pub mean_tile_bytes: f64,
    pub largest_tile_bytes: u64,
    pub memory_bytes: u64,
    pub store_reads: u64,
    pub sent: u64,
    pub sent_bytes: u64,
}

impl TileTable {
    fn hold(&mut self, tick: u64, id: TileId, frame: Bytes) {
        if let Some(e) = self.entries.get_mut(&id) {
            if e.frame.is_none() {
                self.frame_bytes += frame.len() as u64;
            }
            self.lru.remove(&e.used);
            e.used = tick;
            e.frame = Some(frame);
            self.lru.insert(tick, id);
        }
    }

    fn drop_entry(&mut self, id: TileId) {
        if let Some(e) = self.entries.remove(&id) {
            self.lru.remove(&e.used);
            if let Some(f) = e.frame {
                self.frame_bytes = self.frame_bytes.saturating_sub(f.len() as u64);
            }
        }
    }

    /// Drops stored frames, least recently used first, until within `budget`.
    fn enforce(&mut self, budget: u64) {
        let mut kept = Vec::new();
        while self.frame_bytes > budget {
            let Some((tick, id)) = self.lru.pop_first() else {
                break;
            };
            match self.entries.get_mut(&id) {
                Some(e) if e.stored => {
                    if let Some(f) = e.frame.take() {
                        self.frame_bytes = self.frame_bytes.saturating_sub(f.len() as u64);
                    }
                }
                // Only in memory: it stays (losing it would lose the tile).
                Some(_) => kept.push((tick, id)),
                None => {}
            }
        }
        self.lru.extend(kept);
    }
}

impl Hub {
    /// Applies the level-of-detail stage's changes and offers each as a frame to the
    /// clients that speak version 3 (`TileListed`, `TileWithdrawn`).
    pub fn publish_tiles(&self, changes: Vec<TileChange>) -> Result<(), HubError> {
        let mut inner = self.lock();
        if inner.closed.is_some() {
            return Err(HubError::Closed);
        }
        for change in changes {
            let message = match change {
                TileChange::Built {
                    id,
                    listing,
                    frame,
                    stored,
                } => {
                    inner.tiles.drop_entry(id);
                    inner.tick += 1;
                    let tick = inner.tick;
                    inner.tiles.entries.insert(
                        id,
                        TileEntry {
                            listing,
                            frame: None,
                            stored,
                            used: tick,
                        },
                    );
                    inner.tiles.hold(tick, id, frame);
                    Message::TileListed { id, listing }
                }
                TileChange::Relisted { id, listing } => {
                    let Some(e) = inner.tiles.entries.get_mut(&id) else {
                        continue;
                    };
                    e.listing = listing;
                    Message::TileListed { id, listing }
                }
                TileChange::Withdrawn { id } => {
                    inner.tiles.drop_entry(id);
                    Message::TileWithdrawn { id }
                }
            };
            let frame = Bytes::from(message.encode()?);
            Self::broadcast_where(&mut inner, &frame, |c| c.tiles);
        }
        let budget = self.options.tile_memory_budget_bytes;
        inner.tiles.enforce(budget);
        Ok(())
    }

    /// The `TileListed` frames of every tile, coarsest first (what a newcomer needs
    /// for an overview comes first).
    pub(super) fn tile_snapshot(inner: &Inner) -> Result<Vec<Bytes>, HubError> {
        let mut listed: Vec<(TileId, TileListing)> = inner
            .tiles
            .entries
            .iter()
            .map(|(id, e)| (*id, e.listing))
            .collect();
        listed.sort_by(|a, b| b.0.lod.cmp(&a.0.lod).then(a.0.cmp(&b.0)));
        listed
            .into_iter()
            .map(|(id, listing)| Ok(Bytes::from(Message::TileListed { id, listing }.encode()?)))
            .collect()
    }

    /// The `TileData` frame of a listed tile, from memory or read back from the tile
    /// store (which blocks: call from a blocking thread).
    pub fn fetch_tile(&self, id: TileId) -> Result<Bytes, FetchError> {
        let revision = {
            let mut inner = self.lock();
            if inner.closed.is_some() {
                return Err(FetchError::Closed);
            }
            let Some(e) = inner.tiles.entries.get(&id) else {
                return Err(FetchError::UnknownTile(id));
            };
            let revision = e.listing.revision;
            if let Some(frame) = e.frame.clone() {
                inner.tick += 1;
                let tick = inner.tick;
                inner.tiles.hold(tick, id, frame.clone());
                return Ok(frame);
            }
            revision
        };
        let store = self
            .options
            .tile_store
            .as_ref()
            .ok_or(FetchError::UnknownTile(id))?;
        let read = store.read(revision);
        let mut inner = self.lock();
        match read {
            Ok(frame) => {
                inner.tiles.store_reads += 1;
                let current = inner
                    .tiles
                    .entries
                    .get(&id)
                    .is_some_and(|e| e.listing.revision == revision);
                if current {
                    inner.tick += 1;
                    let tick = inner.tick;
                    inner.tiles.hold(tick, id, frame.clone());
                    let budget = self.options.tile_memory_budget_bytes;
                    inner.tiles.enforce(budget);
                }
                Ok(frame)
            }
            Err(source) => Err(FetchError::TileStore { id, source }),
        }
    }

    /// Counts a tile's data written to a client.
    pub fn note_tile_sent(&self, bytes: usize) {
        let mut inner = self.lock();
        inner.tiles.sent += 1;
        inner.tiles.sent_bytes += bytes as u64;
    }

    /// The tiles' part of the status.
    pub fn tile_counts(&self) -> TileCounts {
        let inner = self.lock();
        let t = &inner.tiles;
        let tiles = t.entries.len() as u64;
        let total: u64 = t.entries.values().map(|e| e.listing.encoded_bytes).sum();
        TileCounts {
            tiles,
            mean_tile_bytes: if tiles == 0 {
                0.0
            } else {
                total as f64 / tiles as f64
            },
            largest_tile_bytes: t
                .entries
                .values()
                .map(|e| e.listing.encoded_bytes)
                .max()
                .unwrap_or(0),
            memory_bytes: t.frame_bytes,
            store_reads: t.store_reads,
            sent: t.sent,
            sent_bytes: t.sent_bytes,
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use std::sync::Arc;

    use texel::wire::{Limits, WireTile, decode_frame};

    use super::*;
    use crate::hub::ModelOptions;
    use crate::store::Store;

    fn tile(lod: u8, x: i64) -> TileId {
        TileId { lod, x, y: 0 }
    }

    fn built(id: TileId, revision: u64, store: &Store, bytes: usize) -> TileChange {
        let frame = Message::TileData(Box::new(WireTile {
            id,
            revision,
            data: vec![revision as u8; bytes],
        }))
        .encode()
        .unwrap();
        store.append(revision, &frame).unwrap();
        TileChange::Built {
            id,
            listing: TileListing {
                revision,
                bounds_min_m: [0.0; 3],
                bounds_max_m: [1.0; 3],
                geometric_error_m: 0.1 * f64::from(id.lod),
                triangles: 10,
                encoded_bytes: frame.len() as u64,
            },
            frame: Bytes::from(frame),
            stored: true,
        }
    }

    fn kinds(frames: &[Bytes]) -> Vec<String> {
        frames
            .iter()
            .map(|f| {
                let (m, _) = decode_frame(f, &Limits::FROM_SERVER).unwrap().unwrap();
                match m {
                    Message::TileListed { id, .. } => format!("listed {}", id.path()),
                    Message::TileWithdrawn { id } => format!("withdrawn {}", id.path()),
                    m => m.kind_name().to_string(),
                }
            })
            .collect()
    }

    #[test]
    fn tiles_beyond_the_budget_are_read_back_and_only_version_3_clients_see_them() {
        let dir = tempfile::tempdir().unwrap();
        let store = Arc::new(Store::create(&dir.path().join("t.tiles")).unwrap());
        let hub = Hub::with_model(
            16,
            ModelOptions {
                memory_budget_bytes: u64::MAX,
                tile_memory_budget_bytes: 2500,
                tile_store: Some(Arc::clone(&store)),
                ..ModelOptions::default()
            },
        );
        let mut old = hub.subscribe_with(false).unwrap();
        let mut new = hub.subscribe_with(true).unwrap();
        hub.publish_tiles(vec![
            built(tile(0, 0), 1, &store, 1000),
            built(tile(0, 1), 2, &store, 1000),
            built(tile(1, 0), 3, &store, 1000),
        ])
        .unwrap();
        // Two of three frames fit the budget; the least recently used went to disk.
        let counts = hub.tile_counts();
        assert_eq!(counts.tiles, 3);
        assert!(counts.memory_bytes <= 2500, "{counts:?}");
        assert!(counts.largest_tile_bytes > 1000);
        let first = hub.fetch_tile(tile(0, 0)).unwrap();
        assert_eq!(hub.tile_counts().store_reads, 1);
        let (m, _) = decode_frame(&first, &Limits::FROM_SERVER).unwrap().unwrap();
        let Message::TileData(data) = m else {
            panic!("{m:?}")
        };
        assert_eq!((data.revision, data.data.len()), (1, 1000));
        assert!(hub.tile_counts().memory_bytes <= 2500);
        // A rebuild replaces the tile; a withdrawal forgets it.
        hub.publish_tiles(vec![
            built(tile(0, 1), 4, &store, 500),
            TileChange::Withdrawn { id: tile(0, 0) },
        ])
        .unwrap();
        let e = hub.fetch_tile(tile(0, 0)).unwrap_err().to_string();
        assert!(e.contains("tile 0/0/0 is not in the served tree"), "{e}");
        let again = hub.fetch_tile(tile(0, 1)).unwrap();
        assert!(again.len() < 1000);
        // Live: the version 3 client saw every change, the version 2 client none.
        let mut live = Vec::new();
        while let Ok(f) = new.live.try_recv() {
            live.push(f);
        }
        assert_eq!(
            kinds(&live),
            [
                "listed 0/0/0",
                "listed 0/1/0",
                "listed 1/0/0",
                "listed 0/1/0",
                "withdrawn 0/0/0"
            ]
        );
        assert!(old.live.try_recv().is_err());
        // A newcomer's snapshot lists the tiles coarsest first, before the scans.
        let snapshot = hub.subscribe_with(true).unwrap().snapshot;
        assert_eq!(
            kinds(&snapshot),
            [
                "ModelReset",
                "listed 1/0/0",
                "listed 0/1/0",
                "SnapshotComplete"
            ]
        );
        let snapshot = hub.subscribe_with(false).unwrap().snapshot;
        assert_eq!(kinds(&snapshot), ["ModelReset", "SnapshotComplete"]);
    }
}
