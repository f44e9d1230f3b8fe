//! Building the hierarchy: every registered scan fused into one leaf-resolution field,
//! the field halved in resolution level by level, and each tile of each level cut from
//! its level's field and simplified to one triangle budget (Liu 2014 §4.1.2, §4.2).

use std::collections::{BTreeMap, BTreeSet};

use texel::{Pose, TexelScan};
use texel_surface::{SurfaceMesh, Tsdf, TsdfConfig, TsdfError, VoxelRegion, extract, simplify};
use thiserror::Error;

use crate::tree::{Layout, TileId};

/// How fine the hierarchy is and what a tile may cost. TOML overrides the defaults;
/// unknown keys are errors.
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LodConfig {
    /// Voxel size of the finest level, metres. Ten centimetres resolve doors, windows
    /// and kerbs; the scans themselves stand in below that.
    pub leaf_voxel_m: f64,
    /// Voxels across a tile, at every level (a multiple of 8).
    pub tile_voxels: u32,
    /// Triangles a tile is simplified towards, at every level.
    pub tile_triangle_budget: usize,
    /// Largest surface movement simplification may make, in voxels of the tile's level.
    pub simplify_error_voxels: f64,
    /// Half-width of the TSDF band, in leaf voxels.
    pub truncation_voxels: f64,
}

