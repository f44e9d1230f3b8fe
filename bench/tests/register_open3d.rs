//! Peer cross-check: Open3D's point-to-plane ICP (`scripts/python/open3d_icp.py`, the
//! script the trade-offs run uses) and Texel's `align_pair` on the same `lab` pair
//! (16k points each, 3 degrees and 5 cm apart, range noise) from the same initial
//! guess reach the true pose and each other; Open3D's colored ICP runs on the
//! texels' colours and reaches it too.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use texel_bench::tradeoffs::registration::data::perturbed_pairs;
use texel_bench::tradeoffs::registration::open3d::{Open3dSettings, run_open3d, run_texel};
use texel_register::AlignConfig;

#[test]
fn open3d_and_texel_agree_on_a_lab_pair() {
    let scenes = texel_e2e::repo_root().join("configs/scenes");
    let pairs = perturbed_pairs(&scenes, "lab", 1, 3.0, 0.05, 5).unwrap();
    assert!(pairs[0].source.vertex_count() > 10_000);
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
            colored: false,
        },
    )
    .unwrap();
    assert!(version.starts_with("0."), "{version}");
    let ours = run_texel(&pairs, "defaults", &AlignConfig::default(), 1);
    let (o, t) = (&ours[0], &theirs[0]);
    assert!(o.ok);
    // Both moved from 3 degrees / 50 mm to the truth (5 mm range noise)...
    assert!(
        o.rotation_error_deg < 0.1 && o.translation_error_mm < 8.0,
        "{o:?}"
    );
    assert!(
        t.rotation_error_deg < 0.1 && t.translation_error_mm < 8.0,
        "{t:?}"
    );
    // ... and so to within a few millimetres of each other.
    assert!(
        (o.translation_error_mm - t.translation_error_mm).abs() < 5.0,
        "{o:?} {t:?}"
    );
    // CPU times are reported, not judged here (a coarse process clock may read 0).
    assert!(t.normals_ms.is_finite() && t.align_ms.is_finite() && t.align_ms >= 0.0);
}

#[test]
fn open3d_colored_icp_runs_on_texel_colours_and_reaches_the_truth() {
    let scenes = texel_e2e::repo_root().join("configs/scenes");
    let pairs = perturbed_pairs(&scenes, "lab", 1, 3.0, 0.05, 5).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let script = texel_e2e::repo_root().join("scripts/python/open3d_icp.py");
    let (_, theirs) = run_open3d(
        &texel_e2e::python(),
        &script,
        dir.path(),
        &pairs,
        &Open3dSettings {
            max_correspondence_distance_m: 0.1,
            max_iterations: 30,
            repeats: 1,
            colored: true,
        },
    )
    .unwrap();
    let t = &theirs[0];
    assert_eq!(t.method, "open3d colored");
    assert!(
        t.rotation_error_deg < 0.2 && t.translation_error_mm < 10.0,
        "{t:?}"
    );
}
