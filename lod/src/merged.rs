//! The whole model as one merged surface (what view-dependent texture mapping
//! textures): the scans fused into the tree's field at one voxel size, the finest
//! level's tiles extracted unsimplified and joined into one mesh.

use texel::{Pose, TexelScan};
use texel_surface::SurfaceMesh;

use crate::build::{Hierarchy, LodConfig, LodError};
use crate::model::LodModel;

/// The tree's settings that keep the merged surface whole at `voxel_m`: no
/// simplification below the leaf voxel's own error, no atlases (the surface is
/// textured from the images themselves).
pub fn whole_surface_config(voxel_m: f64) -> LodConfig {
    LodConfig {
        leaf_voxel_m: voxel_m,
        tile_triangle_budget: usize::MAX / 4,
        atlas_max_px: 0,
        ..LodConfig::default()
    }
}

/// The scans, placed by their poses, fused at `voxel_m` into one mesh (vertices on
/// tile borders stay apart; positions relative to the first tile's origin).
pub fn merged_surface<'a>(
    placed: impl IntoIterator<Item = (&'a TexelScan, &'a Pose)>,
    voxel_m: f64,
) -> Result<SurfaceMesh, LodError> {
    let mut model = LodModel::new(whole_surface_config(voxel_m))?;
    for (scan, pose) in placed {
        model.add_scan(scan, pose);
    }
    model.rebuild(usize::MAX);
    Ok(join_finest(&model.hierarchy()?))
}

/// The finest level's tiles joined into one mesh.
fn join_finest(h: &Hierarchy) -> SurfaceMesh {
    let nodes: Vec<_> = h.nodes.values().filter(|n| n.id.lod == 0).collect();
    let origin = nodes.first().map_or([0.0; 3], |n| n.mesh.origin_m);
    let mut out = SurfaceMesh::empty(origin);
    for node in nodes {
        let m = &node.mesh;
        let Ok(base) = u32::try_from(out.positions.len()) else {
            break;
        };
        // Tile origins are near each other: the f64 shift keeps f32 positions exact
        // to the voxel's precision.
        let shift = [0, 1, 2].map(|a| m.origin_m[a] - origin[a]);
        out.positions.extend(
            m.positions
                .iter()
                .map(|p| [0, 1, 2].map(|a| (f64::from(p[a]) + shift[a]) as f32)),
        );
        out.colours.extend(&m.colours);
        out.triangles
            .extend(m.triangles.iter().map(|t| t.map(|v| v + base)));
    }
    out
}
