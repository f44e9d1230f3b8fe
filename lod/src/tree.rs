//! The quadtree over the ground: a fixed grid of square tiles in the world, level by
//! level, and the voxel size each level is merged at.
//!
//! A quadtree (Liu 2014 §4.1.2), not an octree: a walk with a texel camera covers
//! ground, kilometres across and tens of metres high, so splitting height would only
//! cut tall facades into more tiles without making any tile cheaper to draw. Every
//! tile at every level is cut from a field of the same number of voxels across, so
//! polygon counts stay comparable across levels, as in Liu.
//!
//! The grid is anchored at the world origin and never moves, so a tile keeps its id
//! while the model grows around it (what incremental rebuilds and caches key on).
//! Levels count up from the finest (`lod` 0); the top of a hierarchy is the first
//! level where at most four tiles hold the model, under one root without content.

use serde::{Deserialize, Serialize};

pub use texel::tile::{MAX_LOD, TileId};

/// The grid's resolution: how fine the finest level is and how many voxels a tile
/// has across at every level.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    pub leaf_voxel_m: f64,
    pub tile_voxels: u32,
}

impl Grid {
    /// The voxel size tiles of level `lod` are merged at: doubling per level.
    pub fn voxel_m(&self, lod: u8) -> f64 {
        self.leaf_voxel_m * f64::from(1u32 << lod.min(31))
    }

    /// Edge of a tile of level `lod`, metres.
    pub fn tile_m(&self, lod: u8) -> f64 {
        self.voxel_m(lod) * f64::from(self.tile_voxels)
    }

    /// The tile's footprint: minimum and maximum world x and y.
    pub fn footprint(&self, id: TileId) -> ([f64; 2], [f64; 2]) {
        // Through the voxel columns, so the borders are the field's voxel borders to
        // the bit.
        let (lo, hi) = self.columns(id);
        let v = self.voxel_m(id.lod);
        (lo.map(|c| c as f64 * v), hi.map(|c| c as f64 * v))
    }

    /// The voxel columns `[lo, hi)` of the tile in its level's field (fields are
    /// anchored at the world origin).
    pub fn columns(&self, id: TileId) -> ([i64; 2], [i64; 2]) {
        let n = i64::from(self.tile_voxels);
        let lo = [id.x * n, id.y * n];
        (lo, [lo[0] + n, lo[1] + n])
    }

    /// The tile of level `lod` holding voxel column `column` of that level's field.
    pub fn tile_of_column(&self, lod: u8, column: [i64; 2]) -> TileId {
        let n = i64::from(self.tile_voxels.max(1));
        TileId {
            lod,
            x: column[0].div_euclid(n),
            y: column[1].div_euclid(n),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    #[test]
    fn tiles_nest_across_the_origin_and_columns_map_back_to_tiles() {
        let grid = Grid {
            leaf_voxel_m: 0.1,
            tile_voxels: 128,
        };
        assert_eq!(grid.tile_m(0), 12.8);
        assert_eq!(grid.tile_m(3), 102.4);
        let leaf = TileId {
            lod: 0,
            x: -3,
            y: 5,
        };
        assert_eq!(
            leaf.parent(),
            Some(TileId {
                lod: 1,
                x: -2,
                y: 2
            })
        );
        assert_eq!(
            leaf.ancestor(3),
            TileId {
                lod: 3,
                x: -1,
                y: 0
            }
        );
        assert!(leaf.is_within(TileId {
            lod: 3,
            x: -1,
            y: 0
        }));
        assert!(!leaf.is_within(TileId { lod: 3, x: 0, y: 0 }));
        assert!(leaf.is_within(leaf));
        let parent = leaf.parent().unwrap();
        assert!(parent.children().unwrap().contains(&leaf));
        assert!(leaf.children().is_none());
        let (lo, hi) = grid.footprint(leaf);
        assert!((lo[0] - -38.4).abs() < 1e-12 && (lo[1] - 64.0).abs() < 1e-12);
        assert!((hi[0] - -25.6).abs() < 1e-12);
        for lod in 0..5 {
            let id = TileId { lod, x: -1, y: 2 };
            let (c_lo, c_hi) = grid.columns(id);
            assert_eq!(c_hi[0] - c_lo[0], 128);
            assert_eq!(grid.tile_of_column(lod, c_lo), id);
            assert_eq!(grid.tile_of_column(lod, [c_hi[0] - 1, c_hi[1] - 1]), id);
        }
    }
}
