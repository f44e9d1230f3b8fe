//! Tests of the primitives: intersections, bounds, texture coordinates, and the
//! probe that traversals keep their winners' hits from.

use super::*;

fn ray(o: [f64; 3], d: [f64; 3]) -> Ray {
    Ray {
        origin: Point3::new(o[0], o[1], o[2]),
        dir: Vector3::new(d[0], d[1], d[2]).normalize(),
    }
}

#[test]
fn sphere_hits_front_and_back() {
    let s = Primitive {
        shape: Shape::Sphere {
            center: Point3::new(0.0, 0.0, 5.0),
            radius: 1.0,
            axis_x: Vector3::x(),
            axis_y: Vector3::y(),
            axis_z: Vector3::z(),
        },
        object: 0,
        material: 0,
    };
    let h = s
        .intersect(&ray([0.0; 3], [0.0, 0.0, 1.0]), f64::INFINITY)
        .unwrap();
    assert!((h.distance_m - 4.0).abs() < 1e-12);
    assert!((h.normal - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
    // From inside: the far wall.
    let h = s
        .intersect(&ray([0.0, 0.0, 5.0], [1.0, 0.0, 0.0]), f64::INFINITY)
        .unwrap();
    assert!((h.distance_m - 1.0).abs() < 1e-12);
    assert!(
        s.intersect(&ray([0.0; 3], [0.0, 1.0, 0.0]), f64::INFINITY)
            .is_none()
    );
}

#[test]
fn cylinder_side_and_cap() {
    let c = Primitive {
        shape: Shape::Cylinder {
            center: Point3::new(0.0, 0.0, 0.0),
            radius: 0.5,
            half_height: 1.0,
            axis_x: Vector3::x(),
            axis_y: Vector3::y(),
            axis_z: Vector3::z(),
        },
        object: 0,
        material: 0,
    };
    let h = c
        .intersect(&ray([3.0, 0.0, 0.2], [-1.0, 0.0, 0.0]), f64::INFINITY)
        .unwrap();
    assert!((h.distance_m - 2.5).abs() < 1e-12);
    let h = c
        .intersect(&ray([0.1, 0.0, 4.0], [0.0, 0.0, -1.0]), f64::INFINITY)
        .unwrap();
    assert!((h.distance_m - 3.0).abs() < 1e-12);
    assert_eq!(h.normal, Vector3::z());
    assert!(
        c.intersect(&ray([3.0, 0.0, 1.5], [-1.0, 0.0, 0.0]), f64::INFINITY)
            .is_none()
    );
}

/// One primitive of every shape, near the origin.
fn one_of_each() -> Vec<Primitive> {
    let mut out = vec![
        parallelogram(
            Point3::new(-1.0, -0.5, 2.0),
            Vector3::new(2.0, 0.3, 0.0),
            Vector3::new(0.1, 1.5, 0.4),
            0,
            0,
        )
        .unwrap(),
        triangle(
            [
                Point3::new(-1.0, -1.0, 1.0),
                Point3::new(1.5, -0.5, 1.5),
                Point3::new(0.0, 1.0, 2.5),
            ],
            [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]],
            1,
            1,
        )
        .unwrap(),
    ];
    let axes = (Vector3::x(), Vector3::y(), Vector3::z());
    out.push(Primitive {
        shape: Shape::InfinitePlane {
            origin: Point3::new(0.0, 0.0, 3.0),
            axis_u: axes.0,
            axis_v: axes.1,
            normal: axes.2,
        },
        object: 2,
        material: 2,
    });
    out.push(Primitive {
        shape: Shape::Sphere {
            center: Point3::new(0.3, 0.2, 2.0),
            radius: 0.8,
            axis_x: axes.0,
            axis_y: axes.1,
            axis_z: axes.2,
        },
        object: 3,
        material: 3,
    });
    out.push(Primitive {
        shape: Shape::Cylinder {
            center: Point3::new(-0.2, 0.1, 2.2),
            radius: 0.6,
            half_height: 0.7,
            axis_x: axes.0,
            axis_y: axes.2,
            axis_z: -axes.1,
        },
        object: 4,
        material: 4,
    });
    out
}

proptest::proptest! {
    /// What traversals keep from `probe` is exactly what `distance` and
    /// `intersect` give: the same distance, and for flat shapes the same hit
    /// (curved ones leave it to `intersect`).
    #[test]
    fn probing_agrees_with_distance_and_intersect(
        o in proptest::array::uniform3(-1.5f64..1.5),
        d in proptest::array::uniform3(-1.0f64..1.0),
        t_max in 0.5f64..6.0,
    ) {
        let dir = Vector3::from(d);
        proptest::prop_assume!(dir.norm() > 1e-3);
        let r = ray(o, d);
        for p in one_of_each() {
            let probed = p.probe(&r, t_max);
            proptest::prop_assert_eq!(probed.map(|(t, _)| t), p.distance(&r, t_max));
            let flat = !matches!(p.shape, Shape::Sphere { .. } | Shape::Cylinder { .. });
            if let Some((_, hit)) = probed {
                proptest::prop_assert_eq!(hit.is_some(), flat);
                proptest::prop_assert_eq!(
                    hit.or_else(|| p.intersect(&r, f64::INFINITY)),
                    p.intersect(&r, t_max)
                );
            }
        }
    }
}

/// `t_max` stepped `ulps` representable values up (positive) or down from `t`.
fn ulps_from(t: f64, ulps: i32) -> f64 {
    let mut v = t;
    for _ in 0..ulps.unsigned_abs() {
        v = if ulps > 0 { v.next_up() } else { v.next_down() };
    }
    v
}

proptest::proptest! {
    /// The division-free rejection of plane-like hits never drops one the division
    /// would keep: whenever it says out of range, the quotient is out of range too,
    /// with `t_max` within a few ulps of the quotient (where rounding decides), at
    /// the quotient scaled by up to ±30 %, or infinite; and quotients at, just above
    /// and below zero and `MIN_HIT_DISTANCE`.
    #[test]
    fn division_free_rejection_is_conservative(
        num in -1.0e3f64..1.0e3,
        denom in -1.0f64..1.0,
        ulps in -6i32..=6,
        scale in 0.7f64..1.3,
        pick in 0u8..4,
    ) {
        proptest::prop_assume!(denom != 0.0);
        let nums = [num, 0.0, -0.0, MIN_HIT_DISTANCE * denom];
        for num in nums {
            let q = num / denom;
            for t_max in [ulps_from(q, ulps), q * scale, f64::INFINITY, ulps_from(q.abs(), ulps)] {
                if surely_out_of_range(num, denom, t_max) {
                    proptest::prop_assert!(!in_range(q, t_max), "{num} / {denom} vs {t_max}");
                }
            }
        }
        // And it does reject what is clearly out: behind the origin, or beyond t_max.
        let behind = -(1.0 + num.abs()) * denom.signum();
        proptest::prop_assert!(surely_out_of_range(behind, denom, 1.0e9));
        let q = (1.0 + num.abs()) * denom.signum() / denom;
        let beyond = q * [1.01, 2.0, 10.0, 1.0e6][usize::from(pick)];
        proptest::prop_assert!(surely_out_of_range(beyond * denom, denom, q));
    }
}

#[test]
fn parallelogram_bounds_and_uv() {
    let p = parallelogram(
        Point3::new(-1.0, -1.0, 2.0),
        Vector3::new(2.0, 0.0, 0.0),
        Vector3::new(0.0, 2.0, 0.0),
        3,
        4,
    )
    .unwrap();
    let h = p
        .intersect(&ray([0.5, 0.25, 0.0], [0.0, 0.0, 1.0]), f64::INFINITY)
        .unwrap();
    assert!((h.distance_m - 2.0).abs() < 1e-12);
    assert!((h.uv_m[0] - 0.5).abs() < 1e-12 && (h.uv_m[1] - 0.25).abs() < 1e-12);
    assert_eq!((h.object, h.material), (3, 4));
    assert!(
        p.intersect(&ray([1.5, 0.0, 0.0], [0.0, 0.0, 1.0]), f64::INFINITY)
            .is_none()
    );
    assert!(
        p.intersect(&ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]), 1.5)
            .is_none()
    );
}
