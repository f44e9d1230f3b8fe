//! Pairwise alignment against ground truth: analytic scenes (exact poses) and the
//! simulator's `lab` and `plane` scenes; the hard cases stay finite and say what is
//! wrong or unobservable.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod register_support;

use std::path::Path;
use std::sync::Arc;

use nalgebra::Vector6;
use register_support::*;
use texel::{FuseConfig, Pose, TexelScan, fuse};
use texel_register::se3;
use texel_register::{
    AlignConfig, FailureReason, PhotometricMode, RobustKernel, ScanPyramid, Solver, align_pair,
};

/// The scan's pyramid with its EO pyramid, as the registrar builds it.
fn pyramid(scan: Arc<texel::TexelScan>, s: &texel::Sensor) -> ScanPyramid {
    eo_pyramid(scan, s)
}

fn with_photometric(mode: PhotometricMode) -> AlignConfig {
    let mut config = AlignConfig::default();
    config.photometric.mode = mode;
    config
}

fn assert_finite(a: &texel_register::Alignment) {
    assert!(se3::is_finite(&a.world_from_source));
    assert!(a.covariance.iter().all(|c| c.is_finite()));
    assert!(a.information.iter().all(|c| c.is_finite()));
    assert!(a.fitness.rms_residual_m.is_finite() && a.fitness.inlier_ratio.is_finite());
}

/// A simulated scene at 64x64 lidar pixels, with the given effects.
fn sim(scene: &str, effects: Vec<sims::Effect>) -> sims::Simulator {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../configs/scenes/{scene}.toml"));
    let scene = sims::Scene::load(&path).unwrap();
    let options = sims::SimOptions {
        seed: 3,
        effects: Some(effects),
        lidar_size: Some([64, 64]),
        eo_size: Some([160, 120]),
        ..Default::default()
    };
    sims::Simulator::with_options(scene, &options).unwrap()
}

fn sim_scan(sim: &sims::Simulator, world_from_eo: &Pose, t: u64) -> Arc<TexelScan> {
    let pair = sim.render_at(world_from_eo, t, t);
    Arc::new(fuse(&pair.range, pair.eo, sim.sensor(), &FuseConfig::default()).unwrap())
}

#[test]
fn room_pair_converges_with_every_kernel_and_solver() {
    let s = sensor(64, 64, 0.005);
    let scene = Scene::room();
    let world_from_a = look_at([-2.0, 0.5, 1.5], [3.0, 0.0, 0.8]);
    let world_from_b = world_from_a * perturbation(3.0, [0.2, 1.0, 0.3], 0.05, [1.0, 0.2, -0.5]);
    let a = pyramid(scan(&scene, &s, &world_from_a, 0.005, 1), &s);
    let b = pyramid(scan(&scene, &s, &world_from_b, 0.005, 2), &s);
    let truth = world_from_a.inverse() * world_from_b;
    for kernel in [
        RobustKernel::Huber,
        RobustKernel::Tukey,
        RobustKernel::GemanMcclure,
    ] {
        for solver in [Solver::GaussNewton, Solver::LevenbergMarquardt] {
            for photometric in [PhotometricMode::Off, PhotometricMode::Full] {
                let config = AlignConfig {
                    kernel,
                    solver,
                    ..with_photometric(photometric)
                };
                let result = align_pair(&b, &a, &Pose::identity(), &config);
                let (r, t) = error_deg_mm(&result.world_from_source, &truth);
                assert!(result.is_ok(), "{kernel:?} {solver:?}: {:?}", result.status);
                assert!(
                    r < 0.1 && t < 5.0,
                    "{kernel:?} {solver:?} {photometric:?}: {r} deg {t} mm"
                );
                assert!(result.degenerate.is_empty(), "{:?}", result.degenerate);
                assert_finite(&result);
                // The start was 3 degrees and 5 cm off: the solver really moved.
                let (r0, t0) = error_deg_mm(&Pose::identity(), &truth);
                assert!(r0 > 2.9 && t0 > 49.0);
            }
        }
    }
}

