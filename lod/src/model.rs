//! The hierarchy built as scans arrive: one field per level, the finest fed by the
//! scans, each coarser one following the level below block by block; tiles whose
//! blocks changed wait in a queue and are rebuilt a bounded number at a time, so the
//! daemon can keep the hierarchy current off the ingest path and report how far it
//! lags.
//!
//! A scan whose pose is revised (loop closure) is taken out of the finest field at
//! its old pose and fused in at its new one; every tile it touched, at every level, is
//! rebuilt.

use std::collections::{BTreeMap, BTreeSet};

use texel::paged::PageStore;
use texel::{Pose, TexelScan};
use texel_surface::{BlockKey, Sample, Tsdf, parent_block, scan_samples};

use crate::build::{Hierarchy, LodConfig, LodError, LodNode, build_tile, nest};
use crate::fields::{Fields, PagingCounts};
use crate::select::TileInfo;
use crate::tree::{Grid, TileId};

/// The level-of-detail model of a growing scan model.
#[derive(Debug)]
pub struct LodModel {
    config: LodConfig,
    grid: Grid,
    /// One field per level, finest first (paged beyond a budget when given one).
    fields: Fields,
    /// Blocks of the finest field changed since the levels above last followed.
    changed: BTreeSet<BlockKey>,
    /// Tiles waiting to be rebuilt.
    dirty: BTreeSet<TileId>,
    /// Built tiles, each with its own error and bounds (the tree adds its
    /// descendants').
    nodes: BTreeMap<TileId, LodNode>,
    /// Tiles rebuilt (or emptied) since [`Self::take_rebuilt`] was last called.
    rebuilt: BTreeSet<TileId>,
    scans: usize,
}

impl LodModel {
    pub fn new(config: LodConfig) -> Result<Self, LodError> {
        config.validate()?;
        let mut fields = vec![Tsdf::new(config.field())?];
        for _ in 0..config.max_lod {
            let coarser = fields.last().map(Tsdf::coarser_empty);
            fields.extend(coarser);
        }
        Ok(Self {
            grid: config.grid(),
            config,
            fields: Fields::new(fields),
            changed: BTreeSet::new(),
            dirty: BTreeSet::new(),
            nodes: BTreeMap::new(),
            rebuilt: BTreeSet::new(),
            scans: 0,
        })
    }

    /// A model over an existing finest field (anchored at the world origin, at the
    /// config's leaf voxel size); every tile is queued.
    pub fn from_field(field: Tsdf, config: &LodConfig) -> Result<Self, LodError> {
        if field.origin_m() != [0.0; 3] {
            return Err(LodError::FieldNotAnchored {
                origin_m: field.origin_m(),
            });
        }
        let mut config = *config;
        config.leaf_voxel_m = field.voxel_m();
        config.truncation_voxels = field.config().truncation_voxels;
        let mut model = Self::new(config)?;
        model.changed = field.block_keys().collect();
        model.fields.set_finest(field);
        Ok(model)
    }

    pub fn config(&self) -> &LodConfig {
        &self.config
    }

    pub fn grid(&self) -> Grid {
        self.grid
    }

    /// Fuses one registered scan; returns the voxel updates it made.
    pub fn add_scan(&mut self, scan: &TexelScan, world_from_scan: &Pose) -> usize {
        self.scans += 1;
        self.add_samples(&scan_samples(scan, world_from_scan))
    }

    /// Takes a scan out (it leaves the model).
    pub fn remove_scan(&mut self, scan: &TexelScan, world_from_scan: &Pose) -> usize {
        self.scans = self.scans.saturating_sub(1);
        self.remove_samples(&scan_samples(scan, world_from_scan))
    }

    /// Moves a scan whose pose was revised: out at `old`, in at `new`.
    pub fn revise_scan(&mut self, scan: &TexelScan, old: &Pose, new: &Pose) -> usize {
        self.remove_samples(&scan_samples(scan, old)) + self.add_samples(&scan_samples(scan, new))
    }

    /// Fuses samples into the finest field.
    pub fn add_samples(&mut self, samples: &[Sample]) -> usize {
        let updates = self.fields.integrate(samples, &mut self.changed);
        self.fields.keep_within_budget();
        updates
    }

    /// Takes samples out of the finest field.
    pub fn remove_samples(&mut self, samples: &[Sample]) -> usize {
        let updates = self.fields.remove(samples, &mut self.changed);
        self.fields.keep_within_budget();
        updates
    }

    pub fn scans(&self) -> usize {
        self.scans
    }

    /// Tiles waiting to be rebuilt (after the levels follow the finest field's
    /// pending changes, which [`Self::rebuild`] does first): how far the hierarchy
    /// lags behind the scans.
    pub fn pending_tiles(&self) -> usize {
        self.pending_tile_ids().len()
    }

    /// The tiles [`Self::pending_tiles`] counts.
    pub fn pending_tile_ids(&self) -> BTreeSet<TileId> {
        let top = self.top_lod();
        let mut pending: BTreeSet<TileId> =
            self.dirty.range(..=last_of_level(top)).copied().collect();
        // The tiles the finest field's unpropagated changes will queue, level by level.
        let mut changed: BTreeSet<BlockKey> = self.changed.clone();
        for lod in 0..=top {
            for key in &changed {
                pending.insert(self.grid.tile_of_column(lod, [key[0] * 8, key[1] * 8]));
            }
            changed = changed.iter().map(|k| parent_block(*k)).collect();
        }
        pending
    }

    /// Bytes the fields hold in memory.
    pub fn field_bytes(&self) -> usize {
        self.fields.resident_bytes()
    }

