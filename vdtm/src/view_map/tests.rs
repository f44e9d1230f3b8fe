#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
use std::f64::consts::PI;

use super::*;

fn assert_orthonormal(f: &PolygonFrame) {
    for v in [f.normal, f.x, f.y] {
        assert!((v.norm() - 1.0).abs() < 1e-12, "{f:?}");
    }
    assert!(f.normal.dot(&f.x).abs() < 1e-12, "{f:?}");
    assert!(f.normal.dot(&f.y).abs() < 1e-12, "{f:?}");
    assert!(f.x.dot(&f.y).abs() < 1e-12, "{f:?}");
    assert!(
        (f.x.cross(&f.y) - f.normal).norm() < 1e-12,
        "right-handed: {f:?}"
    );
}

fn near(a: [f64; 2], b: [f64; 2]) -> bool {
    (a[0] - b[0]).abs() < 1e-12 && (a[1] - b[1]).abs() < 1e-12
}

#[test]
fn the_frame_of_a_normal_along_a_world_axis_is_orthonormal() {
    // n = ±y^W is Eq. 1's second case: x = x^W.
    let up = PolygonFrame::of_normal(Vector3::y()).unwrap();
    assert_eq!(up.x, Vector3::x());
    assert_orthonormal(&up);
    let down = PolygonFrame::of_normal(-Vector3::y() * 7.0).unwrap();
    assert_eq!(down.x, Vector3::x());
    assert_orthonormal(&down);
    // The other axes, and a normal within rounding of y^W.
    for n in [
        Vector3::x(),
        -Vector3::x(),
        Vector3::z(),
        -Vector3::z(),
        Vector3::new(1e-13, 1.0, -1e-13),
        Vector3::new(0.3, -0.2, 0.9),
    ] {
        assert_orthonormal(&PolygonFrame::of_normal(n).unwrap());
    }
    // Eq. 1's first case: x = y^W × n.
    let f = PolygonFrame::of_normal(Vector3::z()).unwrap();
    assert!((f.x - Vector3::x()).norm() < 1e-15 && (f.y - Vector3::y()).norm() < 1e-15);
    assert!(PolygonFrame::of_normal(Vector3::zeros()).is_none());
    assert!(PolygonFrame::of_normal(Vector3::new(f64::NAN, 1.0, 0.0)).is_none());
    assert!(PolygonFrame::of_normal(Vector3::new(f64::INFINITY, 1.0, 0.0)).is_none());
}

#[test]
fn a_degenerate_triangle_has_no_frame() {
    let (a, b) = (Point3::new(0.0, 0.0, 0.0), Point3::new(1.0, 0.0, 0.0));
    assert!(PolygonFrame::of_triangle(&a, &b, &Point3::new(2.0, 0.0, 0.0)).is_none());
    assert!(PolygonFrame::of_triangle(&a, &a, &a).is_none());
    let f = PolygonFrame::of_triangle(&a, &b, &Point3::new(0.0, 1.0, 0.0)).unwrap();
    assert!((f.normal - Vector3::z()).norm() < 1e-15);
}

#[test]
fn views_map_by_arc_length_from_the_normal() {
    let f = PolygonFrame::of_normal(Vector3::z()).unwrap();
    let c = Point3::new(10.0, -4.0, 2.0);
    let at = |d: Vector3<f64>| f.map_view(&c, &(c + d)).unwrap();
    assert!(near(at(Vector3::z() * 3.0), [0.0, 0.0]));
    assert!(near(at(Vector3::x() * 3.0), [PI / 2.0, 0.0]));
    assert!(near(at(Vector3::y() * 0.5), [0.0, PI / 2.0]));
    assert!(near(at(-Vector3::x()), [-PI / 2.0, 0.0]));
    // 45 degrees from the normal towards +x+y: arc π/4, split evenly.
    let p = at(Vector3::new(1.0, 1.0, 2f64.sqrt()));
    let e = PI / 4.0 / 2f64.sqrt();
    assert!(near(p, [e, e]), "{p:?}");
    // Straight behind: arc π with no azimuth.
    assert!(near(at(-Vector3::z()), [PI, 0.0]));
    // The eye on the centroid, or not finite: no direction.
    assert!(f.map_view(&c, &c).is_none());
    assert!(f.map_view(&c, &Point3::new(f64::NAN, 0.0, 0.0)).is_none());
}

/// Grid coordinates of vertex (i, j) for a side.
fn vertex_at(side: usize, i: usize, j: usize) -> [f64; 2] {
    let step = PI / (side - 1) as f64;
    [-PI / 2.0 + i as f64 * step, -PI / 2.0 + j as f64 * step]
}

fn sum(b: &Blend) -> f64 {
    b.iter().map(|(_, w)| w).sum()
}

#[test]
fn a_polygon_seen_by_one_view_takes_it_everywhere() {
    let map = ViewMap::build(&[(7, [0.2, -0.1])], 5).unwrap();
    for p in [[0.0, 0.0], [1.5, -1.5], [3.0, 3.0], vertex_at(5, 2, 2)] {
        let b = map.query(p);
        assert_eq!(b.iter().collect::<Vec<_>>(), vec![(7, 1.0)]);
    }
}

