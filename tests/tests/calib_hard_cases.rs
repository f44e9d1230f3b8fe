//! Hard cases: strong barrel distortion converges, boards near the image border,
//! degenerate captures refused with the constraint that is missing, and no NaN from
//! garbage input.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod calib_common;

use calib::config::CalibConfig;
use calib::error::CalibError;
use calib::pipeline::{CalibInput, calibrate};
use calib_common::*;
use texel_bench::calibration::simulate::{PoseStyle, accuracy, render_input, sample_poses};

fn run(input: &CalibInput) -> Result<calib::pipeline::Calibration, CalibError> {
    calibrate(input, &CalibConfig::default(), &mut |_, _, _| {})
}

#[test]
fn strong_barrel_distortion_converges() {
    // k1 = -0.3, k2 = 0.06: corners move by up to ~60 px at the image's corners.
    let sim = sim(target_scene(), 8, Some(effects_with_distortion(6.0)));
    let config = CalibConfig::default();
    let poses = sample_poses(&sim, &config.target, 14, PoseStyle::Varied, 8);
    let input = render_input(&sim, &poses[..12], 0);
    let held = render_input(&sim, &poses[12..], 500);
    let c = run(&input).unwrap();
    assert!(
        c.eo_only.converged && c.eo.per_view.len() >= 11,
        "{} views",
        c.eo.per_view.len()
    );
    let a = accuracy(&c, sim.sensor_model(), &held, &config.target);
    println!("{a:?}");
    assert!(a.focal_error_percent < 0.3, "{a:?}");
    assert!(a.held_out_rms_px < 0.2, "{a:?}");
    let texel::Distortion::PlumbBob(d) = c.sensor.eo.distortion else {
        panic!("no distortion estimated");
    };
    assert!((d.k1 + 0.3).abs() < 0.02, "k1 {}", d.k1);
}

#[test]
fn boards_near_the_image_border_are_detected_and_calibrate() {
    let sim = sim(target_scene(), 9, None);
    let config = CalibConfig::default();
    let mut poses = sample_poses(&sim, &config.target, 8, PoseStyle::NearBorder, 9);
    poses.extend(sample_poses(&sim, &config.target, 6, PoseStyle::Varied, 19));
    let input = render_input(&sim, &poses, 0);
    let c = run(&input).unwrap();
    let border_used = c.eo.per_view.iter().filter(|v| v.view < 8).count();
    assert!(
        border_used >= 7,
        "only {border_used} of 8 border views used"
    );
    assert!(c.eo.rms_px < 0.15, "{}", c.eo.rms_px);
    let truth = &sim.sensor_model().eo;
    assert!((c.sensor.eo.fx - truth.fx).abs() / truth.fx < 0.003);
}

fn message(r: Result<calib::pipeline::Calibration, CalibError>) -> (CalibError, String) {
    match r {
        Ok(_) => panic!("a degenerate capture was calibrated"),
        Err(e) => {
            let m = e.to_string();
            (e, m)
        }
    }
}