#[test]
fn lab_converges_from_five_degrees_and_twenty_centimetres() {
    let sim = sim(
        "lab",
        vec![
            sims::Effect::RangeNoise(Default::default()),
            sims::Effect::MixedPixels(Default::default()),
        ],
    );
    let world_from_a = sim.true_pose(0);
    let world_from_b = sim.true_pose(1);
    let a = pyramid(sim_scan(&sim, &world_from_a, 0), sim.sensor());
    let b = pyramid(sim_scan(&sim, &world_from_b, 1), sim.sensor());
    let truth = world_from_a.inverse() * world_from_b;
    let initial = truth * perturbation(5.0, [0.3, -1.0, 0.4], 0.2, [0.5, 0.3, -1.0]);
    let (r0, t0) = error_deg_mm(&initial, &truth);
    assert!(r0 > 4.9 && t0 > 190.0, "{r0} {t0}");
    let result = align_pair(&b, &a, &initial, &AlignConfig::default());
    let (r, t) = error_deg_mm(&result.world_from_source, &truth);
    assert!(result.is_ok(), "{:?}", result.status);
    assert!(r < 0.15 && t < 5.0, "{r} deg {t} mm");
    assert_finite(&result);
}

#[test]
fn plane_keeps_the_prior_in_its_three_unobservable_directions_without_the_eo() {
    let sim = sim("wall", vec![sims::Effect::RangeNoise(Default::default())]);
    let world_from_a = sim.true_pose(4);
    let a = pyramid(sim_scan(&sim, &world_from_a, 0), sim.sensor());
    // The second view: 1.5 degrees and 4 cm away in every direction.
    let truth = perturbation(1.5, [0.4, 0.8, -0.3], 0.04, [0.6, -0.5, 0.6]);
    let b = pyramid(sim_scan(&sim, &(world_from_a * truth), 1), sim.sensor());
    let initial = Pose::identity();
    // Geometry alone: the three directions keep the prior.
    let result = align_pair(&b, &a, &initial, &with_photometric(PhotometricMode::Off));
    assert_finite(&result);
    assert!(result.is_ok(), "{:?}", result.status);
    assert_eq!(result.degenerate.len(), 3, "{:?}", result.degenerate);
    assert_eq!(result.photometric.residuals, 0);
    // The degenerate subspace in scaled coordinates (ω·L, v).
    let dirs: Vec<Vector6<f64>> = result
        .degenerate
        .iter()
        .map(|d| Vector6::from_column_slice(&d.direction))
        .collect();
    let length = {
        let l0 = &b.levels[0];
        let s = l0.samples(2);
        (s.iter()
            .map(|&i| l0.point(i as usize).norm_squared())
            .sum::<f64>()
            / s.len() as f64)
            .sqrt()
    };
    let scaled = |d: Vector6<f64>| {
        Vector6::new(
            d[0] * length,
            d[1] * length,
            d[2] * length,
            d[3],
            d[4],
            d[5],
        )
    };
    let moved = scaled(se3::log(&(initial.inverse() * result.world_from_source)));
    let remaining = scaled(se3::log(&(result.world_from_source.inverse() * truth)));
    let project = |v: &Vector6<f64>| dirs.iter().map(|d| d.dot(v).powi(2)).sum::<f64>().sqrt();
    // Along the degenerate directions the estimate did not move from the prior...
    assert!(
        project(&moved) < 0.02 * moved.norm() && project(&moved) < 1e-3,
        "moved {} along degenerate of {}",
        project(&moved),
        moved.norm()
    );
    // ... and the truth's motion there is still to be explained (it was not guessed).
    assert!(project(&remaining) > 0.01, "{}", project(&remaining));
    // Along the observable ones it reached the truth.
    let observable = remaining
        - dirs
            .iter()
            .fold(Vector6::zeros(), |acc, d| acc + d * d.dot(&remaining));
    assert!(
        observable.norm() < 2e-3,
        "observable error {}",
        observable.norm()
    );
    // The covariance in the degenerate directions is the prior's, far larger than in
    // the observed ones.
    let names: Vec<&str> = result
        .degenerate
        .iter()
        .map(|d| d.description.as_str())
        .collect();
    assert_eq!(
        names
            .iter()
            .filter(|n| n.starts_with("translation"))
            .count(),
        2,
        "{names:?}"
    );
    assert_eq!(
        names
            .iter()
            .filter(|n| n.starts_with("rotation about"))
            .count(),
        1,
        "{names:?}"
    );
}

