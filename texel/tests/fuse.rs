//! Fusion against analytic ground truth: planes at known poses give exact points and
//! texture coordinates; hard cases (grazing, no returns of every kind, all-invalid
//! frames, degenerate triangles, a lidar wider than the EO view, a non-identity
//! extrinsic, depth steps) stay finite and flagged as the rules say.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use nalgebra::{Vector2, Vector3};
use proptest::prelude::*;
use texel::fuse::{FuseConfig, fuse, normal_accuracy, pixel_of_tex_coord};
use texel::pose::pose_from_parts;
use texel::scan::NO_VERTEX;
use texel::{
    Distortion, EoFrame, PinholeCamera, PlumbBob, Pose, RangeFrame, RangeNoise, Sensor, SensorModel,
};

fn lidar(w: u32, h: u32, fov_deg: f64) -> PinholeCamera {
    PinholeCamera::from_vertical_fov(w, h, fov_deg).unwrap()
}

fn eo_camera() -> PinholeCamera {
    PinholeCamera {
        width: 320,
        height: 240,
        fx: 260.0,
        fy: 262.0,
        cx: 161.3,
        cy: 118.7,
        skew: 0.0,
        distortion: Distortion::PlumbBob(PlumbBob {
            k1: -0.21,
            k2: 0.07,
            p1: 0.0012,
            p2: -0.0008,
            k3: -0.004,
        }),
    }
}

fn sensor(lidar: PinholeCamera, eo_from_lidar: Pose, sigma_m: f64) -> Sensor {
    Sensor::new(SensorModel {
        name: "test".into(),
        lidar,
        eo: eo_camera(),
        eo_from_lidar,
        range_noise: RangeNoise {
            sigma_m,
            sigma_per_m: 0.0,
        },
        range_bias_m: 0.0,
        min_range_m: 0.1,
        max_range_m: 100.0,
        eo_response: None,
    })
}

fn eo_frame(s: &Sensor) -> EoFrame {
    let (w, h) = (s.model.eo.width, s.model.eo.height);
    EoFrame {
        width: w,
        height: h,
        rgb: (0..w * h * 3).map(|i| (i % 251) as u8).collect(),
        timestamp_ns: 5,
        exposure: None,
    }
}

/// A plane `n·x = d` in the EO frame; returns the lidar range frame that sees it
/// exactly (computed in f64 from the camera model, not the f32 ray table) and the
/// true EO-frame point of each pixel.
fn plane_frame(s: &Sensor, n: Vector3<f64>, d: f64) -> (RangeFrame, Vec<Option<Vector3<f64>>>) {
    let lidar = &s.model.lidar;
    let eo_from_lidar = s.model.eo_from_lidar;
    // The plane in the lidar frame: n_l·x = d_l.
    let n_l = eo_from_lidar.rotation.inverse() * n;
    let d_l = d - n.dot(&eo_from_lidar.translation.vector);
    let mut frame = RangeFrame::empty(lidar.width, lidar.height, 5, 1);
    let mut truth = vec![None; frame.pixel_count()];
    for v in 0..lidar.height {
        for u in 0..lidar.width {
            let ray = lidar
                .unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                .unwrap();
            let denom = n_l.dot(&ray);
            if denom.abs() < 1e-12 {
                continue;
            }
            let t = d_l / denom;
            if t > 0.0 {
                let i = (v * lidar.width + u) as usize;
                frame.ranges_m[i] = t as f32;
                truth[i] = Some(eo_from_lidar * nalgebra::Point3::from(ray * f64::from(t as f32)))
                    .map(|p| p.coords);
            }
        }
    }
    (frame, truth)
}