#[test]
fn degenerate_captures_are_refused_naming_the_missing_constraint() {
    let sim = sim(target_scene(), 10, None);
    let config = CalibConfig::default();
    let good = sample_poses(&sim, &config.target, 2, PoseStyle::Varied, 10);
    // Two views.
    let (e, m) = message(run(&render_input(&sim, &good, 0)));
    assert!(
        matches!(e, CalibError::TooFewViews { usable: 2, .. }),
        "{m}"
    );
    assert!(
        m.contains("at least 3") && m.contains("Capture more views"),
        "{m}"
    );
    // Square-on views only.
    let fronto = sample_poses(&sim, &config.target, 4, PoseStyle::FrontoParallel, 10);
    let (e, m) = message(run(&render_input(&sim, &fronto, 0)));
    assert!(matches!(e, CalibError::FrontoParallel { .. }), "{m}");
    assert!(m.contains("fronto-parallel") && m.contains("tilted"), "{m}");
    // A little tilt, not enough to fix the focal length.
    let slight = sample_poses(&sim, &config.target, 4, PoseStyle::Tilt(9.0), 10);
    let (e, m) = message(run(&render_input(&sim, &slight, 0)));
    assert!(matches!(e, CalibError::TooLittleTilt { .. }), "{m}");
    assert!(
        m.contains("focal length") && m.contains("tilted by 20-45 degrees"),
        "{m}"
    );
    // The board always cut by the lidar's narrower field of view.
    let cut = sample_poses(&sim, &config.target, 5, PoseStyle::LidarCut, 10);
    let (e, m) = message(run(&render_input(&sim, &cut, 0)));
    assert!(matches!(e, CalibError::LidarNeverSawTarget { .. }), "{m}");
    assert!(m.contains("never fully seen by the lidar"), "{m}");
}

#[test]
fn garbage_frames_give_errors_not_nan() {
    let sim = sim(target_scene(), 11, None);
    let config = CalibConfig::default();
    let poses = sample_poses(&sim, &config.target, 3, PoseStyle::Varied, 11);
    let mut input = render_input(&sim, &poses, 0);
    let mut rng = texel_bench::calibration::simulate::Rng::new(3);
    for v in &mut input.views {
        for b in &mut v.pair.eo.rgb {
            *b = (rng.next_u64() & 0xff) as u8;
        }
        for (k, r) in v.pair.range.ranges_m.iter_mut().enumerate() {
            *r = match k % 4 {
                0 => f32::NAN,
                1 => f32::INFINITY,
                2 => -1.0,
                _ => rng.uniform(0.0, 1e6) as f32,
            };
        }
        v.pair.range.intensity = Some(vec![f32::NAN; v.pair.range.pixel_count()]);
    }
    let (e, _) = message(run(&input));
    assert!(matches!(e, CalibError::TooFewViews { usable: 0, .. }));
    // Empty input and inconsistent buffers are refused too.
    input.views.clear();
    assert!(run(&input).is_err());
}

#[test]
fn lidar_intrinsics_are_estimated_when_asked() {
    let sim = sim(target_scene(), 13, None);
    let mut config = CalibConfig::default();
    config.solver.estimate_lidar_intrinsics = true;
    let poses = sample_poses(&sim, &config.target, 16, PoseStyle::Varied, 13);
    let mut input = render_input(&sim, &poses, 0);
    // Start from a wrong lidar calibration: 3 % off in focal length, 2 px in centre.
    let truth = sim.sensor_model().lidar.clone();
    input.lidar.fx *= 1.03;
    input.lidar.fy *= 0.97;
    input.lidar.cx += 2.0;
    let c = calibrate(&input, &config, &mut |_, _, _| {}).unwrap();
    let l = &c.lidar.lidar;
    let sd = c.lidar.lidar_intrinsics_std.unwrap();
    println!("{l:?} ± {sd:?}");
    assert!(
        (l.fx - truth.fx).abs() / truth.fx < 0.003,
        "fx {} vs {}",
        l.fx,
        truth.fx
    );
    assert!(
        (l.fy - truth.fy).abs() / truth.fy < 0.003,
        "fy {} vs {}",
        l.fy,
        truth.fy
    );
    // The principal point trades against the extrinsic's rotation (a shift of d px is
    // a turn of d / f): it is recovered only to its stated uncertainty.
    for (est, t, s) in [(l.cx, truth.cx, sd[2]), (l.cy, truth.cy, sd[3])] {
        assert!(
            (est - t).abs() < 1.0 && (est - t).abs() < 4.0 * s,
            "{est} vs {t} ± {s}"
        );
    }
    assert!((l.fx - truth.fx).abs() < 4.0 * sd[0] + 0.05);
    assert_eq!(c.sensor.lidar.fx, l.fx);
}
