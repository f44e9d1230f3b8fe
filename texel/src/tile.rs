//! The id of a tile of the level-of-detail quadtree (`texel-lod` builds the tree; the
//! wire protocol names its tiles by these ids): its level and its place on a fixed
//! grid anchored at the world origin.

use serde::{Deserialize, Serialize};

/// A tile of the grid: `lod` levels above the finest, column `x` and row `y` (tile
/// `(x, y)` of level `lod` spans `[x, x + 1) × [y, y + 1)` tile edges from the world
/// origin).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct TileId {
    pub lod: u8,
    pub x: i64,
    pub y: i64,
}

/// The highest level a grid has: 2^24 finest tiles across is beyond any walk.
pub const MAX_LOD: u8 = 24;

impl TileId {
    /// The four tiles of the level below that make this one, in a fixed order;
    /// `None` at the finest level.
    pub fn children(self) -> Option<[TileId; 4]> {
        let lod = self.lod.checked_sub(1)?;
        let (x, y) = (self.x * 2, self.y * 2);
        Some([
            TileId { lod, x, y },
            TileId { lod, x: x + 1, y },
            TileId { lod, x, y: y + 1 },
            TileId {
                lod,
                x: x + 1,
                y: y + 1,
            },
        ])
    }

    /// The tile of the level above that holds this one, `None` at [`MAX_LOD`].
    pub fn parent(self) -> Option<TileId> {
        (self.lod < MAX_LOD).then(|| TileId {
            lod: self.lod + 1,
            x: self.x.div_euclid(2),
            y: self.y.div_euclid(2),
        })
    }

    /// The tile `levels` above (itself for 0), saturating at [`MAX_LOD`].
    pub fn ancestor(self, lod: u8) -> TileId {
        let up = u32::from(lod.saturating_sub(self.lod));
        TileId {
            lod: self.lod.max(lod),
            x: self.x.div_euclid(1i64 << up.min(62)),
            y: self.y.div_euclid(1i64 << up.min(62)),
        }
    }

    /// Whether `self` is `other` or lies inside it.
    pub fn is_within(self, other: TileId) -> bool {
        self.lod <= other.lod && self.ancestor(other.lod) == other
    }

    /// A path-like name, `lod/x/y`.
    pub fn path(self) -> String {
        format!("{}/{}/{}", self.lod, self.x, self.y)
    }
}

/// A tile as the daemon lists it: enough to select it by screen-space error and to
/// cull it (Liu 2014 §4.3), and to decide whether to fetch its data.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TileListing {
    /// Grows every time the tile is rebuilt (unique across the daemon's tiles): a
    /// client holding an older revision fetches it again when it wants the tile.
    pub revision: u64,
    /// World bounds of the tile's surface and every descendant's, metres.
    pub bounds_min_m: [f64; 3],
    pub bounds_max_m: [f64; 3],
    /// How far drawing this tile instead of its children can move the surface,
    /// metres; never less than any child's.
    pub geometric_error_m: f64,
    /// Triangles of its mesh.
    pub triangles: u32,
    /// Bytes of its data on the wire (the `TileData` frame).
    pub encoded_bytes: u64,
}

impl TileListing {
    /// Why the listing is not valid, if it is not: non-finite numbers, inverted
    /// bounds, a negative error.
    pub fn check(&self) -> Result<(), String> {
        let floats = self
            .bounds_min_m
            .iter()
            .chain(&self.bounds_max_m)
            .chain(std::iter::once(&self.geometric_error_m));
        if floats.into_iter().any(|v| !v.is_finite()) {
            return Err("non-finite bounds or geometric error".into());
        }
        if let Some(axis) = (0..3).find(|&k| self.bounds_min_m[k] > self.bounds_max_m[k]) {
            return Err(format!("bounds min > max on axis {axis}"));
        }
        if self.geometric_error_m < 0.0 {
            return Err(format!(
                "negative geometric error {}",
                self.geometric_error_m
            ));
        }
        Ok(())
    }
}