fn check_points_and_tex_coords(s: &Sensor, n: Vector3<f64>, d: f64) {
    let (frame, truth) = plane_frame(s, n, d);
    let scan = fuse(&frame, eo_frame(s), s, &FuseConfig::default()).unwrap();
    assert_eq!(scan.vertex_count(), frame.return_count());
    let mut textured = 0;
    for (k, v) in scan.vertices.iter().enumerate() {
        let p = Vector3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
        // On the plane within 1e-4 m.
        assert!(
            (n.dot(&p) - d).abs() < 1e-4,
            "vertex {k}: {}",
            n.dot(&p) - d
        );
        let t = truth[scan.vertex_pixel[k] as usize].unwrap();
        assert!((p - t).norm() < 1e-4);
        if scan.vertex_textured[k] {
            textured += 1;
            let want = s.model.eo.project(&t).unwrap();
            let got = pixel_of_tex_coord(scan.tex_coords[k], s.model.eo.width, s.model.eo.height);
            assert!((got - want).norm() < 0.05, "{got:?} vs {want:?}");
        } else {
            // Untextured only when the true point is outside the EO image.
            let outside = s
                .model
                .eo
                .project(&t)
                .map(|px| !s.model.eo.contains_pixel(px))
                .unwrap_or(true);
            assert!(outside, "vertex {k} should be textured");
        }
    }
    assert!(textured > 0);
}

#[test]
fn plane_points_and_tex_coords_match_the_analytic_truth() {
    let s = sensor(lidar(64, 48, 40.0), Pose::identity(), 0.005);
    check_points_and_tex_coords(&s, Vector3::new(0.0, 0.0, 1.0), 3.0);
    check_points_and_tex_coords(&s, Vector3::new(0.3, -0.2, 1.0).normalize(), 5.5);
}

#[test]
fn non_identity_extrinsic_is_applied() {
    let eo_from_lidar = pose_from_parts([0.04, -0.015, 0.01], [0.004, -0.006, 0.002, 1.0]).unwrap();
    let s = sensor(lidar(64, 48, 40.0), eo_from_lidar, 0.005);
    check_points_and_tex_coords(&s, Vector3::new(0.1, 0.2, 1.0).normalize(), 4.0);
    // With the identity assumed instead, points would be centimetres off the plane:
    // the check above would fail, so the extrinsic is really used.
    let (frame, _) = plane_frame(&s, Vector3::z(), 4.0);
    let wrong = sensor(lidar(64, 48, 40.0), Pose::identity(), 0.005);
    let scan = fuse(&frame, eo_frame(&wrong), &wrong, &FuseConfig::default()).unwrap();
    let worst = scan
        .vertices
        .iter()
        .map(|v| (f64::from(v[2]) - 4.0).abs())
        .fold(0.0, f64::max);
    assert!(worst > 0.005, "{worst}");
}

#[test]
fn range_bias_is_subtracted_before_the_points_are_placed() {
    let eo_from_lidar = pose_from_parts([0.02, 0.0, 0.0], [0.0, 0.0017, 0.0, 1.0]).unwrap();
    let mut s = sensor(lidar(64, 48, 40.0), eo_from_lidar, 0.005);
    let (n, d) = (Vector3::new(0.2, -0.1, 1.0).normalize(), 3.0);
    let (mut frame, truth) = plane_frame(&s, n, d);
    // The lidar reports 2 cm too far everywhere.
    let bias = 0.02;
    for r in frame.ranges_m.iter_mut().filter(|r| r.is_finite()) {
        *r += bias as f32;
    }
    let worst_error = |s: &Sensor| {
        let scan = fuse(&frame, eo_frame(s), s, &FuseConfig::default()).unwrap();
        assert_eq!(scan.vertex_count(), frame.return_count());
        scan.vertices
            .iter()
            .zip(&scan.vertex_pixel)
            .map(|(v, &pixel)| {
                let p = Vector3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
                (p - truth[pixel as usize].unwrap()).norm()
            })
            .fold(0.0, f64::max)
    };
    // Ignoring the bias puts every point about 2 cm behind the plane...
    assert!(worst_error(&s) > 0.019, "{}", worst_error(&s));
    // ... subtracting it puts them back on the true surface (f32 ranges: ~1e-6 m).
    s.model.range_bias_m = bias;
    assert!(worst_error(&s) < 1e-5, "{}", worst_error(&s));
    // A bias beyond every range leaves no point, and nothing non-finite.
    s.model.range_bias_m = 50.0;
    let scan = fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).unwrap();
    assert_eq!(scan.vertex_count(), 0);
    assert!(scan.triangles.is_empty());
}