#[test]
fn corridor_has_one_unobservable_direction_along_its_axis() {
    // The simulator's featureless corridor (plain walls, open ends), looking down it.
    let sim = sim(
        "corridor-plain",
        vec![sims::Effect::RangeNoise(Default::default())],
    );
    let world_from_a = sim.true_pose(10);
    let truth = perturbation(1.0, [0.0, 1.0, 0.2], 0.05, [0.2, 0.3, 1.0]);
    let a = pyramid(sim_scan(&sim, &world_from_a, 0), sim.sensor());
    let b = pyramid(sim_scan(&sim, &(world_from_a * truth), 1), sim.sensor());
    let result = align_pair(&b, &a, &Pose::identity(), &AlignConfig::default());
    assert_finite(&result);
    assert!(result.is_ok(), "{:?}", result.status);
    assert_eq!(result.degenerate.len(), 1, "{:?}", result.degenerate);
    // The corridor axis (world x) in the camera frame.
    let axis = world_from_a.rotation.inverse() * nalgebra::Vector3::x();
    let d = result.degenerate[0].direction;
    let along = nalgebra::Vector3::new(d[3], d[4], d[5]);
    assert!(
        along.dot(&axis).abs() > 0.95,
        "{:?} vs {axis:?}",
        result.degenerate[0]
    );
    assert!(
        result.degenerate[0]
            .description
            .starts_with("translation along")
    );
    // Across the axis the walls, floor and ceiling fix the pose.
    let remaining = se3::log(&(result.world_from_source.inverse() * truth));
    let t = nalgebra::Vector3::new(remaining[3], remaining[4], remaining[5]);
    let across = t - axis * axis.dot(&t);
    assert!(across.norm() < 0.005, "{across:?}");
}

#[test]
fn views_without_overlap_fail_with_the_reason() {
    let s = sensor(64, 64, 0.005);
    let scene = Scene::room();
    let world_from_a = look_at([0.0, 0.0, 1.5], [3.0, 0.0, 1.5]);
    let world_from_b = look_at([0.0, 0.0, 1.5], [-3.0, 0.0, 1.5]);
    let a = pyramid(scan(&scene, &s, &world_from_a, 0.005, 1), &s);
    let b = pyramid(scan(&scene, &s, &world_from_b, 0.005, 2), &s);
    // Back to back: at the true relative pose nothing of one lies in the other's view.
    let truth = world_from_a.inverse() * world_from_b;
    let result = align_pair(&b, &a, &truth, &AlignConfig::default());
    assert!(
        matches!(result.status, Err(FailureReason::TooLittleOverlap { .. })),
        "{:?}",
        result.status
    );
    assert!(
        result
            .status
            .as_ref()
            .unwrap_err()
            .to_string()
            .contains("overlap")
    );
    assert_finite(&result);
}

#[test]
fn all_outliers_fail_and_never_give_a_pose() {
    let s = sensor(64, 64, 0.005);
    let a = pyramid(
        scan(
            &Scene::room(),
            &s,
            &look_at([-2.0, 0.5, 1.5], [3.0, 0.0, 0.8]),
            0.005,
            1,
        ),
        &s,
    );
    // Another scene altogether seen with the same pose: a tilted plane half a metre
    // nearer than anything in the room view.
    let other = Scene {
        shapes: vec![Shape::Plane {
            n: nalgebra::Vector3::new(0.8, 0.3, 0.4).normalize(),
            d: -0.5,
        }],
    };
    let b = pyramid(
        scan(
            &other,
            &s,
            &look_at([-2.0, 0.5, 1.5], [3.0, 0.0, 0.8]),
            0.005,
            2,
        ),
        &s,
    );
    let result = align_pair(&b, &a, &Pose::identity(), &AlignConfig::default());
    assert!(
        result.status.is_err(),
        "{:?} {:?}",
        result.status,
        result.fitness
    );
    assert_finite(&result);
}

#[test]
fn frames_full_of_no_returns_fail_cleanly_or_register() {
    let s = sensor(64, 64, 0.005);
    let scene = Scene::room();
    let pose = look_at([-2.0, 0.5, 1.5], [3.0, 0.0, 0.8]);
    let a = pyramid(scan(&scene, &s, &pose, 0.005, 1), &s);
    let (mut range, eo) = render(&scene, &s, &pose, 0.005, 2);
    // Every pixel a no-return of some kind.
    for (i, r) in range.ranges_m.iter_mut().enumerate() {
        *r = [f32::NAN, 0.0, f32::INFINITY, -1.0][i % 4];
    }
    let empty = Arc::new(fuse(&range, eo.clone(), &s, &FuseConfig::default()).unwrap());
    let result = align_pair(
        &pyramid(empty, &s),
        &a,
        &Pose::identity(),
        &AlignConfig::default(),
    );
    assert!(
        matches!(result.status, Err(FailureReason::NoPoints { .. })),
        "{:?}",
        result.status
    );
    assert_finite(&result);
    // The target empty instead.
    let empty = Arc::new(fuse(&range, eo.clone(), &s, &FuseConfig::default()).unwrap());
    let result = align_pair(
        &a,
        &pyramid(empty, &s),
        &Pose::identity(),
        &AlignConfig::default(),
    );
    assert!(
        matches!(result.status, Err(FailureReason::NoPoints { .. })),
        "{:?}",
        result.status
    );
    // 95 % no-returns in scattered pixels: no normals survive, a clean failure.
    let (mut range, eo) = render(&scene, &s, &pose, 0.005, 3);
    for (i, r) in range.ranges_m.iter_mut().enumerate() {
        if i % 20 != 0 {
            *r = f32::NAN;
        }
    }
    let sparse = Arc::new(fuse(&range, eo, &s, &FuseConfig::default()).unwrap());
    let result = align_pair(
        &pyramid(sparse, &s),
        &a,
        &Pose::identity(),
        &AlignConfig::default(),
    );
    assert!(result.status.is_err());
    assert_finite(&result);
}

