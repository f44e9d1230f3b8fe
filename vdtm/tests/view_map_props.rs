//! Properties of the view maps over random polygons, views and viewpoints: weights
//! in [0, 1] summing to 1, only views that see the polygon, at most three, the
//! nearest view at every grid vertex, and weights that move no faster than the
//! viewpoint (Debevec 1998 §7's smoothness claim).
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use nalgebra::{Point3, Vector3};
use proptest::prelude::*;
use texel_vdtm::view_map::{DEFAULT_SIDE, HALF_SIDE_RAD};
use texel_vdtm::{PolygonFrame, ViewMap};

fn vector() -> impl Strategy<Value = Vector3<f64>> {
    (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64).prop_map(|(x, y, z)| Vector3::new(x, y, z))
}

/// A normal, sometimes exactly along a world axis (Eq. 1's special case).
fn normal() -> impl Strategy<Value = Vector3<f64>> {
    prop_oneof![
        vector().prop_filter("a direction", |v| v.norm() > 1e-3),
        Just(Vector3::y()),
        Just(-Vector3::y()),
        Just(Vector3::x()),
        Just(Vector3::z()),
    ]
}

/// Eyes in front of the polygon's plane (the views that see it).
fn views(n: Vector3<f64>) -> impl Strategy<Value = Vec<Point3<f64>>> {
    prop::collection::vec(vector(), 1..7).prop_map(move |offsets| {
        let n = n.normalize();
        offsets
            .into_iter()
            .map(|o| {
                let d = o - n * o.dot(&n) + n * (0.05 + o.norm());
                Point3::from(d * 4.0)
            })
            .collect()
    })
}

fn setup() -> impl Strategy<Value = (Vector3<f64>, Vec<Point3<f64>>, Point3<f64>, usize)> {
    normal().prop_flat_map(|n| {
        (
            Just(n),
            views(n),
            vector().prop_map(|v| Point3::from(v * 10.0)),
            prop_oneof![Just(2usize), Just(3), Just(DEFAULT_SIDE), Just(16)],
        )
    })
}

fn build(n: Vector3<f64>, eyes: &[Point3<f64>], side: usize) -> (PolygonFrame, ViewMap) {
    let frame = PolygonFrame::of_normal(n).unwrap();
    let c = Point3::origin();
    let mapped: Vec<(u32, [f64; 2])> = eyes
        .iter()
        .enumerate()
        .map(|(i, e)| (i as u32, frame.map_view(&c, e).unwrap()))
        .collect();
    (frame, ViewMap::build(&mapped, side).unwrap())
}

proptest! {
    #[test]
    fn weights_are_a_partition_of_one_over_seeing_views((n, eyes, virtual_eye, side) in setup()) {
        let (frame, map) = build(n, &eyes, side);
        // Any viewpoint, in front or behind (the origin itself has no direction).
        let p = frame.map_view(&Point3::origin(), &virtual_eye).unwrap_or([0.0, 0.0]);
        prop_assert!(p.iter().all(|c| c.is_finite()));
        let blend = map.query(p);
        prop_assert!(!blend.is_empty() && blend.len() <= 3);
        let total: f64 = blend.iter().map(|(_, w)| w).sum();
        prop_assert!((total - 1.0).abs() < 1e-12, "{blend:?}");
        for (view, w) in blend.iter() {
            prop_assert!((view as usize) < eyes.len());
            prop_assert!(w > 0.0 && w <= 1.0);
        }
        let weights: Vec<f64> = blend.iter().map(|(_, w)| w).collect();
        prop_assert!(weights.windows(2).all(|w| w[0] >= w[1]), "heaviest first");
    }

    #[test]
    fn each_grid_vertex_holds_the_nearest_view((n, eyes, _e, side) in setup()) {
        let (frame, map) = build(n, &eyes, side);
        let step = 2.0 * HALF_SIDE_RAD / (side - 1) as f64;
        let mapped: Vec<[f64; 2]> =
            eyes.iter().map(|e| frame.map_view(&Point3::origin(), e).unwrap()).collect();
        for j in 0..side {
            for i in 0..side {
                let at = [-HALF_SIDE_RAD + i as f64 * step, -HALF_SIDE_RAD + j as f64 * step];
                let d2 = |p: &[f64; 2]| (p[0] - at[0]).powi(2) + (p[1] - at[1]).powi(2);
                let held = map.vertex(i, j).unwrap() as usize;
                let best = mapped.iter().map(d2).fold(f64::INFINITY, f64::min);
                prop_assert!(d2(&mapped[held]) <= best + 1e-12);
                // Querying the vertex itself gives its view whole (to rounding of the
                // vertex's position).
                prop_assert!(map.query(at).weight_of(held as u32) >= 1.0 - 1e-12);
            }
        }
    }

    #[test]
    fn weights_move_no_faster_than_the_viewpoint(
        (n, eyes, _e, side) in setup(),
        p in (-2.0..2.0f64, -2.0..2.0f64),
        d in (-1e-3..1e-3f64, -1e-3..1e-3f64),
    ) {
        let (_, map) = build(n, &eyes, side);
        let (a, b) = (map.query([p.0, p.1]), map.query([p.0 + d.0, p.1 + d.1]));
        let change: f64 = (0..eyes.len() as u32)
            .map(|v| (a.weight_of(v) - b.weight_of(v)).abs())
            .sum();
        // Barycentric weights are piecewise linear with slope at most 2 per grid step
        // along each axis: a change of at most 4·|d|₁/step over the views.
        let step = 2.0 * HALF_SIDE_RAD / (side - 1) as f64;
        let bound = 4.0 * (d.0.abs() + d.1.abs()) / step + 1e-9;
        prop_assert!(change <= bound, "change {change} bound {bound}");
    }
}
