//! The hierarchy built as scans arrive: rebuilding a bounded number of tiles at a time
//! while scans keep coming ends in the same tree as one build of everything; a scan
//! fused at a wrong pose and then revised leaves the tree a correct build would give;
//! the queue reports its lag and rebuilds the coarsest tiles first.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use texel_lod::{Hierarchy, LodConfig, LodModel};
use texel_surface::Sample;

fn config() -> LodConfig {
    LodConfig {
        tile_voxels: 64,
        tile_triangle_budget: 3_000,
        ..LodConfig::default()
    }
}

fn worst_distance(h: &Hierarchy) -> f64 {
    let mut worst: f64 = 0.0;
    for node in h.nodes.values().filter(|n| n.id.lod == 0) {
        for v in 0..node.mesh.vertex_count() {
            worst = worst.max(support::distance_to_truth(
                node.mesh.world(v).unwrap(),
                [0.0; 3],
            ));
        }
    }
    worst
}

#[test]
fn rebuilding_a_few_tiles_at_a_time_ends_where_one_build_does() {
    let stops = support::street_stops(40.0, 1.0, [0.0; 3]);
    let mut live = LodModel::new(config()).unwrap();
    let mut lag = Vec::new();
    for stop in &stops {
        live.add_samples(stop);
        let pending = live.pending_tiles();
        let done = live.rebuild(3);
        // The lag reported is the work a rebuild finds.
        assert_eq!(live.pending_tiles(), pending - done);
        lag.push(live.pending_tiles());
    }
    assert!(
        lag.iter().any(|&l| l > 0),
        "the queue never lagged: {lag:?}"
    );
    live.rebuild(usize::MAX);
    assert_eq!(live.pending_tiles(), 0);
    let mut once = LodModel::new(config()).unwrap();
    for stop in &stops {
        once.add_samples(stop);
    }
    once.rebuild(usize::MAX);
    assert_eq!(live.hierarchy().unwrap(), once.hierarchy().unwrap());
}

#[test]
fn a_revised_pose_moves_the_surface_and_rebuilds_what_it_touched() {
    let stops = support::street_stops(30.0, 1.0, [0.0; 3]);
    // Stop 12 was placed 0.6 m to the side, then loop closure corrected it.
    let shifted = |samples: &[Sample]| -> Vec<Sample> {
        samples
            .iter()
            .map(|s| Sample {
                point_m: [s.point_m[0], s.point_m[1] + 0.6, s.point_m[2]],
                centre_m: [s.centre_m[0], s.centre_m[1] + 0.6, s.centre_m[2]],
                ..*s
            })
            .collect()
    };
    let mut model = LodModel::new(config()).unwrap();
    for (i, stop) in stops.iter().enumerate() {
        if i == 12 {
            model.add_samples(&shifted(stop));
        } else {
            model.add_samples(stop);
        }
    }
    model.rebuild(usize::MAX);
    let wrong = model.hierarchy().unwrap();
    model.remove_samples(&shifted(&stops[12]));
    model.add_samples(&stops[12]);
    assert!(model.pending_tiles() > 0);
    model.rebuild(usize::MAX);
    let revised = model.hierarchy().unwrap();
    let mut right = LodModel::new(config()).unwrap();
    for stop in &stops {
        right.add_samples(stop);
    }
    right.rebuild(usize::MAX);
    let right = right.hierarchy().unwrap();
    // The misplaced scan showed: the surface pulled off the truth where it fused.
    let (w_wrong, w_right) = (worst_distance(&wrong), worst_distance(&right));
    assert!(
        w_wrong > 0.1 && w_wrong > 2.0 * w_right,
        "{w_wrong} vs {w_right}"
    );
    // Taking samples out is exact up to rounding: the same tiles, the same counts to a
    // percent, and the surface back on the truth.
    assert_eq!(
        revised.nodes.keys().collect::<Vec<_>>(),
        right.nodes.keys().collect::<Vec<_>>()
    );
    for (id, node) in &revised.nodes {
        let other = right.nodes[id].mesh.triangle_count() as f64;
        let mine = node.mesh.triangle_count() as f64;
        assert!(
            (mine - other).abs() <= 0.01 * other + 2.0,
            "{id:?}: {mine} vs {other}"
        );
    }
    let w_revised = worst_distance(&revised);
    assert!(w_revised <= w_right + 0.01, "{w_revised} vs {w_right}");
}

#[test]
fn the_queue_reports_its_lag_and_rebuilds_the_coarsest_tiles_first() {
    let stops = support::street_stops(60.0, 1.0, [0.0; 3]);
    let mut model = LodModel::new(config()).unwrap();
    for stop in &stops {
        model.add_samples(stop);
    }
    assert!(model.pending_tiles() > 0);
    assert!(
        model.hierarchy().is_err(),
        "nothing is built before a rebuild"
    );
    // The first rebuilds reach the top of the tree: an overview before any detail.
    assert_eq!(model.rebuild(6), 6);
    let early = model.hierarchy().unwrap();
    let coarsest = early.nodes.keys().map(|id| id.lod).min().unwrap();
    assert!(coarsest > 0, "detail came first: {:?}", early.nodes.keys());
    let before = model.pending_tiles();
    assert!(before > 0);
    model.rebuild(usize::MAX);
    assert_eq!(model.pending_tiles(), 0);
    assert!(model.hierarchy().unwrap().nodes.len() >= early.nodes.len() + before - 1);
    assert!(model.field_bytes() > 0 && model.mesh_bytes() > 0);
}

#[test]
fn tiles_not_ready_stay_queued_and_the_rest_are_rebuilt() {
    let stops = support::street_stops(40.0, 1.0, [0.0; 3]);
    let mut model = LodModel::new(config()).unwrap();
    for stop in &stops {
        model.add_samples(stop);
    }
    // Only the finest tiles may be rebuilt: the coarser ones wait, still queued.
    let rebuilt = model.rebuild_ready(usize::MAX, &|id| id.lod == 0);
    assert!(!rebuilt.is_empty());
    assert!(rebuilt.iter().all(|id| id.lod == 0), "{rebuilt:?}");
    let waiting = model.pending_tile_ids();
    assert!(!waiting.is_empty());
    assert!(waiting.iter().all(|id| id.lod > 0), "{waiting:?}");
    assert_eq!(model.pending_tiles(), waiting.len());
    // Then the coarse ones, at most two, coarsest first.
    let next = model.rebuild_ready(2, &|_| true);
    assert_eq!(next.len(), 2.min(waiting.len()));
    let top = waiting.iter().map(|id| id.lod).max().unwrap();
    assert_eq!(next[0].lod, top);
    // Whatever the order, the tree ends where one build of everything does.
    model.rebuild(usize::MAX);
    let mut once = LodModel::new(config()).unwrap();
    for stop in &stops {
        once.add_samples(stop);
    }
    once.rebuild(usize::MAX);
    assert_eq!(model.hierarchy().unwrap(), once.hierarchy().unwrap());
}