#[test]
fn identical_frames_give_the_identity() {
    let s = sensor(64, 64, 0.005);
    let sc = scan(
        &Scene::room(),
        &s,
        &look_at([-2.0, 0.5, 1.5], [3.0, 0.0, 0.8]),
        0.005,
        1,
    );
    let a = pyramid(Arc::clone(&sc), &s);
    let b = pyramid(sc, &s);
    let result = align_pair(&b, &a, &Pose::identity(), &AlignConfig::default());
    assert!(result.is_ok());
    let (r, t) = error_deg_mm(&result.world_from_source, &Pose::identity());
    assert!(r < 1e-9 && t < 1e-9, "{r} {t}");
    assert_eq!(result.fitness.rms_residual_m, 0.0);
    assert!(result.iterations <= 3 * AlignConfig::default().pyramid_levels);
}

#[test]
fn poses_are_bit_identical_with_one_and_two_threads() {
    let s = sensor(64, 64, 0.005);
    let scene = Scene::room();
    let world_from_a = look_at([-2.0, 0.5, 1.5], [3.0, 0.0, 0.8]);
    let world_from_b = world_from_a * perturbation(3.0, [0.2, 1.0, 0.3], 0.05, [1.0, 0.2, -0.5]);
    let a = pyramid(scan(&scene, &s, &world_from_a, 0.005, 1), &s);
    let b = pyramid(scan(&scene, &s, &world_from_b, 0.005, 2), &s);
    let config = AlignConfig {
        point_stride: 1,
        ..with_photometric(PhotometricMode::Full)
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| align_pair(&b, &a, &Pose::identity(), &config))
    };
    let (one, two) = (run(1), run(2));
    let serial = align_pair(
        &b,
        &a,
        &Pose::identity(),
        &AlignConfig {
            parallel: false,
            ..config.clone()
        },
    );
    // More samples than one chunk, so the parallel path really splits the work.
    assert!(one.fitness.samples > 2 * texel_register::normal_eq::CHUNK);
    for other in [&two, &serial] {
        assert_eq!(
            one.world_from_source.translation.vector,
            other.world_from_source.translation.vector
        );
        assert_eq!(
            one.world_from_source.rotation.quaternion(),
            other.world_from_source.rotation.quaternion()
        );
        assert_eq!(one.covariance, other.covariance);
        assert_eq!(one.iterations, other.iterations);
    }
}

#[test]
fn the_eo_image_fixes_what_the_textured_plane_leaves_to_the_prior() {
    let sim = sim("wall", vec![sims::Effect::RangeNoise(Default::default())]);
    let world_from_a = sim.true_pose(4);
    let a = pyramid(sim_scan(&sim, &world_from_a, 0), sim.sensor());
    let truth = perturbation(1.5, [0.4, 0.8, -0.3], 0.04, [0.6, -0.5, 0.6]);
    let b = pyramid(sim_scan(&sim, &(world_from_a * truth), 1), sim.sensor());
    let result = align_pair(&b, &a, &Pose::identity(), &AlignConfig::default());
    assert_finite(&result);
    assert!(result.is_ok(), "{:?}", result.status);
    let (r, t) = error_deg_mm(&result.world_from_source, &truth);
    assert!(result.degenerate.is_empty(), "{:?}", result.degenerate);
    // Selective: admitted in the three weak directions only.
    assert_eq!(result.photometric.admitted_directions, 3);
    assert!(result.photometric.residuals > 200);
    assert!(result.photometric.min_eigenvalue > 100.0 * result.photometric.geometry_min_eigenvalue);
    assert!(r < 0.1 && t < 5.0, "{r} deg {t} mm");
}
