//! The level-of-detail stage: a thread that keeps the tree (`texel-lod`'s
//! `LodModel`) current as scans arrive and poses are revised, off the ingest path,
//! and publishes its tiles to the hub (`docs/lod.md`, "In the daemon").
//!
//! The encode stage never waits for it. What it hands over goes into an inbox that
//! coalesces by scan: the newest pose of a scan replaces an older one not yet taken,
//! so the inbox holds at most one entry per scan (ids and poses, a few dozen bytes
//! each). A new scan's data is held only while fewer than `held_scans` are; beyond
//! that the stage reads the scan back from the model's store when its turn comes, so
//! a lagging stage costs time, not memory. Nothing is dropped, and how far the tree
//! lags is in the status.
//!
//! Each round fuses a few scans, then rebuilds a few tiles, coarsest first (an
//! overview before detail), and publishes what changed: rebuilt tiles with a new
//! revision, tiles whose nested bounds or error changed, tiles left empty.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use bytes::Bytes;
use nalgebra::Point3;
use texel::model::ScanId;
use texel::paged::PageStore;
use texel::tile::{TileId, TileListing};
use texel::wire::{LodStatus, Message, WireTile};
use texel::{Pose, TexelScan};
use texel_lod::{LodModel, encode_tile};

use crate::config::LodSection;
use crate::hub::{Hub, HubError, TileChange};
use crate::store::Store;

/// How long an idle stage sleeps before looking again (it is woken at once by new
/// work; this only bounds how stale the lag it reports can be).
const IDLE_WAIT: Duration = Duration::from_millis(250);
/// How long a round waits for scans while only coarse tiles wait their interval.
const INTERVAL_WAIT: Duration = Duration::from_millis(20);

/// What the stage is to do with one scan.
struct Target {
    world_from_scan: Pose,
    scan: Option<Arc<TexelScan>>,
    /// When the oldest change coalesced here arrived.
    since: Instant,
}

#[derive(Default)]
struct InboxState {
    targets: BTreeMap<ScanId, Target>,
    held: usize,
    closed: bool,
}

/// The hand-over from the encode stage: coalescing, never blocking the sender.
pub struct LodInbox {
    state: Mutex<InboxState>,
    ready: Condvar,
    max_held: usize,
}

impl LodInbox {
    pub fn new(max_held_scans: usize) -> Arc<Self> {
        Arc::new(Self {
            state: Mutex::new(InboxState::default()),
            ready: Condvar::new(),
            max_held: max_held_scans,
        })
    }

    fn lock(&self) -> MutexGuard<'_, InboxState> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// A new scan at its first pose.
    pub fn scan(&self, id: ScanId, scan: &Arc<TexelScan>, world_from_scan: Pose) {
        let mut s = self.lock();
        let hold = s.held < self.max_held;
        let since = s.targets.get(&id).map_or_else(Instant::now, |t| t.since);
        let old = s.targets.insert(
            id,
            Target {
                world_from_scan,
                scan: hold.then(|| Arc::clone(scan)),
                since,
            },
        );
        if old.is_some_and(|t| t.scan.is_some()) {
            s.held -= 1;
        }
        if hold {
            s.held += 1;
        }
        drop(s);
        self.ready.notify_one();
    }

    /// A scan's pose was revised: the newest pose wins.
    pub fn revision(&self, id: ScanId, world_from_scan: Pose) {
        let mut s = self.lock();
        match s.targets.get_mut(&id) {
            Some(t) => t.world_from_scan = world_from_scan,
            None => {
                s.targets.insert(
                    id,
                    Target {
                        world_from_scan,
                        scan: None,
                        since: Instant::now(),
                    },
                );
            }
        }
        drop(s);
        self.ready.notify_one();
    }

    /// No more changes: the stage stops after what it holds now is no longer needed.
    pub fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }

    /// Scans waiting.
    pub fn pending(&self) -> usize {
        self.lock().targets.len()
    }

    /// Up to `n` targets, oldest scan ids first, waiting up to `wait` for one; and
    /// whether the inbox is closed.
    fn take(&self, n: usize, wait: Duration) -> (Vec<(ScanId, Target)>, bool, Option<Instant>) {
        let mut s = self.lock();
        if s.targets.is_empty() && !s.closed && !wait.is_zero() {
            s = self
                .ready
                .wait_timeout(s, wait)
                .map(|(g, _)| g)
                .unwrap_or_else(|e| e.into_inner().0);
        }
        let mut out = Vec::with_capacity(n.min(s.targets.len()));
        while out.len() < n {
            let Some((id, t)) = s.targets.pop_first() else {
                break;
            };
            if t.scan.is_some() {
                s.held -= 1;
            }
            out.push((id, t));
        }
        let oldest = s.targets.values().map(|t| t.since).min();
        (out, s.closed, oldest)
    }
}

