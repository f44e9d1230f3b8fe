//! Pairwise alignment on analytic scenes with exact ground truth.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod register_support;

use register_support::*;
use texel_daemon::register::{AlignConfig, ScanPyramid, align_pair};

#[test]
fn room_pair_converges_to_the_truth() {
    let s = sensor(64, 64, 0.005);
    let scene = Scene::room();
    let world_from_a = look_at([-2.0, 0.5, 1.5], [3.0, 0.0, 0.8]);
    let world_from_b = world_from_a * perturbation(3.0, [0.2, 1.0, 0.3], 0.05, [1.0, 0.2, -0.5]);
    let a = scan(&scene, &s, &world_from_a, 0.005, 1);
    let b = scan(&scene, &s, &world_from_b, 0.005, 2);
    let config = AlignConfig::default();
    let pa = ScanPyramid::build(a, &s.model.lidar, config.pyramid_levels);
    let pb = ScanPyramid::build(b, &s.model.lidar, config.pyramid_levels);
    let truth = world_from_a.inverse() * world_from_b;
    let result = align_pair(&pb, &pa, &texel::Pose::identity(), &config);
    let (r, t) = error_deg_mm(&result.world_from_source, &truth);
    eprintln!(
        "{:?} iters {} fitness {:?} err {r:.4} deg {t:.3} mm degenerate {:?}",
        result.status, result.iterations, result.fitness, result.degenerate
    );
    assert!(result.is_ok());
    assert!(r < 0.05 && t < 2.0, "{r} deg {t} mm");
}
