//! What the hierarchy is made of: its configuration, its tiles (a merged, simplified
//! mesh each, Liu 2014 §4.2) and the tree they form; and how one tile is cut from its
//! level's field.

use std::collections::BTreeMap;

use texel_surface::{SurfaceMesh, Tsdf, TsdfConfig, TsdfError, VoxelRegion, extract, simplify};
use thiserror::Error;

use crate::atlas::{AtlasParams, MAX_ATLAS_PX, TileTexture, paint_atlas, plan_atlas};
use crate::fields::Fields;
use crate::select::TileInfo;
use crate::tree::{Grid, MAX_LOD, TileId};

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
    /// The coarsest level kept: tiles of `tile_voxels · leaf_voxel_m · 2^max_lod`
    /// (12.8 m · 2^10 ≈ 13 km with the defaults).
    pub max_lod: u8,
    /// Largest side of a tile's texture atlas, texels; 0 leaves tiles coloured per
    /// vertex only. 1024² holds a full triangle budget's charts (at least 3×3 texels
    /// each) with room for their detail.
    pub atlas_max_px: u32,
    /// The finest atlas texel, in leaf voxels (doubled per try until the atlas fits).
    /// One: the leaf field's colour is a mean over a voxel, so finer texels would only
    /// resample its interpolation at four times the bytes.
    pub atlas_texel_voxels: f64,
}

impl Default for LodConfig {
    fn default() -> Self {
        Self {
            leaf_voxel_m: 0.1,
            tile_voxels: 128,
            tile_triangle_budget: 16_384,
            simplify_error_voxels: 1.0,
            truncation_voxels: 3.0,
            max_lod: 10,
            atlas_max_px: 1024,
            atlas_texel_voxels: 1.0,
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
    #[error("the field to build from starts at {origin_m:?}, not at the world origin")]
    FieldNotAnchored { origin_m: [f64; 3] },
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
        if self.max_lod > MAX_LOD {
            return Err(bad("max_lod", "at most 24", f64::from(self.max_lod)));
        }
        if !(self.simplify_error_voxels.is_finite() && self.simplify_error_voxels >= 0.0) {
            return Err(bad(
                "simplify_error_voxels",
                "finite and not negative",
                self.simplify_error_voxels,
            ));
        }
        if self.atlas_max_px != 0 && !(16..=MAX_ATLAS_PX).contains(&self.atlas_max_px) {
            return Err(bad(
                "atlas_max_px",
                "0 (no atlas) or in [16, 4096]",
                f64::from(self.atlas_max_px),
            ));
        }
        if !(self.atlas_texel_voxels.is_finite()
            && (0.25..=1024.0).contains(&self.atlas_texel_voxels))
        {
            return Err(bad(
                "atlas_texel_voxels",
                "in [0.25, 1024]",
                self.atlas_texel_voxels,
            ));
        }
        Ok(())
    }

    pub(crate) fn grid(&self) -> Grid {
        Grid {
            leaf_voxel_m: self.leaf_voxel_m,
            tile_voxels: self.tile_voxels,
        }
    }

    pub(crate) fn field(&self) -> TsdfConfig {
        TsdfConfig {
            voxel_m: self.leaf_voxel_m,
            truncation_voxels: self.truncation_voxels,
        }
    }
}

/// One tile of the hierarchy: its merged, simplified mesh and what a viewer needs to
/// choose it.
#[derive(Debug, Clone, PartialEq)]
pub struct LodNode {
    pub id: TileId,
    /// The surface in the tile, origin at the middle of its bounds.
    pub mesh: SurfaceMesh,
    /// World bounds of the mesh and, in a [`Hierarchy`], of every descendant's (the
    /// footprint where all are empty).
    pub bounds_min_m: [f64; 3],
    pub bounds_max_m: [f64; 3],
    /// How far, in metres, drawing this tile instead of its children can move the
    /// surface: half its voxel (surface extraction) plus the simplification's error,
    /// and, in a [`Hierarchy`], never less than any child's.
    pub geometric_error_m: f64,
    /// The voxel size the tile was merged at.
    pub voxel_m: f64,
    /// Triangles before simplification.
    pub merged_triangles: usize,
    /// The tile's colour as an atlas (then the mesh has one vertex per triangle
    /// corner, and the texture one coordinate per vertex); `None` where the tile is
    /// coloured per vertex only.
    pub texture: Option<TileTexture>,
}

/// A snapshot of the tree: every tile that holds surface up to the top level, by id.
/// The top level's tiles (at most four) hang under one root without content.
#[derive(Debug, Clone, PartialEq)]
pub struct Hierarchy {
    pub grid: Grid,
    pub top_lod: u8,
    pub nodes: BTreeMap<TileId, LodNode>,
}

impl LodNode {
    /// What selection needs of the tile: its bounds and error.
    pub fn info(&self) -> TileInfo {
        TileInfo {
            bounds_min_m: self.bounds_min_m,
            bounds_max_m: self.bounds_max_m,
            geometric_error_m: self.geometric_error_m,
        }
    }
}

impl Hierarchy {
    /// Tiles of the top level.
    pub fn roots(&self) -> Vec<TileId> {
        self.nodes
            .keys()
            .filter(|id| id.lod == self.top_lod)
            .copied()
            .collect()
    }

    /// The children of `id` that hold surface.
    pub fn children(&self, id: TileId) -> impl Iterator<Item = &LodNode> + '_ {
        id.children()
            .into_iter()
            .flatten()
            .filter_map(|c| self.nodes.get(&c))
    }