/// A fused scan: where it was fused and how far its points reach from that pose's
/// origin (a rotation moves far points most).
#[derive(Clone, Copy)]
struct Fused {
    world_from_scan: Pose,
    reach_m: f64,
}

/// The stage's state, owned by its thread.
pub struct LodStage {
    pub inbox: Arc<LodInbox>,
    pub hub: Arc<Hub>,
    /// The model's store, where scans not held are read back from.
    pub scans: Option<Arc<Store>>,
    /// Where tile data is written (keyed by revision) before the hub may drop it
    /// from memory.
    pub tiles: Option<Arc<Store>>,
    /// Where the fields' blocks go beyond `config.field_memory_budget_mb` (without
    /// one, the fields stay in memory).
    pub field_pages: Option<Box<dyn PageStore>>,
    pub config: LodSection,
    pub status: Arc<Mutex<LodStatus>>,
    /// Set to stop at the next round (the session ends).
    pub stop: Arc<AtomicBool>,
}

impl LodStage {
    /// Runs until the inbox closes (or `stop`), publishing as it goes.
    pub fn run(mut self) {
        let mut model = match LodModel::new(self.config.tree) {
            Ok(m) => m,
            Err(e) => {
                tracing::error!("level of detail: {e}; no tree is built");
                return;
            }
        };
        if let Some(pages) = self.field_pages.take() {
            model.page_fields_to(pages, self.config.field_memory_budget_bytes());
        }
        let mut page_errors_logged = 0;
        let mut fused: BTreeMap<ScanId, Fused> = BTreeMap::new();
        let mut published: BTreeMap<TileId, TileListing> = BTreeMap::new();
        let mut next_revision = 1u64;
        let mut counts = LodStatus::default();
        // Per queued tile, since when: the lag is the oldest change not yet served.
        let mut queued_since: BTreeMap<TileId, Instant> = BTreeMap::new();
        // When each tile was last rebuilt, for the coarse tiles' interval.
        let mut built_at: BTreeMap<TileId, Instant> = BTreeMap::new();
        // Tiles ready to rebuild after the last round: while there are, rounds do not
        // wait; while only coarse tiles wait their interval, rounds wait a little.
        let mut ready_tiles = false;
        let mut pending_tiles = 0;
        while !self.stop.load(Ordering::Acquire) {
            let wait = if ready_tiles {
                Duration::ZERO
            } else if pending_tiles > 0 {
                INTERVAL_WAIT
            } else {
                IDLE_WAIT
            };
            let (batch, closed, oldest_waiting) =
                self.inbox.take(self.config.scans_per_round, wait);
            // The scans' arrival, so a tile they queue counts from when they came.
            let arrived = batch.iter().map(|(_, t)| t.since).min();
            for (id, target) in &batch {
                self.fuse(&mut model, &mut fused, &mut counts, *id, target);
            }
            let now = Instant::now();
            // A tile is due once its level's interval has passed since it was built.
            let due = |built_at: &BTreeMap<TileId, Instant>, id: TileId, now: Instant| {
                built_at
                    .get(&id)
                    .is_none_or(|t| now.duration_since(*t) >= self.config.coarse_interval(id.lod))
            };
            let rebuilt_ids =
                model.rebuild_ready(self.config.tiles_per_round, &|id| due(&built_at, id, now));
            for id in &rebuilt_ids {
                built_at.insert(*id, now);
            }
            let rebuilt = rebuilt_ids.len();
            counts.rebuilds += rebuilt as u64;
            if rebuilt > 0 {
                let changes = self.changes(&mut model, &mut published, &mut next_revision);
                match self.hub.publish_tiles(changes) {
                    Ok(()) => {}
                    // The hub closed: the session is over.
                    Err(HubError::Closed) => return,
                    Err(e) => tracing::error!("level of detail: tiles not published: {e}"),
                }
            }
            let pending = model.pending_tile_ids();
            pending_tiles = pending.len();
            let now = Instant::now();
            ready_tiles = pending.iter().any(|id| due(&built_at, *id, now));
            queued_since.retain(|id, _| pending.contains(id));
            for id in pending {
                queued_since
                    .entry(id)
                    .or_insert(arrived.unwrap_or(now).min(now));
            }
            let oldest_queued = queued_since.values().min().copied();
            let lag_from = match (oldest_queued, oldest_waiting) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
            counts.pending_tiles = pending_tiles as u64;
            counts.pending_scans = self.inbox.pending() as u64;
            counts.lag_s = lag_from.map_or(0.0, |t| now.duration_since(t).as_secs_f64());
            counts.top_lod = u64::from(model.top_lod());
            counts.field_bytes = model.field_bytes() as u64;
            let paging = model.field_paging();
            counts.field_paged_bytes = paging.bytes_out;
            counts.field_page_errors = paging.errors;
            if paging.errors > page_errors_logged {
                // Once per new batch of failures, not per block.
                tracing::error!(
                    "level of detail: {} field page writes or reads failed so far \
                     (unwritten blocks stay in memory; unreadable ones are observed anew)",
                    paging.errors
                );
                page_errors_logged = paging.errors;
            }
            if let Ok(mut s) = self.status.lock() {
                let tiles = self.hub.tile_counts();
                *s = LodStatus {
                    tiles: tiles.tiles,
                    mean_tile_bytes: tiles.mean_tile_bytes,
                    largest_tile_bytes: tiles.largest_tile_bytes,
                    tile_memory_bytes: tiles.memory_bytes,
                    tiles_sent: tiles.sent,
                    tile_bytes_sent: tiles.sent_bytes,
                    ..counts.clone()
                };
            }
            if closed && batch.is_empty() && self.inbox.pending() == 0 && pending_tiles == 0 {
                return;
            }
        }
    }