    /// From now on, keeps the fields within `max_field_bytes` of memory (beyond what
    /// one operation needs at once), their other blocks in `store`, so the model's
    /// memory no longer grows with the ground covered. The tiles built are the same.
    pub fn page_fields_to(&mut self, store: Box<dyn PageStore>, max_field_bytes: usize) {
        self.fields.page_to(store, max_field_bytes);
    }

    /// What paging the fields has done (all zero when they are not paged).
    pub fn field_paging(&self) -> PagingCounts {
        self.fields.paging()
    }

    /// Bytes the built tiles' meshes and atlases hold.
    pub fn mesh_bytes(&self) -> usize {
        self.nodes
            .values()
            .map(|n| n.mesh.heap_bytes() + n.texture.as_ref().map_or(0, |t| t.heap_bytes()))
            .sum()
    }

    /// The field of level `lod` (the blocks in memory, when the fields are paged).
    pub fn field(&self, lod: u8) -> Option<&Tsdf> {
        self.fields.level(usize::from(lod))
    }

    /// Brings every level up to the finest field's changes (recomputing only the
    /// blocks above changed ones), then rebuilds at most `max_tiles` queued tiles up
    /// to the top of the tree, coarsest first (an overview first, then detail).
    /// Tiles above the top wait until the model grows into them. Returns the tiles
    /// rebuilt.
    pub fn rebuild(&mut self, max_tiles: usize) -> usize {
        self.rebuild_ready(max_tiles, &|_| true).len()
    }

    /// [`Self::rebuild`] of only the queued tiles `ready` accepts (the others stay
    /// queued): a server rebuilding coarse tiles at most so often, say. Returns the
    /// tiles rebuilt.
    pub fn rebuild_ready(
        &mut self,
        max_tiles: usize,
        ready: &dyn Fn(TileId) -> bool,
    ) -> Vec<TileId> {
        self.follow_changes();
        let top = self.top_lod();
        // Ids order by level first: from the last up to the top, coarsest first.
        let chosen: Vec<TileId> = self
            .dirty
            .range(..=last_of_level(top))
            .rev()
            .copied()
            .filter(|id| ready(*id))
            .take(max_tiles)
            .collect();
        for &id in &chosen {
            self.dirty.remove(&id);
            let (lo, hi) = self.grid.columns(id);
            // Surface nets reads a voxel beyond the tile's columns on each side.
            let lod = usize::from(id.lod);
            self.fields.page_in_columns(
                lod,
                lo.map(|i| i.saturating_sub(1)),
                hi.map(|i| i.saturating_add(1)),
            );
            let occupied = self
                .fields
                .level(lod)
                .is_some_and(|f| f.voxels_in_columns(lo, hi).next().is_some());
            // The finer levels colour the tile's atlas.
            let node = occupied
                .then(|| build_tile(&mut self.fields, &self.grid, id, &self.config))
                .flatten();
            self.fields.keep_within_budget();
            match node {
                Some(node) => {
                    self.nodes.insert(id, node);
                }
                None => {
                    self.nodes.remove(&id);
                }
            }
            self.rebuilt.insert(id);
        }
        chosen
    }

    /// The tiles rebuilt since the last call (a tile rebuilt empty is among them and
    /// no longer in [`Self::node`]): what a server publishes anew.
    pub fn take_rebuilt(&mut self) -> BTreeSet<TileId> {
        std::mem::take(&mut self.rebuilt)
    }

    /// A built tile as it was built (its own bounds and error).
    pub fn node(&self, id: TileId) -> Option<&LodNode> {
        self.nodes.get(&id)
    }

    /// Every built tile up to the top of the tree with its nested bounds and error
    /// (as in [`Self::hierarchy`], without copying a mesh).
    pub fn tree_infos(&self) -> BTreeMap<TileId, TileInfo> {
        nest(
            self.nodes.iter().map(|(id, n)| (*id, n.info())).collect(),
            self.top_lod(),
        )
    }

    /// The tiles rebuilt so far as a tree.
    pub fn hierarchy(&self) -> Result<Hierarchy, LodError> {
        Hierarchy::over(self.grid, &self.nodes, self.top_lod())
    }

    /// The top of the tree: the finest level whose field lies in at most four tiles
    /// (so the root above them has at most four children), else `max_lod`. Read from
    /// the finest field (a coarse block exists exactly above fine ones), so it does not
    /// wait for the coarser fields to follow.
    pub fn top_lod(&self) -> u8 {
        for lod in 0..=self.config.max_lod {
            let mut tiles = BTreeSet::new();
            for key in self.fields.block_keys(0) {
                let shift = 1i64 << lod.min(62);
                let column = [key[0].div_euclid(shift) * 8, key[1].div_euclid(shift) * 8];
                tiles.insert(self.grid.tile_of_column(lod, column));
                if tiles.len() > 4 {
                    break;
                }
            }
            if tiles.len() <= 4 {
                return lod;
            }
        }
        self.config.max_lod
    }

    /// Each level recomputes the blocks above the level below's changed ones, and
    /// queues the tiles they lie in.
    fn follow_changes(&mut self) {
        let mut changed = std::mem::take(&mut self.changed);
        for lod in 0..self.fields.len() {
            for key in &changed {
                let tile = self
                    .grid
                    .tile_of_column(lod as u8, [key[0] * 8, key[1] * 8]);
                self.dirty.insert(tile);
            }
            if lod + 1 == self.fields.len() {
                break;
            }
            let parents: BTreeSet<BlockKey> = changed.iter().map(|k| parent_block(*k)).collect();
            for key in &parents {
                self.fields.resample(lod + 1, *key);
            }
            changed = parents;
        }
        self.fields.keep_within_budget();
    }
}

/// The greatest id of level `lod`: ranges up to it hold every tile up to that level.
fn last_of_level(lod: u8) -> TileId {
    TileId {
        lod,
        x: i64::MAX,
        y: i64::MAX,
    }
}
