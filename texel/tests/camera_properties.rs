//! Property tests of the camera model: projection inverts unprojection over whole
//! images under strong distortion, nothing non-finite comes out of finite input, and
//! pixels beyond the distortion model's valid domain are reported.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use nalgebra::{Vector2, Vector3};
use proptest::prelude::*;
use texel::camera::{ProjectError, UnprojectError};
use texel::{Distortion, PinholeCamera, PlumbBob};

fn camera(fx: f64, aspect: f64, cx_off: f64, cy_off: f64, d: PlumbBob) -> PinholeCamera {
    PinholeCamera {
        width: 640,
        height: 480,
        fx,
        fy: fx * aspect,
        cx: 319.5 + cx_off,
        cy: 239.5 + cy_off,
        skew: 0.0,
        distortion: Distortion::PlumbBob(d),
    }
}

fn plumb_bob() -> impl Strategy<Value = PlumbBob> {
    (
        -0.45f64..0.3,
        -0.05f64..0.25,
        -0.004f64..0.004,
        -0.004f64..0.004,
        -0.03f64..0.03,
    )
        .prop_map(|(k1, k2, p1, p2, k3)| PlumbBob { k1, k2, p1, p2, k3 })
}

/// The largest distorted radius the radial model reaches inside its domain.
fn max_distorted_radius(d: &PlumbBob) -> f64 {
    match d.max_radius_squared() {
        None => f64::INFINITY,
        Some(m) => {
            let r = m.sqrt();
            r * (1.0 + m * (d.k1 + m * (d.k2 + m * d.k3)))
        }
    }
}

fn corners_and_edges(c: &PinholeCamera) -> Vec<Vector2<f64>> {
    let (w, h) = (f64::from(c.width) - 1.0, f64::from(c.height) - 1.0);
    let mut v = vec![
        Vector2::new(0.0, 0.0),
        Vector2::new(w, 0.0),
        Vector2::new(0.0, h),
        Vector2::new(w, h),
        Vector2::new(-0.5, -0.5),
        Vector2::new(w + 0.49, h + 0.49),
    ];
    for i in 0..=16 {
        let s = f64::from(i) / 16.0;
        v.push(Vector2::new(s * w, 0.0));
        v.push(Vector2::new(s * w, h));
        v.push(Vector2::new(0.0, s * h));
        v.push(Vector2::new(w, s * h));
        v.push(Vector2::new(s * w, s * h));
    }
    v
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    /// Round trip within 1e-6 px at every corner, edge and diagonal pixel, whenever
    /// the image lies inside the model's valid domain (checked, not assumed).
    #[test]
    fn project_inverts_unproject_over_the_whole_image(
        fx in 250.0f64..900.0,
        aspect in 0.98f64..1.02,
        cx_off in -8.0f64..8.0,
        cy_off in -8.0f64..8.0,
        d in plumb_bob(),
    ) {
        let c = camera(fx, aspect, cx_off, cy_off, d);
        // The farthest image point, in normalised distorted units, with margin for
        // the tangential terms.
        let far = corners_and_edges(&c)
            .iter()
            .map(|p| Vector2::new((p.x - c.cx) / c.fx, (p.y - c.cy) / c.fy).norm())
            .fold(0.0, f64::max);
        prop_assume!(far < 0.97 * max_distorted_radius(&d));
        let m = c.max_radius_squared();
        // The margin above is for the radial model; the tangential terms can still
        // carry an extreme corner across the domain's edge, where refusing is the
        // right answer. Well inside the domain a refusal is a failure.
        let near_edge = far >= 0.9 * max_distorted_radius(&d);
        for px in corners_and_edges(&c) {
            let n = match c.unproject_with_domain(px, m) {
                Ok(n) => n,
                Err(UnprojectError::OutsideDistortionDomain { .. }) if near_edge => continue,
                Err(e) => return Err(TestCaseError::fail(format!("{e} for {d:?} fx {fx}"))),
            };
            let back = c.project_with_domain(&Vector3::new(n.x, n.y, 1.0), m)
                .map_err(|e| TestCaseError::fail(format!("{e}")))?;
            prop_assert!((back - px).norm() < 1e-6, "{px:?} -> {back:?}");
        }
    }

    /// No NaN or infinity from finite input: every answer is finite or an error.
    #[test]
    fn finite_input_gives_finite_output_or_an_error(
        d in plumb_bob(),
        x in -1e6f64..1e6, y in -1e6f64..1e6, z in -1e3f64..1e6,
        u in -1e7f64..1e7, v in -1e7f64..1e7,
    ) {
        let c = camera(500.0, 1.0, 0.0, 0.0, d);
        if let Ok(p) = c.project(&Vector3::new(x, y, z)) {
            prop_assert!(p.x.is_finite() && p.y.is_finite());
        }
        if let Ok(n) = c.unproject(Vector2::new(u, v)) {
            prop_assert!(n.x.is_finite() && n.y.is_finite());
            let back = c.project(&Vector3::new(n.x, n.y, 1.0));
            prop_assert!(back.is_ok(), "an unprojected pixel must project back");
        }
        if let Ok(r) = c.unproject_ray(Vector2::new(u, v)) {
            prop_assert!((r.norm() - 1.0).abs() < 1e-12);
        }
    }

    /// Under pure barrel distortion the model folds at r² = -1/(3 k1): pixels farther
    /// out than the fold's image have no preimage and must be reported, never answered.
    #[test]
    fn pixels_beyond_the_domain_are_reported(
        k1 in -0.6f64..-0.15,
        angle in 0.0f64..std::f64::consts::TAU,
        beyond in 1.001f64..3.0,
    ) {
        let d = PlumbBob { k1, k2: 0.0, p1: 0.0, p2: 0.0, k3: 0.0 };
        let c = camera(400.0, 1.0, 0.0, 0.0, d);
        let rho_max = max_distorted_radius(&d);
        let r = rho_max * beyond;
        let px = Vector2::new(c.cx + c.fx * r * angle.cos(), c.cy + c.fy * r * angle.sin());
        let result = c.unproject(px);
        prop_assert!(
            matches!(result, Err(UnprojectError::OutsideDistortionDomain { .. })),
            "{result:?}"
        );
        // And the points on the far side of the fold do not project either.
        let m = d.max_radius_squared().unwrap();
        let far = (m * beyond * beyond).sqrt();
        prop_assert_eq!(
            c.project(&Vector3::new(far * angle.cos(), far * angle.sin(), 1.0)),
            Err(ProjectError::OutsideDistortionDomain)
        );
    }
}

