//! The photometric term where the geometry is blind, against the analytic truth: a
//! textured corridor's axis recovered from the EO images, a textureless one left to
//! the prior and named, a repeating texture not trusted, a saturated frame, an
//! exposure change, and a walk down a corridor with the registrar.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod register_support;

use std::sync::Arc;

use nalgebra::{Vector3, Vector6};
use register_support::*;
use texel::Pose;
use texel_register::se3;
use texel_register::{
    AlignConfig, Alignment, PhotometricMode, Registrar, RegistrationConfig, ScanPyramid, align_pair,
};

/// The scan's pyramid with its EO pyramid, as the registrar builds it.
fn pyramid(scan: Arc<texel::TexelScan>, s: &texel::Sensor) -> ScanPyramid {
    eo_pyramid(scan, s)
}

/// The test texel camera with an EO camera four times the lidar's resolution (the
/// default sensor's ratio), so that the texture is resolved.
fn texel_camera() -> texel::Sensor {
    let mut model = sensor(64, 64, 0.003).model;
    model.eo = texel::PinholeCamera::from_vertical_fov(256, 256, 66.0).unwrap();
    texel::Sensor::new(model)
}

fn with_mode(mode: PhotometricMode) -> AlignConfig {
    let mut config = AlignConfig::default();
    config.photometric.mode = mode;
    config
}

/// A camera in the corridor (`Scene::corridor`, axis world x), looking down it.
fn in_corridor(x: f64) -> Pose {
    look_at([x, 0.1, 1.3], [x + 10.0, -0.2, 1.1])
}

/// The error of `a`'s estimate along world x (the corridor's axis), metres.
fn axis_error_m(a: &Alignment, truth: &Pose) -> f64 {
    let error = a.world_from_source.translation.vector - truth.translation.vector;
    error.x
}

/// The variance of the estimate along `axis` (in the frame the estimate is in): the
/// covariance is of a right perturbation `(ω, v)` in the source frame, where the
/// axis is `Rᵀ axis`.
fn axis_variance_m2(a: &Alignment, axis: &Vector3<f64>) -> f64 {
    let axis = a.world_from_source.rotation.inverse() * axis;
    let v = Vector6::new(0.0, 0.0, 0.0, axis.x, axis.y, axis.z);
    (v.transpose() * a.covariance * v)[(0, 0)]
}

fn assert_finite(a: &Alignment) {
    assert!(se3::is_finite(&a.world_from_source));
    assert!(a.covariance.iter().all(|c| c.is_finite()));
    assert!(a.information.iter().all(|c| c.is_finite()));
    assert!(
        a.target_information
            .iter()
            .all(|m| m.iter().all(|c| c.is_finite()))
    );
}

