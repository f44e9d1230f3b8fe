//! The hierarchy over a street with known geometry: every tile at every level lies on
//! the true surface within its stated geometric error, errors and boxes nest, tiles
//! of one level partition the surface, and triangle counts stay comparable across
//! levels, 5,000 km from the origin as at it.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![allow(clippy::needless_range_loop)] // x, y and z side by side read clearer indexed

mod support;

use texel_lod::LodConfig;

const FAR: [f64; 3] = [5.0e6, 4.2e6, 120.0];

fn config() -> LodConfig {
    LodConfig {
        tile_voxels: 64,
        tile_triangle_budget: 4_000,
        ..LodConfig::default()
    }
}

#[test]
fn every_tile_lies_on_the_true_surface_within_its_geometric_error() {
    for offset in [[0.0; 3], FAR] {
        let h = support::street(60.0, offset, &config());
        assert!(h.top_lod >= 2, "top level {}", h.top_lod);
        let roots = h.roots();
        assert!(!roots.is_empty() && roots.len() <= 4, "{roots:?}");
        for node in h.nodes.values() {
            let mut worst: f64 = 0.0;
            for v in 0..node.mesh.vertex_count() {
                let p = node.mesh.world(v).unwrap();
                worst = worst.max(support::distance_to_truth(p, offset));
                for a in 0..3 {
                    assert!(
                        p[a] >= node.bounds_min_m[a] - 1e-6 && p[a] <= node.bounds_max_m[a] + 1e-6
                    );
                }
            }
            // Surface nets sit within half a voxel; simplification adds its own error.
            // Where the walls meet the ground, a coarse voxel rounds the corner by up
            // to a voxel: allowed on top.
            assert!(
                worst <= node.geometric_error_m + node.voxel_m + 1e-3,
                "{:?}: worst {worst:.3} m, error {:.3} m, voxel {} m",
                node.id,
                node.geometric_error_m,
                node.voxel_m
            );
        }
    }
}

#[test]
fn errors_and_boxes_nest_and_levels_partition_the_surface() {
    let h = support::street(60.0, [0.0; 3], &config());
    for node in h.nodes.values() {
        if let Some(parent) = node.id.parent().filter(|p| p.lod <= h.top_lod) {
            let p = h.nodes.get(&parent).expect("every tile's parent exists");
            assert!(p.geometric_error_m >= node.geometric_error_m);
            for a in 0..3 {
                assert!(p.bounds_min_m[a] <= node.bounds_min_m[a]);
                assert!(p.bounds_max_m[a] >= node.bounds_max_m[a]);
            }
            assert!(p.voxel_m == 2.0 * node.voxel_m);
        }
        // A tile's surface stays within its footprint (one voxel of slack: a cell
        // vertex on the border may sit in the neighbour's half of the cell).
        let (lo, hi) = h.grid.footprint(node.id);
        for v in 0..node.mesh.vertex_count() {
            let p = node.mesh.world(v).unwrap();
            for a in 0..2 {
                assert!(p[a] >= lo[a] - node.voxel_m && p[a] <= hi[a] + node.voxel_m);
            }
        }
    }
    // Coarser levels see less detail: the merged (pre-simplification) surface of a
    // level shrinks as the voxel grows.
    let merged = |level: u8| -> usize {
        h.nodes
            .values()
            .filter(|n| n.id.lod == level)
            .map(|n| n.merged_triangles)
            .sum()
    };
    let top = h.top_lod;
    assert!(
        merged(top) < merged(0) / 4,
        "{} vs {}",
        merged(top),
        merged(0)
    );
}

#[test]
fn triangle_counts_stay_comparable_across_levels() {
    let config = config();
    let h = support::street(120.0, [0.0; 3], &config);
    for level in 0..=h.top_lod {
        let tiles: Vec<_> = h.nodes.values().filter(|n| n.id.lod == level).collect();
        let most = tiles.iter().map(|n| n.mesh.triangle_count()).max().unwrap();
        // Simplification stops at its error bound (one voxel) before the budget where
        // the borders of unseen patches, which stay locked, hold it: half over at
        // most.
        assert!(
            most <= config.tile_triangle_budget * 3 / 2,
            "level {level}: a tile of {most} triangles"
        );
    }
    // The root alone draws the whole street at a fraction of the leaves' cost.
    let leaves: usize = h
        .nodes
        .values()
        .filter(|n| n.id.lod == 0)
        .map(|n| n.mesh.triangle_count())
        .sum();
    let root: usize = h
        .roots()
        .iter()
        .map(|id| h.nodes[id].mesh.triangle_count())
        .sum();
    assert!(root * 4 < leaves, "root {root}, leaves {leaves}");
}

#[test]
fn bad_configs_and_empty_fields_are_refused() {
    let bad = LodConfig {
        tile_voxels: 60,
        ..LodConfig::default()
    };
    assert!(
        texel_lod::LodModel::new(bad)
            .unwrap_err()
            .to_string()
            .contains("tile_voxels")
    );
    let empty = texel_surface::Tsdf::new(texel_surface::TsdfConfig::default()).unwrap();
    let e = texel_lod::build_from_field(empty, &LodConfig::default()).unwrap_err();
    assert_eq!(e, texel_lod::LodError::Empty);
}