/// A strongly distorted wide camera (fisheye-like barrel) still round-trips at its
/// corners: the fixed worst case beside the random ones.
#[test]
fn strong_barrel_corners_round_trip() {
    let d = PlumbBob {
        k1: -0.42,
        k2: 0.16,
        p1: 0.002,
        p2: -0.0015,
        k3: -0.012,
    };
    let c = camera(260.0, 1.0, 3.0, -2.0, d);
    let m = c.max_radius_squared();
    for px in corners_and_edges(&c) {
        let n = c.unproject_with_domain(px, m).unwrap();
        let back = c
            .project_with_domain(&Vector3::new(n.x, n.y, 1.0), m)
            .unwrap();
        assert!((back - px).norm() < 1e-6, "{px:?} -> {back:?}");
    }
}

#[test]
fn a_pincushion_corner_near_the_fold_is_undistorted() {
    // A wide pincushion lens whose image corner sits at 86 % of the largest distorted
    // radius: its preimage lies well inside the domain (r² 1.60 against 2.40), but
    // the distorted point itself is next to the fold, where Newton's first step used
    // to leave the domain and the pixel was refused.
    let d = PlumbBob {
        k1: 0.19778359087579972,
        k2: 0.015998703466011364,
        p1: 0.0,
        p2: -0.003342023176280032,
        k3: -0.029827872544375404,
    };
    let c = camera(261.9499129410448, 1.007021715682775, -5.83, -3.9, d);
    let m = c.max_radius_squared();
    let corner = Vector2::new(639.0, 479.0);
    let n = c.unproject_with_domain(corner, m).unwrap();
    assert!(n.norm_squared() < 0.7 * m.unwrap(), "{n:?}");
    let back = c
        .project_with_domain(&Vector3::new(n.x, n.y, 1.0), m)
        .unwrap();
    assert!((back - corner).norm() < 1e-6, "{back:?}");
}