#[test]
fn a_textured_corridor_is_pinned_by_the_eo_image() {
    let s = texel_camera();
    let scene = Scene::corridor();
    let world_from_a = in_corridor(2.0);
    // 9 cm down the corridor and a little turned: the axis is the unknown.
    let truth = Pose::translation(0.09, 0.0, 0.0) * world_from_a;
    let a = pyramid(scan_with(&scene, &s, &world_from_a, 1, &speckle, 1.0), &s);
    let b = pyramid(scan_with(&scene, &s, &truth, 2, &speckle, 1.0), &s);
    let target_from_source = world_from_a.inverse() * truth;
    // Geometry alone: the axis is named and kept at the guess (no motion).
    let geometry = align_pair(&b, &a, &Pose::identity(), &with_mode(PhotometricMode::Off));
    assert_finite(&geometry);
    assert_eq!(geometry.degenerate.len(), 1, "{:?}", geometry.degenerate);
    let moved = geometry.world_from_source.translation.vector.norm();
    assert!(moved < 0.02, "moved {moved} m without information");
    // With the EO image (the default): the axis is recovered.
    let eo = align_pair(&b, &a, &Pose::identity(), &AlignConfig::default());
    assert_finite(&eo);
    assert!(eo.is_ok(), "{:?}", eo.status);
    assert!(eo.degenerate.is_empty(), "{:?}", eo.degenerate);
    let (r, t) = error_deg_mm(&eo.world_from_source, &target_from_source);
    assert!(r < 0.1 && t < 3.0, "{r} deg {t} mm");
    // Admitted in the weak direction only, and it filled the degeneracy.
    assert_eq!(eo.photometric.admitted_directions, 1);
    assert!(eo.photometric.residuals >= 100);
    assert!(eo.photometric.min_eigenvalue > 20.0 * eo.photometric.geometry_min_eigenvalue);
    // The pose graph's edge carries it: far more certain along the axis than the
    // prior (0.2 m).
    let axis = eo.world_from_source.rotation.inverse() * Vector3::x();
    let v = Vector6::new(0.0, 0.0, 0.0, axis.x, axis.y, axis.z);
    let edge = (v.transpose() * eo.target_information[0] * v)[(0, 0)];
    let prior = 1.0 / (0.2f64 * 0.2);
    assert!(edge > 100.0 * prior, "{edge} vs {prior}");
    // Full mode agrees.
    let full = align_pair(&b, &a, &Pose::identity(), &with_mode(PhotometricMode::Full));
    let (r, t) = error_deg_mm(&full.world_from_source, &target_from_source);
    assert!(r < 0.15 && t < 5.0, "full: {r} deg {t} mm");
}

#[test]
fn a_textureless_corridor_keeps_the_prior_and_names_the_axis() {
    let s = texel_camera();
    let scene = Scene::corridor();
    let world_from_a = in_corridor(2.0);
    let truth = Pose::translation(0.09, 0.0, 0.0) * world_from_a;
    let plain = |_: &Vector3<f64>| 0.5;
    let a = pyramid(scan_with(&scene, &s, &world_from_a, 1, &plain, 1.0), &s);
    let b = pyramid(scan_with(&scene, &s, &truth, 2, &plain, 1.0), &s);
    let result = align_pair(&b, &a, &Pose::identity(), &AlignConfig::default());
    assert_finite(&result);
    assert!(result.is_ok(), "{:?}", result.status);
    // Both sensors blind: no photometric residual, the axis named, no motion made up.
    assert_eq!(result.photometric.residuals, 0);
    assert_eq!(result.degenerate.len(), 1, "{:?}", result.degenerate);
    let d = result.degenerate[0].direction;
    let axis = world_from_a.rotation.inverse() * Vector3::x();
    assert!(Vector3::new(d[3], d[4], d[5]).dot(&axis).abs() > 0.95);
    let along = result
        .world_from_source
        .translation
        .vector
        .dot(&Vector3::x());
    assert!(along.abs() < 0.005, "invented {along} m of motion");
    // The covariance along the axis is the prior's.
    // (The estimate is in the first camera's frame, where the axis is `Rᵀ x`.)
    let variance = axis_variance_m2(&result, &(world_from_a.rotation.inverse() * Vector3::x()));
    assert!(variance > 0.9 * 0.2 * 0.2, "{variance}");
}

#[test]
fn a_texture_repeating_faster_than_the_motion_gives_no_confident_wrong_pose() {
    let s = texel_camera();
    let scene = Scene::corridor();
    // Stripes across the corridor every 10 cm (bricks' joints), and 13 cm of motion
    // from a guess of none: 3 cm from the wrong stripe, 10 from the right one.
    let stripes = |p: &Vector3<f64>| 0.5 + 0.3 * (std::f64::consts::TAU * p.x / 0.1).sin();
    let world_from_a = in_corridor(2.0);
    let truth = Pose::translation(0.13, 0.0, 0.0) * world_from_a;
    let a = pyramid(scan_with(&scene, &s, &world_from_a, 1, &stripes, 1.0), &s);
    let b = pyramid(scan_with(&scene, &s, &truth, 2, &stripes, 1.0), &s);
    let initial = world_from_a;
    let targets = [texel_register::AlignTarget {
        pyramid: &a,
        world_from_target: world_from_a,
    }];
    let result = texel_register::align(&b, &targets, &initial, &AlignConfig::default());
    assert_finite(&result);
    let error = axis_error_m(&result, &truth);
    let sigma = axis_variance_m2(&result, &Vector3::x()).sqrt();
    let ambiguous = result.degenerate.iter().any(|d| d.ambiguous);
    // Whatever period it settled on, it does not claim to know: the axis is named
    // ambiguous and its uncertainty (the prior's) covers the error.
    assert!(ambiguous, "{:?}", result.degenerate);
    assert!(
        sigma > 1.5 * error.abs(),
        "error {error} m with sigma {sigma} m"
    );
}