    /// Fuses a new scan, or moves a fused one whose pose changed past the threshold.
    fn fuse(
        &self,
        model: &mut LodModel,
        fused: &mut BTreeMap<ScanId, Fused>,
        counts: &mut LodStatus,
        id: ScanId,
        target: &Target,
    ) {
        let new = target.world_from_scan;
        let before = fused.get(&id).copied();
        if let Some(before) = before
            && displacement_m(&before.world_from_scan, &new, before.reach_m)
                < self.config.revise_threshold_m
        {
            counts.revisions_skipped += 1;
            return;
        }
        let scan = match &target.scan {
            Some(scan) => Arc::clone(scan),
            None => match self.read_back(id) {
                Ok(scan) => Arc::new(scan),
                Err(e) => {
                    counts.read_errors += 1;
                    if counts.read_errors == 1 {
                        tracing::error!("level of detail: scan {id}: {e}; left out of the tree");
                    }
                    return;
                }
            },
        };
        match before {
            Some(before) => {
                model.revise_scan(&scan, &before.world_from_scan, &new);
                counts.revisions_applied += 1;
            }
            None => {
                model.add_scan(&scan, &new);
                counts.scans_fused += 1;
            }
        }
        fused.insert(
            id,
            Fused {
                world_from_scan: new,
                reach_m: reach_m(&scan),
            },
        );
    }

    /// A scan's data from the model's store (its texture decoded: colours are fused).
    fn read_back(&self, id: ScanId) -> Result<TexelScan, String> {
        let store = self.scans.as_ref().ok_or("no store holds it")?;
        let frame = store.read(id).map_err(|e| e.to_string())?;
        match texel::wire::decode_frame(&frame, &texel::wire::Limits::FROM_SERVER) {
            Ok(Some((Message::ScanAdded(wire), _))) => wire
                .into_scan()
                .map(|(_, scan, _)| scan)
                .map_err(|e| e.to_string()),
            Ok(_) => Err("its stored frame is not a whole ScanAdded".into()),
            Err(e) => Err(format!("its stored frame does not decode: {e}")),
        }
    }

