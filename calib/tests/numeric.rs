//! Property tests of the numeric building blocks against independent computations.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use calib::geometry::{apply_homography, homography, intrinsics_of, project};
use calib::zhang;
use nalgebra::{Matrix3, Point3, Vector2, Vector3};
use proptest::prelude::*;
use texel::{Distortion, PinholeCamera, PlumbBob, Pose};

fn camera(f: f64, aspect: f64, cx: f64, cy: f64, d: [f64; 4]) -> PinholeCamera {
    PinholeCamera {
        width: 640,
        height: 480,
        fx: f,
        fy: f * aspect,
        cx,
        cy,
        skew: 0.0,
        distortion: Distortion::PlumbBob(PlumbBob {
            k1: d[0],
            k2: d[1],
            p1: d[2],
            p2: d[3],
            k3: 0.0,
        }),
    }
}

fn board_pose(rx: f64, ry: f64, rz: f64, dist: f64) -> Pose {
    // camera_from_board: the board 9 x 6 x 5 cm centred in front of the camera.
    let r = nalgebra::UnitQuaternion::from_euler_angles(rx, ry, rz);
    let centre = Vector3::new(0.2, 0.125, 0.0);
    let t = Vector3::new(0.0, 0.0, dist) - r * centre;
    Pose::from_parts(t.into(), r)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn projection_matches_the_texel_camera_model(
        f in 300.0..900.0f64, aspect in 0.98..1.02f64, cx in 300.0..340.0f64, cy in 220.0..260.0f64,
        k1 in -0.3..0.1f64, k2 in -0.05..0.1f64, p1 in -0.002..0.002f64, p2 in -0.002..0.002f64,
        x in -0.6..0.6f64, y in -0.5..0.5f64, z in 0.5..5.0f64,
    ) {
        let c = camera(f, aspect, cx, cy, [k1, k2, p1, p2]);
        let p = Vector3::new(x * z, y * z, z);
        if let Ok(expected) = c.project(&p) {
            let got = project(&intrinsics_of(&c), &p).unwrap();
            prop_assert!((got - expected).norm() < 1e-9);
        }
    }

    #[test]
    fn zhang_recovers_intrinsics_from_exact_homographies(
        f in 400.0..900.0f64, aspect in 0.97..1.03f64, cx in 290.0..350.0f64, cy in 210.0..270.0f64,
        tilts in proptest::collection::vec((-0.6..0.6f64, -0.6..0.6f64, -0.4..0.4f64, 0.8..1.6f64), 4..7),
    ) {
        let c = camera(f, aspect, cx, cy, [0.0; 4]);
        let k = intrinsics_of(&c);
        let mut hs = Vec::new();
        for (rx, ry, rz, d) in &tilts {
            // Skip nearly fronto-parallel views (they carry no focal information).
            if rx.abs().max(ry.abs()) < 0.15 {
                continue;
            }
            let pose = board_pose(*rx, *ry, *rz, *d);
            let plane: Vec<Vector2<f64>> = (0..54).map(|n| Vector2::new(0.05 * f64::from(n % 9), 0.05 * f64::from(n / 9))).collect();
            let image: Vec<Vector2<f64>> = plane.iter().map(|b| project(&k, &(pose * Point3::new(b.x, b.y, 0.0)).coords).unwrap()).collect();
            let h = homography(&plane, &image).unwrap();
            for (b, px) in plane.iter().zip(&image) {
                prop_assert!((apply_homography(&h, *b).unwrap() - px).norm() < 1e-6);
            }
            hs.push(h);
        }
        prop_assume!(hs.len() >= 3);
        let est = zhang::intrinsics(&hs, (319.5, 239.5)).unwrap();
        // Views whose normal equations leave a near-double smallest eigenvalue do not
        // fix the principal point; the documented answer is then the fixed-centre
        // variant, which cannot recover a centre elsewhere. Those draws are set aside
        // (if every draw fell back, the rejections would fail the test).
        prop_assume!(est[2] != 319.5 || est[3] != 239.5);
        prop_assert!((est[0] - c.fx).abs() / c.fx < 1e-4, "{est:?} vs {c:?}");
        prop_assert!((est[1] - c.fy).abs() / c.fy < 1e-4, "{est:?} vs {c:?}");
        prop_assert!((est[2] - cx).abs() < 0.05 && (est[3] - cy).abs() < 0.05, "{est:?}");
        // Each pose follows from its homography.
        let pose = zhang::pose_from_homography(&hs[0], est).unwrap();
        prop_assert!(pose.translation.vector.z > 0.0);
    }
}

#[test]
fn pose_from_homography_refuses_degenerate_input() {
    assert!(zhang::pose_from_homography(&Matrix3::zeros(), [500.0, 500.0, 320.0, 240.0]).is_none());
    assert!(zhang::intrinsics(&[], (0.0, 0.0)).is_none());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Any image, including non-finite values, gives a detection or an error.
    #[test]
    fn detection_never_panics_on_arbitrary_images(
        values in proptest::collection::vec(prop_oneof![
            -1.0f32..2.0,
            Just(f32::NAN),
            Just(f32::INFINITY),
            Just(0.0f32),
            Just(1.0f32),
        ], 48 * 36),
    ) {
        let img = calib::gray::GrayImage::new(48, 36, values).unwrap();
        let target = calib::config::TargetConfig::default();
        let _ = calib::detect::detect_board(&img, &target, &calib::detect::DetectParams::eo(48, 36));
        let _ = calib::detect::detect_board(&img, &target, &calib::detect::DetectParams::lidar());
    }
}