#[test]
fn on_a_grid_vertex_one_view_on_an_edge_two_inside_three() {
    // Side 3: vertices at -π/2, 0, π/2 per axis. Three views, one at each of the
    // vertices (0,0), (1,0) and (0,1) of the lower-left cell; the others go to the
    // nearest of them.
    let side = 3;
    let (a, b, c) = (
        vertex_at(side, 0, 0),
        vertex_at(side, 1, 0),
        vertex_at(side, 0, 1),
    );
    let map = ViewMap::build(&[(1, a), (2, b), (3, c)], side).unwrap();
    assert_eq!(map.vertex(0, 0), Some(1));
    assert_eq!(map.vertex(1, 0), Some(2));
    assert_eq!(map.vertex(0, 1), Some(3));
    assert_eq!(map.vertex(3, 0), None);
    // Exactly on a vertex: that view alone.
    let on = map.query(b);
    assert_eq!(on.len(), 1);
    assert_eq!(on.weight_of(2), 1.0);
    // On the edge between (0,0) and (1,0), a quarter of the way: two views.
    let q = [a[0] + 0.25 * (b[0] - a[0]), a[1]];
    let edge = map.query(q);
    assert_eq!(edge.len(), 2);
    assert!((edge.weight_of(1) - 0.75).abs() < 1e-12 && (edge.weight_of(2) - 0.25).abs() < 1e-12);
    // Inside the lower triangle: the barycentric coordinates.
    let step = PI / 2.0;
    let inside = map.query([a[0] + 0.2 * step, a[1] + 0.3 * step]);
    assert_eq!(inside.len(), 3);
    assert!((inside.weight_of(1) - 0.5).abs() < 1e-12);
    assert!((inside.weight_of(2) - 0.2).abs() < 1e-12);
    assert!((inside.weight_of(3) - 0.3).abs() < 1e-12);
    assert!((sum(&inside) - 1.0).abs() < 1e-12);
    // Heaviest first.
    let order: Vec<u32> = inside.iter().map(|(v, _)| v).collect();
    assert_eq!(order, vec![1, 3, 2]);
    // On the cell's diagonal: the two corners it joins.
    let diagonal = map.query([a[0] + 0.5 * step, a[1] + 0.5 * step]);
    assert_eq!(diagonal.weight_of(1), 0.0);
    assert!((sum(&diagonal) - 1.0).abs() < 1e-12);
}

#[test]
fn two_views_blend_across_the_boundary_between_them() {
    let map = ViewMap::build(&[(4, [-0.8, 0.0]), (9, [0.8, 0.0])], DEFAULT_SIDE).unwrap();
    let left = map.query([-1.0, 0.0]);
    assert_eq!(left.iter().collect::<Vec<_>>(), vec![(4, 1.0)]);
    // Between the grid columns at 0 (nearest both; the tie goes to the lower id) and
    // π/8 (nearest view 9): both.
    let middle = map.query([0.2, 0.01]);
    assert!(middle.weight_of(4) > 0.0 && middle.weight_of(9) > 0.0);
    assert!((sum(&middle) - 1.0).abs() < 1e-12);
}

#[test]
fn a_polygon_no_view_sees_has_no_map() {
    assert_eq!(ViewMap::build(&[], 5), Err(ViewMapError::NoViews));
    assert_eq!(
        ViewMap::build(&[(1, [f64::NAN, 0.0]), (2, [0.0, f64::INFINITY])], 5),
        Err(ViewMapError::NoViews)
    );
    assert_eq!(
        ViewMap::build(&[(1, [0.0, 0.0])], 1),
        Err(ViewMapError::Side(1))
    );
    assert_eq!(
        ViewMap::build(&[(1, [0.0, 0.0])], MAX_SIDE + 1),
        Err(ViewMapError::Side(MAX_SIDE + 1))
    );
    // A non-finite point among finite ones is left out.
    let map = ViewMap::build(&[(1, [f64::NAN, 0.0]), (2, [0.0, 0.0])], 5).unwrap();
    assert_eq!(
        map.query([0.3, 0.3]).iter().collect::<Vec<_>>(),
        vec![(2, 1.0)]
    );
}

#[test]
fn a_view_from_behind_or_nowhere_still_gets_valid_weights() {
    let frame = PolygonFrame::of_normal(Vector3::new(0.0, 0.0, 1.0)).unwrap();
    let c = Point3::origin();
    let views: Vec<(u32, [f64; 2])> = [
        (1, Point3::new(5.0, 0.0, 5.0)),
        (2, Point3::new(-5.0, 0.0, 5.0)),
        (3, Point3::new(0.0, 5.0, 5.0)),
    ]
    .iter()
    .map(|(id, eye)| (*id, frame.map_view(&c, eye).unwrap()))
    .collect();
    let map = ViewMap::build(&views, DEFAULT_SIDE).unwrap();
    let behind = [
        Point3::new(0.0, 0.0, -5.0),
        Point3::new(3.0, 1.0, -5.0),
        Point3::new(-1.0, -2.0, -0.1),
    ];
    for eye in behind {
        let p = frame.map_view(&c, &eye).unwrap();
        let b = map.query(p);
        assert!(!b.is_empty() && b.len() <= 3);
        assert!((sum(&b) - 1.0).abs() < 1e-12);
        assert!(
            b.iter()
                .all(|(v, w)| (1..=3).contains(&v) && (0.0..=1.0).contains(&w))
        );
    }
    for p in [[f64::NAN, 0.0], [f64::INFINITY, f64::NEG_INFINITY]] {
        let b = map.query(p);
        assert!((sum(&b) - 1.0).abs() < 1e-12, "{b:?}");
        assert_eq!(b, map.query([0.0, 0.0]));
    }
    assert_eq!(map.heap_bytes(), DEFAULT_SIDE * DEFAULT_SIDE * 4);
}