    /// What changed in the served tree since the last publication.
    fn changes(
        &self,
        model: &mut LodModel,
        published: &mut BTreeMap<TileId, TileListing>,
        next_revision: &mut u64,
    ) -> Vec<TileChange> {
        let infos = model.tree_infos();
        let rebuilt = model.take_rebuilt();
        let mut changes = Vec::new();
        for (id, info) in &infos {
            let listing = |revision: u64, triangles: u32, encoded_bytes: u64| TileListing {
                revision,
                bounds_min_m: info.bounds_min_m,
                bounds_max_m: info.bounds_max_m,
                geometric_error_m: info.geometric_error_m,
                triangles,
                encoded_bytes,
            };
            let old = published.get(id).copied();
            if rebuilt.contains(id) || old.is_none() {
                let Some(node) = model.node(*id) else {
                    continue;
                };
                let revision = *next_revision;
                *next_revision += 1;
                let frame = match (Message::TileData(Box::new(WireTile {
                    id: *id,
                    revision,
                    data: encode_tile(node),
                })))
                .encode()
                {
                    Ok(f) => Bytes::from(f),
                    Err(e) => {
                        tracing::error!("level of detail: tile {}: {e}", id.path());
                        continue;
                    }
                };
                let stored = self
                    .tiles
                    .as_ref()
                    .is_some_and(|store| store.append(revision, &frame).is_ok());
                let triangles = u32::try_from(node.mesh.triangle_count()).unwrap_or(u32::MAX);
                let l = listing(revision, triangles, frame.len() as u64);
                published.insert(*id, l);
                changes.push(TileChange::Built {
                    id: *id,
                    listing: l,
                    frame,
                    stored,
                });
            } else if let Some(old) = old {
                let l = listing(old.revision, old.triangles, old.encoded_bytes);
                if l != old {
                    published.insert(*id, l);
                    changes.push(TileChange::Relisted {
                        id: *id,
                        listing: l,
                    });
                }
            }
        }
        let gone: Vec<TileId> = published
            .keys()
            .filter(|id| !infos.contains_key(id))
            .copied()
            .collect();
        for id in gone {
            published.remove(&id);
            changes.push(TileChange::Withdrawn { id });
        }
        changes
    }
}

/// How far a scan's points reach from its origin (the farthest vertex).
fn reach_m(scan: &TexelScan) -> f64 {
    scan.vertices
        .iter()
        .map(|v| {
            Point3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]))
                .coords
                .norm()
        })
        .filter(|d| d.is_finite())
        .fold(0.0, f64::max)
}

/// The largest distance any point within `reach_m` of the scan's origin moves
/// between two poses: the origin's shift plus the chord the rotation sweeps at that
/// reach.
pub fn displacement_m(a: &Pose, b: &Pose, reach_m: f64) -> f64 {
    let shift = (b.translation.vector - a.translation.vector).norm();
    let angle = a.rotation.angle_to(&b.rotation);
    let chord = 2.0 * (0.5 * angle).sin().abs() * reach_m.max(0.0);
    shift + chord
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    #[test]
    fn displacement_counts_the_rotation_at_the_scans_reach() {
        let a = Pose::identity();
        let b = Pose::translation(0.03, 0.0, 0.04);
        assert!((displacement_m(&a, &b, 50.0) - 0.05).abs() < 1e-12);
        // 0.1 degree at 30 m moves a far point about 5 cm.
        let r = Pose::from_parts(
            nalgebra::Translation3::identity(),
            nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 0.1f64.to_radians()),
        );
        let d = displacement_m(&a, &r, 30.0);
        assert!((d - 30.0 * 0.1f64.to_radians()).abs() < 1e-6, "{d}");
        assert_eq!(displacement_m(&a, &a, 30.0), 0.0);
    }

    #[test]
    fn the_inbox_coalesces_by_scan_and_bounds_what_it_holds() {
        let inbox = LodInbox::new(2);
        let scan = texel::fuzzing::sample_messages()
            .into_iter()
            .find_map(|m| match m {
                Message::ScanAdded(wire) => Some(wire.into_scan().unwrap().1),
                _ => None,
            })
            .unwrap();
        let scan = Arc::new(scan);
        for id in 0..5 {
            inbox.scan(id, &scan, Pose::identity());
        }
        inbox.revision(1, Pose::translation(1.0, 0.0, 0.0));
        inbox.revision(1, Pose::translation(2.0, 0.0, 0.0));
        inbox.revision(9, Pose::translation(3.0, 0.0, 0.0));
        assert_eq!(inbox.pending(), 6);
        // Only the first two scans' data is held; the newest pose of scan 1 wins.
        assert_eq!(Arc::strong_count(&scan), 3);
        let (batch, closed, _) = inbox.take(3, Duration::ZERO);
        assert!(!closed);
        let ids: Vec<ScanId> = batch.iter().map(|(id, _)| *id).collect();
        assert_eq!(ids, vec![0, 1, 2]);
        assert!(batch[0].1.scan.is_some() && batch[1].1.scan.is_some());
        assert!(batch[2].1.scan.is_none());
        assert_eq!(batch[1].1.world_from_scan.translation.vector.x, 2.0);
        drop(batch);
        assert_eq!(Arc::strong_count(&scan), 1);
        // Freed room holds the next scan's data.
        inbox.scan(10, &scan, Pose::identity());
        assert_eq!(Arc::strong_count(&scan), 2);
        inbox.close();
        let (rest, closed, _) = inbox.take(100, Duration::from_secs(5));
        assert!(closed);
        assert_eq!(rest.len(), 4);
    }
}