#[test]
fn lidar_wider_than_the_eo_view_leaves_outside_points_untextured() {
    let s = sensor(lidar(96, 72, 100.0), Pose::identity(), 0.005);
    check_points_and_tex_coords(&s, Vector3::z(), 2.0);
    let (frame, _) = plane_frame(&s, Vector3::z(), 2.0);
    let scan = fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).unwrap();
    let untextured = scan.vertex_textured.iter().filter(|t| !**t).count();
    assert!(untextured > 1000, "{untextured}");
    // No triangle uses an untextured vertex.
    for t in &scan.triangles {
        assert!(t.iter().all(|&v| scan.vertex_textured[v as usize]));
    }
}

/// Every triangle's accuracy against the analytic cosine at its centroid `g` for the
/// plane `n·x = d` (camera at the origin on the plane's positive side): `-d / |g|`.
fn assert_plane_accuracy(scan: &texel::TexelScan, d: f64, tolerance: f64) {
    for (t, &acc) in scan.triangles.iter().zip(&scan.triangle_accuracy) {
        let g: Vector3<f64> = t
            .iter()
            .map(|&i| {
                let v = scan.vertices[i as usize];
                Vector3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]))
            })
            .sum::<Vector3<f64>>()
            / 3.0;
        let want = (d.abs() / g.norm()).clamp(0.0, 1.0);
        assert!((f64::from(acc) - want).abs() < tolerance, "{acc} vs {want}");
    }
}

#[test]
fn fronto_parallel_accuracy_is_the_cosine_to_the_cop() {
    let s = sensor(lidar(41, 41, 30.0), Pose::identity(), 0.005);
    let (frame, _) = plane_frame(&s, -Vector3::z(), -3.0);
    let scan = fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).unwrap();
    assert_eq!(scan.triangle_count(), 2 * 40 * 40);
    assert_eq!(scan.stretched_count(), 0);
    assert_plane_accuracy(&scan, -3.0, 1e-5);
    let centre = scan
        .triangle_accuracy
        .iter()
        .cloned()
        .fold(0.0f32, f32::max);
    assert!(centre > 0.999);
}

#[test]
fn grazing_surfaces_go_to_zero_accuracy_and_stay_finite() {
    let s = sensor(lidar(64, 48, 30.0), Pose::identity(), 0.001);
    let config = FuseConfig {
        max_incidence_deg: 89.99,
        ..FuseConfig::default()
    };
    let mut lowest = 1.0f32;
    for angle_deg in [60.0f64, 75.0, 85.0, 89.0, 89.9] {
        // A plane tilted about the x axis that the optical axis meets 2 m out at
        // angle_deg incidence.
        let a = angle_deg.to_radians();
        let n = Vector3::new(0.0, -a.sin(), -a.cos());
        let d = -2.0 * a.cos();
        let (frame, _) = plane_frame(&s, n, d);
        let scan = fuse(&frame, eo_frame(&s), &s, &config).unwrap();
        assert!(scan.triangle_count() > 100, "{angle_deg}");
        assert!(scan.vertices.iter().flatten().all(|c| c.is_finite()));
        assert!(
            scan.triangle_accuracy
                .iter()
                .all(|a| a.is_finite() && (0.0..=1.0).contains(a))
        );
        assert_plane_accuracy(&scan, d, 2e-3);
        lowest = scan
            .triangle_accuracy
            .iter()
            .cloned()
            .fold(lowest, f32::min);
    }
    assert!(lowest < 0.01, "{lowest}");
}