impl Default for LodConfig {
    fn default() -> Self {
        Self {
            leaf_voxel_m: 0.1,
            tile_voxels: 128,
            tile_triangle_budget: 16_384,
            simplify_error_voxels: 1.0,
            truncation_voxels: 3.0,
        }
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum LodError {
    #[error(transparent)]
    Field(#[from] TsdfError),
    #[error("LOD {field} must be {expected}, got {value}")]
    BadConfig {
        field: &'static str,
        expected: &'static str,
        value: f64,
    },
    #[error("nothing to build: no scan left a usable return in the field")]
    Empty,
}

impl LodConfig {
    pub fn validate(&self) -> Result<(), LodError> {
        let bad = |field, expected, value| LodError::BadConfig {
            field,
            expected,
            value,
        };
        if self.tile_voxels < 8 || !self.tile_voxels.is_multiple_of(8) || self.tile_voxels > 4096 {
            return Err(bad(
                "tile_voxels",
                "a multiple of 8 in [8, 4096]",
                f64::from(self.tile_voxels),
            ));
        }
        if self.tile_triangle_budget < 64 {
            return Err(bad(
                "tile_triangle_budget",
                "at least 64",
                self.tile_triangle_budget as f64,
            ));
        }
        if !(self.leaf_voxel_m.is_finite() && (0.005..=10.0).contains(&self.leaf_voxel_m)) {
            return Err(bad(
                "leaf_voxel_m",
                "in [0.005, 10] metres",
                self.leaf_voxel_m,
            ));
        }
        if !(self.truncation_voxels.is_finite() && (1.0..=16.0).contains(&self.truncation_voxels)) {
            return Err(bad(
                "truncation_voxels",
                "in [1, 16]",
                self.truncation_voxels,
            ));
        }
        if !(self.simplify_error_voxels.is_finite() && self.simplify_error_voxels >= 0.0) {
            return Err(bad(
                "simplify_error_voxels",
                "finite and not negative",
                self.simplify_error_voxels,
            ));
        }
        Ok(())
    }

    fn field(&self) -> TsdfConfig {
        TsdfConfig {
            voxel_m: self.leaf_voxel_m,
            truncation_voxels: self.truncation_voxels,
            ..TsdfConfig::default()
        }
    }
}

/// One tile of the hierarchy: its merged, simplified mesh and what a viewer needs to
/// choose it.
#[derive(Debug, Clone, PartialEq)]
pub struct LodNode {
    pub id: TileId,
    /// The surface in the tile, origin at the centre of its bounds.
    pub mesh: SurfaceMesh,
    /// World bounds of the mesh and of every descendant's (the footprint where all
    /// are empty).
    pub bounds_min_m: [f64; 3],
    pub bounds_max_m: [f64; 3],
    /// How far, in metres, drawing this tile instead of its children can move the
    /// surface: half its voxel (surface extraction) plus the simplification's error,
    /// and never less than any child's.
    pub geometric_error_m: f64,
    /// The voxel size the tile was merged at.
    pub voxel_m: f64,
    /// Triangles before simplification.
    pub merged_triangles: usize,
}

/// The whole tree: every tile that holds surface, by id.
#[derive(Debug, Clone, PartialEq)]
pub struct Hierarchy {
    pub layout: Layout,
    pub nodes: BTreeMap<TileId, LodNode>,
}

impl Hierarchy {
    /// The children of `id` that hold surface.
    pub fn children(&self, id: TileId) -> impl Iterator<Item = &LodNode> + '_ {
        id.children().into_iter().filter_map(|c| self.nodes.get(&c))
    }

    pub fn triangle_count(&self) -> usize {
        self.nodes.values().map(|n| n.mesh.triangle_count()).sum()
    }
}

/// Fuses registered scans into the leaf field, then builds the hierarchy from it.
#[derive(Debug, Clone)]
pub struct LodBuilder {
    config: LodConfig,
    field: Tsdf,
    scans: usize,
}

impl LodBuilder {
    pub fn new(config: LodConfig) -> Result<Self, LodError> {
        config.validate()?;
        Ok(Self {
            field: Tsdf::new(config.field())?,
            config,
            scans: 0,
        })
    }

    /// Fuses one registered scan; returns the voxel updates it made.
    pub fn add_scan(&mut self, scan: &TexelScan, world_from_scan: &Pose) -> usize {
        self.scans += 1;
        texel_surface::integrate_scan(&mut self.field, scan, world_from_scan)
    }

    /// Moves a scan whose pose was revised: out at `old`, in at `new` (loop closure
    /// revises poses while the model is being built).
    pub fn revise_scan(&mut self, scan: &TexelScan, old: &Pose, new: &Pose) -> usize {
        texel_surface::remove_scan(&mut self.field, scan, old)
            + texel_surface::integrate_scan(&mut self.field, scan, new)
    }

    /// Takes a scan out (it leaves the model).
    pub fn remove_scan(&mut self, scan: &TexelScan, world_from_scan: &Pose) -> usize {
        self.scans = self.scans.saturating_sub(1);
        texel_surface::remove_scan(&mut self.field, scan, world_from_scan)
    }

    pub fn scans(&self) -> usize {
        self.scans
    }

    /// Bytes the leaf field holds.
    pub fn heap_bytes(&self) -> usize {
        self.field.heap_bytes()
    }

    pub fn field(&self) -> &Tsdf {
        &self.field
    }

    /// The hierarchy of everything fused so far.
    pub fn build(self) -> Result<Hierarchy, LodError> {
        build_from_field(self.field, &self.config)
    }
}

/// The hierarchy over a leaf field.
pub fn build_from_field(field: Tsdf, config: &LodConfig) -> Result<Hierarchy, LodError> {
    config.validate()?;
    // 1. The tree that covers the field, and the field renamed so column [0, 0] is
    //    the root's corner (Liu §4.1.2: a quadtree over a regular grid of tiles).
    let (lo, hi) = field.bounds().ok_or(LodError::Empty)?;
    let layout = Layout::covering(
        [lo[0], lo[1]],
        [hi[0] + 1, hi[1] + 1],
        field.voxel_m(),
        config.tile_voxels,
    );
    let corner = layout.corner_leaf_voxels;
    let mut level_field = field.reanchored([corner[0], corner[1], 0])?;
    // 2. From the leaves up: cut each tile from its level's field and simplify it to
    //    the budget, so every level costs the same per tile (Liu §4.2); then halve
    //    the field's resolution for the level above.
    let mut nodes = BTreeMap::new();
    for level in (0..=layout.depth).rev() {
        for id in occupied_tiles(&level_field, &layout, level) {
            nodes.insert(id, build_tile(&level_field, &layout, id, config));
        }
        if level > 0 {
            level_field = level_field.downsampled();
        }
    }
    // 3. A parent bounds its children: its error is at least theirs (3D Tiles
    //    requires it, and selection by screen-space error relies on it to refine
    //    monotonically) and its box holds theirs (so a child is never in view
    //    while its parent is culled).
    for level in (0..layout.depth).rev() {
        let ids: Vec<TileId> = nodes
            .keys()
            .filter(|id| id.level == level)
            .copied()
            .collect();
        for id in ids {
            let children: Vec<(f64, [f64; 3], [f64; 3])> = id
                .children()
                .iter()
                .filter_map(|c| nodes.get(c))
                .map(|c| (c.geometric_error_m, c.bounds_min_m, c.bounds_max_m))
                .collect();
            if let Some(node) = nodes.get_mut(&id) {
                for (error, lo, hi) in children {
                    node.geometric_error_m = node.geometric_error_m.max(error);
                    for a in 0..3 {
                        node.bounds_min_m[a] = node.bounds_min_m[a].min(lo[a]);
                        node.bounds_max_m[a] = node.bounds_max_m[a].max(hi[a]);
                    }
                }
            }
        }
    }
    Ok(Hierarchy { layout, nodes })
}

/// Tiles of `level` whose columns hold observed voxels. A block of the field lies in
/// one tile: tiles are whole blocks wide and the field is anchored on a tile border.
fn occupied_tiles(field: &Tsdf, layout: &Layout, level: u8) -> BTreeSet<TileId> {
    field
        .block_corners()
        .filter_map(|c| layout.tile_of_column(level, [c[0], c[1]]))
        .collect()
}

fn build_tile(field: &Tsdf, layout: &Layout, id: TileId, config: &LodConfig) -> LodNode {
    let (lo, hi) = layout.columns(id);
    let (foot_lo, foot_hi) = layout.footprint(id);
    let centre = [
        0.5 * (foot_lo[0] + foot_hi[0]),
        0.5 * (foot_lo[1] + foot_hi[1]),
        field.origin_m()[2],
    ];
    let merged = extract(field, VoxelRegion { lo, hi }, centre);
    let voxel_m = field.voxel_m();
    let simplified = simplify(
        &merged,
        config.tile_triangle_budget,
        config.simplify_error_voxels * voxel_m,
    );
    let mut mesh = simplified.mesh;
    // The origin moved to the middle of the mesh, so offsets stay small.
    let mid = match mesh.local_bounds() {
        Some((l, h)) => [0, 1, 2].map(|a| centre[a] + 0.5 * (f64::from(l[a]) + f64::from(h[a]))),
        None => centre,
    };
    for p in &mut mesh.positions {
        for a in 0..3 {
            p[a] = (centre[a] + f64::from(p[a]) - mid[a]) as f32;
        }
    }
    mesh.origin_m = mid;
    // World bounds of the vertices as they will be read back.
    let (bounds_min_m, bounds_max_m) = match mesh.local_bounds() {
        Some((l, h)) => (
            [0, 1, 2].map(|a| mid[a] + f64::from(l[a])),
            [0, 1, 2].map(|a| mid[a] + f64::from(h[a])),
        ),
        None => (
            [foot_lo[0], foot_lo[1], centre[2]],
            [foot_hi[0], foot_hi[1], centre[2]],
        ),
    };
    LodNode {
        id,
        geometric_error_m: 0.5 * voxel_m + simplified.error_m,
        voxel_m,
        merged_triangles: merged.triangle_count(),
        mesh,
        bounds_min_m,
        bounds_max_m,
    }
}