    pub fn triangle_count(&self) -> usize {
        self.nodes.values().map(|n| n.mesh.triangle_count()).sum()
    }

    /// The tree over `built` tiles up to level `top_lod`: a parent's error is at least its children's (3D Tiles
    /// requires it, and selection by screen-space error relies on it to refine
    /// monotonically) and its box holds theirs (a child is never in view while its
    /// parent is culled).
    pub fn over(
        grid: Grid,
        built: &BTreeMap<TileId, LodNode>,
        top_lod: u8,
    ) -> Result<Hierarchy, LodError> {
        if !built.keys().any(|id| id.lod <= top_lod) {
            return Err(LodError::Empty);
        }
        let mut nodes: BTreeMap<TileId, LodNode> = built
            .iter()
            .filter(|(id, _)| id.lod <= top_lod)
            .map(|(id, n)| (*id, n.clone()))
            .collect();
        let nested = nest(
            nodes.iter().map(|(id, n)| (*id, n.info())).collect(),
            top_lod,
        );
        for (id, info) in nested {
            if let Some(node) = nodes.get_mut(&id) {
                node.bounds_min_m = info.bounds_min_m;
                node.bounds_max_m = info.bounds_max_m;
                node.geometric_error_m = info.geometric_error_m;
            }
        }
        Ok(Hierarchy {
            grid,
            top_lod,
            nodes,
        })
    }
}

/// Nests tiles' bounds and errors up to `top_lod`, finest first: a parent's error
/// becomes at least each child's and its box grows to hold theirs.
pub fn nest(mut infos: BTreeMap<TileId, TileInfo>, top_lod: u8) -> BTreeMap<TileId, TileInfo> {
    infos.retain(|id, _| id.lod <= top_lod);
    for lod in 1..=top_lod {
        let ids: Vec<TileId> = infos.keys().filter(|id| id.lod == lod).copied().collect();
        for id in ids {
            let children: Vec<TileInfo> = id
                .children()
                .into_iter()
                .flatten()
                .filter_map(|c| infos.get(&c).copied())
                .collect();
            if let Some(info) = infos.get_mut(&id) {
                for child in children {
                    info.geometric_error_m = info.geometric_error_m.max(child.geometric_error_m);
                    for a in 0..3 {
                        info.bounds_min_m[a] = info.bounds_min_m[a].min(child.bounds_min_m[a]);
                        info.bounds_max_m[a] = info.bounds_max_m[a].max(child.bounds_max_m[a]);
                    }
                }
            }
        }
    }
    infos
}

/// The hierarchy over a leaf field (anchored at the world origin, as
/// [`Tsdf::new`] makes it).
pub fn build_from_field(field: Tsdf, config: &LodConfig) -> Result<Hierarchy, LodError> {
    let mut model = crate::model::LodModel::from_field(field, config)?;
    model.rebuild(usize::MAX);
    model.hierarchy()
}

/// Cuts tile `id` from its level's field (`fields`, one per level, finest first) and
/// simplifies it to the budget, so every level costs the same per tile (Liu §4.2);
/// then colours it from the finer levels into its atlas. `None` when the tile's level
/// has no field. The tile's own columns (and one voxel round them) must be in memory;
/// the level its atlas is coloured from is brought back here.
pub(crate) fn build_tile(
    fields: &mut Fields,
    grid: &Grid,
    id: TileId,
    config: &LodConfig,
) -> Option<LodNode> {
    let field = fields.level(usize::from(id.lod))?;
    let (lo, hi) = grid.columns(id);
    let (foot_lo, foot_hi) = grid.footprint(id);
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
    let geometric_error_m = 0.5 * voxel_m + simplified.error_m;
    let params = AtlasParams {
        texel_m: config.leaf_voxel_m * config.atlas_texel_voxels,
        max_px: config.atlas_max_px,
        lod: id.lod,
        // The mesh lies within its error of the surface, and the colour within the
        // band round it.
        search_m: geometric_error_m + field.truncation_m(),
    };
    let voxels_m: Vec<f64> = fields.levels().iter().map(Tsdf::voxel_m).collect();
    let plan = (config.atlas_max_px > 0)
        .then(|| plan_atlas(&mesh, &voxels_m, &params))
        .flatten();
    let atlas = plan.map(|plan| {
        // The colour is searched for within `search_m` of the mesh, and read
        // trilinearly a voxel round that.
        let reach_m = params.search_m + 2.0 * voxels_m.get(plan.level).copied().unwrap_or(0.0);
        let columns = fields.level(plan.level).map(|f| {
            let lo = f.index_of([bounds_min_m[0] - reach_m, bounds_min_m[1] - reach_m, 0.0]);
            let hi = f.index_of([bounds_max_m[0] + reach_m, bounds_max_m[1] + reach_m, 0.0]);
            (
                [lo[0], lo[1]],
                [hi[0].saturating_add(1), hi[1].saturating_add(1)],
            )
        });
        if let Some((lo, hi)) = columns {
            fields.page_in_columns(plan.level, lo, hi);
        }
        paint_atlas(plan, &mesh, fields.levels(), &params)
    });
    let texture = match atlas {
        Some(atlas) => {
            mesh = atlas.mesh;
            Some(atlas.texture)
        }
        None => None,
    };
    Some(LodNode {
        id,
        geometric_error_m,
        voxel_m,
        merged_triangles: merged.triangle_count(),
        mesh,
        bounds_min_m,
        bounds_max_m,
        texture,
    })
}
