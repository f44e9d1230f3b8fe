//! The registration check's own machinery: putting a sensor model into a capture
//! really changes what the daemon's offline registration uses (a wrong extrinsic
//! shows), and putting the capture's own model back changes nothing.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod calib_common;

use calib_common::root;
use nalgebra::Vector3;
use texel::Pose;
use texel_bench::calibration::lab_check::{compare_registration, render_lab_capture};
use texel_register::RegistrationConfig;

#[test]
fn the_sensor_put_into_the_capture_is_the_one_registration_uses() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("lab.mcap");
    let scene = sims::Scene::load(&root().join("configs/scenes/lab.toml")).unwrap();
    let truth = scene.sensor().clone();
    render_lab_capture(scene, 3, 6, &capture).unwrap();
    let config = RegistrationConfig::default();

    // The capture's own model, written back: identical registration.
    let same = compare_registration(&capture, &truth, dir.path(), &config).unwrap();
    println!("{same:?}");
    assert_eq!(same.truth, same.calibrated);
    assert_eq!(same.ate_ratio(), 1.0);

    // The extrinsic turned by 1 degree about the EO y axis: every scan turns with it,
    // so the unaligned trajectory error grows and the aligned one does not.
    let mut turned = truth.clone();
    turned.eo_from_lidar = Pose::rotation(Vector3::y() * 1.0f64.to_radians()) * truth.eo_from_lidar;
    let c = compare_registration(&capture, &turned, dir.path(), &config).unwrap();
    println!("{c:?}");
    assert_eq!(c.calibrated.registered, 6);
    assert!(c.ate_ratio() > 2.0, "{c:?}");
    assert!(c.aligned_ate_ratio() < c.ate_ratio(), "{c:?}");
}