#[test]
fn every_kind_of_no_return_gives_no_vertex() {
    let s = sensor(lidar(8, 6, 40.0), Pose::identity(), 0.005);
    let mut frame = RangeFrame::empty(8, 6, 0, 0);
    frame.ranges_m.iter_mut().for_each(|r| *r = 2.0);
    let kinds = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 0.0, -0.0, -3.0];
    for (i, k) in kinds.iter().enumerate() {
        frame.ranges_m[i * 7] = *k;
    }
    let scan = fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).unwrap();
    assert_eq!(scan.vertex_count(), 48 - kinds.len());
    for i in 0..kinds.len() {
        assert_eq!(scan.pixel_vertex[i * 7], NO_VERTEX);
    }
}

#[test]
fn an_all_invalid_frame_is_an_empty_scan() {
    let s = sensor(lidar(16, 12, 40.0), Pose::identity(), 0.005);
    let frame = RangeFrame::empty(16, 12, 7, 3);
    let scan = fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).unwrap();
    assert_eq!(scan.vertex_count(), 0);
    assert_eq!(scan.triangle_count(), 0);
    assert!(scan.bounds().is_none());
    assert_eq!((scan.timestamp_ns, scan.seq), (7, 3));
    assert_eq!(
        scan.texture.width, 320,
        "the texture still travels with the scan"
    );
}

#[test]
fn wrong_sizes_are_refused() {
    let s = sensor(lidar(16, 12, 40.0), Pose::identity(), 0.005);
    let frame = RangeFrame::empty(15, 12, 0, 0);
    assert!(fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).is_err());
    let frame = RangeFrame::empty(16, 12, 0, 0);
    let mut eo = eo_frame(&s);
    eo.rgb.pop();
    assert!(fuse(&frame, eo, &s, &FuseConfig::default()).is_err());
}

#[test]
fn degenerate_triangles_get_zero_accuracy_and_a_flag() {
    // Collinear and coincident vertices, directly.
    assert_eq!(
        normal_accuracy([0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0], [0.0; 3]),
        None
    );
    assert_eq!(
        normal_accuracy([1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [2.0, 0.0, 1.0], [0.0; 3]),
        None
    );
    assert_eq!(
        normal_accuracy([0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3]),
        None
    );
    // A face-on triangle has accuracy 1; seen from behind, 0 (not negative).
    let a = normal_accuracy([0.0, 0.0, 2.0], [0.0, 1.0, 2.0], [1.0, 0.0, 2.0], [0.0; 3]).unwrap();
    assert!(a > 0.85);
    assert_eq!(
        normal_accuracy([0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0], [0.0; 3]),
        Some(0.0)
    );
    // Through fuse: with the lidar far out in front of the EO camera, centimetre
    // ranges vanish below the f32 spacing of the stored coordinates, so every vertex
    // lands on the same point, which the EO camera sees: coincident vertices.
    let far = pose_from_parts([1.0e7, 1.0e7, 1.0e8], [0.0, 0.0, 0.0, 1.0]).unwrap();
    let s = sensor(lidar(4, 4, 40.0), far, 0.005);
    let mut frame = RangeFrame::empty(4, 4, 0, 0);
    frame.ranges_m.iter_mut().for_each(|r| *r = 0.05);
    let scan = fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).unwrap();
    assert_eq!(scan.triangle_count(), 18);
    assert!(
        scan.triangle_flags
            .iter()
            .all(|f| f.is_degenerate() && !f.is_usable())
    );
    assert!(scan.triangle_accuracy.iter().all(|&a| a == 0.0));
    assert!(scan.vertices.iter().flatten().all(|c| c.is_finite()));
}

