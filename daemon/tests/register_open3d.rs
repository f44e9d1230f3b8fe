//! Peer cross-check: Open3D's point-to-plane ICP (`scripts/python/open3d_icp.py`, the
//! script the trade-offs run uses) and Texel's `align_pair` on the same small pair
//! from the same initial guess reach the true pose and each other.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod register_support;

use std::sync::Arc;

use register_support::*;
use texel_daemon::register::AlignConfig;
use texel_daemon::tradeoffs::registration::data::ScanPair;
use texel_daemon::tradeoffs::registration::open3d::{Open3dSettings, run_open3d, run_texel};

#[test]
fn open3d_and_texel_agree_on_a_room_pair() {
    let s = sensor(64, 64, 0.005);
    let scene = Scene::room();
    let world_from_target = look_at([-2.0, 0.5, 1.5], [3.0, 0.0, 0.8]);
    let truth = perturbation(3.0, [0.2, 1.0, 0.3], 0.05, [1.0, 0.2, -0.5]);
    let pair = ScanPair {
        scene: "room".into(),
        target: scan(&scene, &s, &world_from_target, 0.005, 1),
        source: scan(&scene, &s, &(world_from_target * truth), 0.005, 2),
        lidar: s.model.lidar.clone(),
        truth,
        initial: texel::Pose::identity(),
    };
    assert!(Arc::strong_count(&pair.target) >= 1);
    let pairs = [pair];
    let dir = tempfile::tempdir().unwrap();
    let script = texel_e2e::repo_root().join("scripts/python/open3d_icp.py");
    let (version, theirs) = run_open3d(
        &texel_e2e::python(),
        &script,
        dir.path(),
        &pairs,
        &Open3dSettings {
            max_correspondence_distance_m: 0.1,
            max_iterations: 30,
            repeats: 1,
        },
    )
    .unwrap();
    assert!(version.starts_with("0."), "{version}");
    let ours = run_texel(&pairs, "defaults", &AlignConfig::default(), 1);
    let (o, t) = (&ours[0], &theirs[0]);
    assert!(o.ok);
    // Both moved from 3 degrees / 50 mm to the truth...
    assert!(
        o.rotation_error_deg < 0.1 && o.translation_error_mm < 3.0,
        "{o:?}"
    );
    assert!(
        t.rotation_error_deg < 0.1 && t.translation_error_mm < 3.0,
        "{t:?}"
    );
    // ... and so to within a few millimetres of each other.
    assert!(
        (o.translation_error_mm - t.translation_error_mm).abs() < 3.0,
        "{o:?} {t:?}"
    );
    assert!(t.normals_ms >= 0.0 && t.align_ms > 0.0);
}