#[test]
fn a_saturated_frame_gives_no_photometric_residual_and_stays_finite() {
    let s = texel_camera();
    let scene = Scene::corridor();
    let world_from_a = in_corridor(2.0);
    let truth = Pose::translation(0.05, 0.0, 0.0) * world_from_a;
    let a = pyramid(scan_with(&scene, &s, &world_from_a, 1, &speckle, 1.0), &s);
    // Eight times over-exposed: every pixel clips.
    let b = pyramid(scan_with(&scene, &s, &truth, 2, &speckle, 8.0), &s);
    let result = align_pair(&b, &a, &Pose::identity(), &AlignConfig::default());
    assert_finite(&result);
    assert!(result.is_ok(), "{:?}", result.status);
    assert_eq!(result.photometric.residuals, 0);
    assert_eq!(result.degenerate.len(), 1, "{:?}", result.degenerate);
}

#[test]
fn an_exposure_change_between_frames_is_compensated() {
    let s = texel_camera();
    let scene = Scene::corridor();
    let world_from_a = in_corridor(2.0);
    let truth = Pose::translation(0.08, 0.0, 0.0) * world_from_a;
    let target_from_source = world_from_a.inverse() * truth;
    let a = pyramid(scan_with(&scene, &s, &world_from_a, 1, &speckle, 1.0), &s);
    for gain in [0.65, 1.25] {
        let b = pyramid(scan_with(&scene, &s, &truth, 2, &speckle, gain), &s);
        let result = align_pair(&b, &a, &Pose::identity(), &AlignConfig::default());
        assert_finite(&result);
        assert!(
            result.degenerate.is_empty(),
            "{gain}: {:?}",
            result.degenerate
        );
        let (r, t) = error_deg_mm(&result.world_from_source, &target_from_source);
        assert!(r < 0.15 && t < 4.0, "gain {gain}: {r} deg {t} mm");
    }
}

#[test]
fn a_walk_down_a_textured_corridor_does_not_drift() {
    let s = texel_camera();
    let scene = Scene::corridor();
    let frames = 16;
    let step_m = 0.08;
    let truth: Vec<Pose> = (0..frames)
        .map(|k| in_corridor(1.0 + step_m * k as f64))
        .collect();
    let path_m = step_m * (frames - 1) as f64;
    let run = |mode: PhotometricMode| {
        let mut config = RegistrationConfig::default();
        config.align.photometric.mode = mode;
        let mut registrar = Registrar::with_anchor(config, truth[0]);
        let mut last = Pose::identity();
        for (k, pose) in truth.iter().enumerate() {
            let scan = scan_with(&scene, &s, pose, k as u64 + 1, &speckle, 1.0);
            let r = registrar.register(scan, &s.model);
            assert!(r.status.is_registered(), "{k}: {:?}", r.status);
            last = r.world_from_scan;
        }
        let end = truth[frames - 1];
        (last.translation.vector - end.translation.vector).norm()
    };
    let blind = run(PhotometricMode::Off);
    let seeing = run(PhotometricMode::Selective);
    // Geometry alone keeps the standing start's prediction: most of the path lost.
    assert!(blind > 0.5 * path_m, "geometry alone ended {blind} m off");
    // With the EO images: within 1 % of the path.
    assert!(
        seeing < 0.01 * path_m,
        "ended {seeing} m off over {path_m} m"
    );
}
