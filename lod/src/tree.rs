//! The quadtree over the ground: tile ids, their square footprints in the world and
//! the voxel size each level is merged at.
//!
//! A quadtree (Liu 2014 §4.1.2), not an octree: a walk with a texel camera covers
//! ground, kilometres across and tens of metres high, so splitting height would only
//! cut tall facades into more tiles without making any tile cheaper to draw. Every
//! tile at every level is cut from a field of the same number of voxels across, so
//! polygon counts stay comparable across levels, as in Liu.

use serde::{Deserialize, Serialize};

/// A tile: its level (0 is the root, the coarsest) and its column and row among the
/// `2^level × 2^level` tiles of that level, counted from the layout's origin.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct TileId {
    pub level: u8,
    pub x: u32,
    pub y: u32,
}

impl TileId {
    pub const ROOT: TileId = TileId {
        level: 0,
        x: 0,
        y: 0,
    };

    /// The four children, in a fixed order.
    pub fn children(self) -> [TileId; 4] {
        let (l, x, y) = (self.level + 1, self.x * 2, self.y * 2);
        [
            TileId { level: l, x, y },
            TileId {
                level: l,
                x: x + 1,
                y,
            },
            TileId {
                level: l,
                x,
                y: y + 1,
            },
            TileId {
                level: l,
                x: x + 1,
                y: y + 1,
            },
        ]
    }

    /// The parent, `None` for the root.
    pub fn parent(self) -> Option<TileId> {
        (self.level > 0).then(|| TileId {
            level: self.level - 1,
            x: self.x / 2,
            y: self.y / 2,
        })
    }

    /// Whether `self` is `other` or lies inside it.
    pub fn is_within(self, other: TileId) -> bool {
        if self.level < other.level {
            return false;
        }
        let shift = u32::from(self.level - other.level);
        (self.x >> shift) == other.x && (self.y >> shift) == other.y
    }

    /// A path-like name, `level/x/y`.
    pub fn path(self) -> String {
        format!("{}/{}/{}", self.level, self.x, self.y)
    }
}

/// Where the tree lies and how fine it is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Layout {
    /// The root's south-west corner (minimum x and y), world metres.
    pub origin_m: [f64; 2],
    /// The same corner as a column of the leaf field the layout was made for.
    pub corner_leaf_voxels: [i64; 2],
    /// The finest level, whose tiles are `leaf_tile_voxels` leaf voxels across.
    pub depth: u8,
    pub leaf_voxel_m: f64,
    pub leaf_tile_voxels: u32,
}

/// Deepest tree a layout builds: 2^20 leaf tiles across is beyond any walk.
pub const MAX_DEPTH: u8 = 20;

impl Layout {
    /// The smallest tree whose root covers the voxel columns `[lo, hi)` of the leaf
    /// field, its corner on a leaf tile border. Each level's field is anchored at the
    /// root's corner (see `build`), so tile borders fall on voxel borders at every
    /// level.
    pub fn covering(
        lo: [i64; 2],
        hi: [i64; 2],
        leaf_voxel_m: f64,
        leaf_tile_voxels: u32,
    ) -> Layout {
        let tile = i64::from(leaf_tile_voxels.max(1));
        let corner = lo.map(|i| i.div_euclid(tile) * tile);
        let span = (0..2)
            .map(|a| (hi[a] - corner[a]).max(1))
            .max()
            .unwrap_or(1);
        let mut depth = 0u8;
        while depth < MAX_DEPTH && tile << depth < span {
            depth += 1;
        }
        Layout {
            origin_m: corner.map(|c| c as f64 * leaf_voxel_m),
            corner_leaf_voxels: corner,
            depth,
            leaf_voxel_m,
            leaf_tile_voxels: tile as u32,
        }
    }

    /// The voxel size tiles at `level` are merged at: doubling per level up.
    pub fn voxel_m(&self, level: u8) -> f64 {
        self.leaf_voxel_m * f64::from(1u32 << (self.depth.saturating_sub(level)).min(31))
    }

    /// Edge of a tile at `level`, metres.
    pub fn tile_m(&self, level: u8) -> f64 {
        self.voxel_m(level) * f64::from(self.leaf_tile_voxels)
    }

    /// The tile's footprint: minimum and maximum world x and y.
    pub fn footprint(&self, id: TileId) -> ([f64; 2], [f64; 2]) {
        let size = self.tile_m(id.level);
        let lo = [
            self.origin_m[0] + f64::from(id.x) * size,
            self.origin_m[1] + f64::from(id.y) * size,
        ];
        (lo, [lo[0] + size, lo[1] + size])
    }

    /// The voxel columns `[lo, hi)` of the tile in its level's field, that field
    /// anchored at the root's corner (column `[0, 0]` starts there).
    pub fn columns(&self, id: TileId) -> ([i64; 2], [i64; 2]) {
        let n = i64::from(self.leaf_tile_voxels);
        let lo = [i64::from(id.x) * n, i64::from(id.y) * n];
        (lo, [lo[0] + n, lo[1] + n])
    }

    /// The tile at `level` holding voxel column `column` of that level's anchored
    /// field, `None` outside the root.
    pub fn tile_of_column(&self, level: u8, column: [i64; 2]) -> Option<TileId> {
        let n = i64::from(self.leaf_tile_voxels);
        let side = 1i64 << level.min(MAX_DEPTH);
        let x = column[0].div_euclid(n);
        let y = column[1].div_euclid(n);
        ((0..side).contains(&x) && (0..side).contains(&y)).then_some(TileId {
            level,
            x: x as u32,
            y: y as u32,
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    #[test]
    fn the_root_covers_what_it_was_built_for_and_tiles_nest() {
        let layout = Layout::covering([-130, 7], [900, 260], 0.1, 128);
        assert_eq!(layout.origin_m, [-25.6, 0.0]);
        assert_eq!(layout.corner_leaf_voxels, [-256, 0]);
        // 1156 columns from -256 need more than 8 leaf tiles: depth 4.
        assert_eq!(layout.depth, 4);
        assert_eq!(layout.tile_m(4), 12.8);
        assert_eq!(layout.tile_m(0), 204.8);
        let (lo, hi) = layout.footprint(TileId::ROOT);
        assert!(lo[0] <= -13.0 && hi[0] >= 90.0 && lo[1] <= 0.7 && hi[1] >= 26.0);
        assert_eq!(layout.tile_of_column(0, [100, 5]), Some(TileId::ROOT));
        assert_eq!(layout.tile_of_column(0, [-1, 5]), None);
        for level in 1..=layout.depth {
            let (c_lo, c_hi) = layout.columns(TileId { level, x: 1, y: 0 });
            assert_eq!(c_hi[0] - c_lo[0], 128);
            let tile = layout.tile_of_column(level, c_lo).unwrap();
            assert_eq!(tile, TileId { level, x: 1, y: 0 });
        }
        let child = TileId {
            level: 3,
            x: 5,
            y: 2,
        };
        assert!(child.is_within(TileId {
            level: 1,
            x: 1,
            y: 0
        }));
        assert!(!child.is_within(TileId {
            level: 1,
            x: 0,
            y: 0
        }));
        assert_eq!(
            child.parent().unwrap().parent().unwrap(),
            TileId {
                level: 1,
                x: 1,
                y: 0
            }
        );
        assert!(
            TileId::ROOT
                .children()
                .iter()
                .all(|c| c.parent() == Some(TileId::ROOT))
        );
    }
}