#[test]
fn depth_steps_are_stretched_and_flat_noisy_surfaces_are_not() {
    let s = sensor(lidar(64, 48, 40.0), Pose::identity(), 0.01);
    let (mut frame, _) = plane_frame(&s, Vector3::z(), 4.0);
    // A box in front of the wall: the left half of the image at 2.5 m.
    let w = frame.width as usize;
    for (i, r) in frame.ranges_m.iter_mut().enumerate() {
        if i % w < w / 2 {
            *r *= 2.5 / 4.0;
        }
    }
    // Deterministic pseudo-noise of up to ±2 sigma on every range.
    let mut state = 12345u64;
    for r in frame.ranges_m.iter_mut() {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let u = ((state >> 33) as f64 / (1u64 << 31) as f64) * 2.0 - 1.0;
        *r += (u * 0.02) as f32;
    }
    let scan = fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).unwrap();
    for (t, f) in scan.triangles.iter().zip(&scan.triangle_flags) {
        let cols: Vec<usize> = t
            .iter()
            .map(|&v| scan.vertex_pixel[v as usize] as usize % w)
            .collect();
        let spans_step = cols.iter().any(|&c| c < w / 2) && cols.iter().any(|&c| c >= w / 2);
        assert_eq!(
            f.is_stretched(),
            spans_step,
            "triangle over columns {cols:?}"
        );
    }
    assert_eq!(scan.stretched_count(), 2 * (frame.height as usize - 1));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any finite vertices, up to f32's range: no NaN, an accuracy within [0, 1] or
    /// a degenerate verdict.
    #[test]
    fn normal_accuracy_is_bounded_for_any_finite_triangle(
        coords in proptest::array::uniform9(
            prop::num::f32::NORMAL | prop::num::f32::SUBNORMAL | prop::num::f32::ZERO
        ),
        cop in proptest::array::uniform3(-1e3f64..1e3),
    ) {
        let [a0, a1, a2, b0, b1, b2, c0, c1, c2] = coords;
        if let Some(acc) = normal_accuracy([a0, a1, a2], [b0, b1, b2], [c0, c1, c2], cop) {
            prop_assert!((0.0..=1.0).contains(&acc), "{acc}");
        }
    }

    /// Random valid sensors and ranges: nothing non-finite anywhere in the scan and
    /// accuracies within [0, 1].
    #[test]
    fn fusion_output_is_always_finite(
        fov in 10.0f64..120.0,
        k1 in -0.3f64..0.2,
        t in proptest::array::uniform3(-0.2f64..0.2),
        q in proptest::array::uniform3(-0.05f64..0.05),
        sigma in 0.0f64..0.1,
        ranges in proptest::collection::vec(
            prop_oneof![
                4 => 0.05f32..80.0,
                1 => Just(f32::NAN),
                1 => Just(0.0f32),
                1 => Just(f32::INFINITY),
                1 => 1e-30f32..1e-3,
                1 => 1e3f32..1e7,
            ],
            12 * 9,
        ),
    ) {
        let mut eo = eo_camera();
        eo.distortion = Distortion::PlumbBob(PlumbBob { k1, k2: 0.0, p1: 0.0, p2: 0.0, k3: 0.0 });
        let s = Sensor::new(SensorModel {
            name: "p".into(),
            lidar: lidar(12, 9, fov),
            eo,
            eo_from_lidar: pose_from_parts(t, [q[0], q[1], q[2], 1.0]).unwrap(),
            range_noise: RangeNoise { sigma_m: sigma, sigma_per_m: 0.001 },
            range_bias_m: 0.0,
            min_range_m: 0.1,
            max_range_m: 100.0,
            eo_response: None,
        });
        let mut frame = RangeFrame::empty(12, 9, 0, 0);
        frame.ranges_m = ranges;
        let scan = fuse(&frame, eo_frame(&s), &s, &FuseConfig::default()).unwrap();
        prop_assert!(scan.vertices.iter().flatten().all(|c| c.is_finite()));
        prop_assert!(scan.tex_coords.iter().flatten().all(|c| c.is_finite()));
        for (k, uv) in scan.tex_coords.iter().enumerate() {
            if scan.vertex_textured[k] {
                prop_assert!((0.0..=1.0).contains(&uv[0]) && (0.0..=1.0).contains(&uv[1]));
            }
        }
        prop_assert!(scan.triangle_accuracy.iter().all(|a| (0.0..=1.0).contains(a)));
        prop_assert_eq!(scan.triangle_accuracy.len(), scan.triangles.len());
        prop_assert!(scan.triangles.iter().flatten().all(|&v| (v as usize) < scan.vertex_count()));
    }
}
