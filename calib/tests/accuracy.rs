//! Calibration against the simulator's truth with noise and distortion on: the
//! issue's accuracy targets, and standard deviations that cover the actual errors.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use calib::config::CalibConfig;
use calib::pipeline::calibrate;
use calib::simulate::{PoseStyle, accuracy, render_input, sample_poses};
use common::*;

#[test]
fn calibration_meets_the_accuracy_targets_against_truth() {
    let sim = sim(target_scene(), 7, None);
    let config = CalibConfig::default();
    let views = 32;
    let poses = sample_poses(&sim, &config.target, views + 4, PoseStyle::Varied, 7);
    let input = render_input(&sim, &poses[..views], 0);
    let held_out = render_input(&sim, &poses[views..], 1000);
    let c = calibrate(&input, &config, &mut |_, _, _| {}).unwrap();
    let truth = sim.sensor_model();
    let a = accuracy(&c, truth, &held_out, &config.target);
    println!("{a:?}");
    assert!(
        a.focal_error_percent < 0.2,
        "focal {} %",
        a.focal_error_percent
    );
    assert!(
        a.principal_point_error_px < 1.0,
        "principal point {} px",
        a.principal_point_error_px
    );
    assert_eq!(a.held_out_views, 4);
    assert!(a.held_out_rms_px < 0.2, "held-out {} px", a.held_out_rms_px);
    assert!(
        a.rotation_error_deg < 0.05,
        "rotation {} deg",
        a.rotation_error_deg
    );
    assert!(
        a.translation_error_mm < 2.0,
        "translation {} mm",
        a.translation_error_mm
    );
    // The truth has no range bias.
    assert!(a.range_bias_mm.abs() < 1.0, "bias {} mm", a.range_bias_mm);
    // Every estimate and standard deviation is finite, and the stated uncertainty
    // covers the actual error (4 sigma).
    let k = &c.eo.intrinsics;
    let sd = &c.eo.intrinsics_std;
    assert!(k.iter().chain(sd.iter()).all(|v| v.is_finite()));
    for (i, t) in [truth.eo.fx, truth.eo.fy, truth.eo.cx, truth.eo.cy]
        .iter()
        .enumerate()
    {
        assert!(
            (k[i] - t).abs() < 4.0 * sd[i] + 1e-9,
            "param {i}: {} vs {t} ± {}",
            k[i],
            sd[i]
        );
    }
    let l = &c.lidar;
    let t_err = l.eo_from_lidar.translation.vector - truth.eo_from_lidar.translation.vector;
    for a in 0..3 {
        assert!(
            t_err[a].abs() < 4.0 * l.translation_std_m[a],
            "axis {a}: {} ± {}",
            t_err[a],
            l.translation_std_m[a]
        );
    }
    assert!(l.range_bias_m.abs() < 4.0 * l.range_bias_std_m + 1e-4);
    assert!(c.eo.rms_px < 0.2 && c.eo.rms_px > 0.0);
    // The sensor file reads back.
    let text = c.sensor_file_text("simulated views");
    let back = texel::SensorModel::from_toml_str(&text, "calibrated").unwrap();
    assert_eq!(back.eo.fx, c.sensor.eo.fx);
}
