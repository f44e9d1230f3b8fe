//! The range bias end to end: a calib-target capture rendered by a lidar that reports
//! every range 2 cm long is calibrated; the sensor file written carries the bias
//! (within 1.5 mm of the truth); and fusing a lab frame rendered by the same biased
//! camera with that file puts the points back on the true surface, where the file
//! without its bias leaves them 2 cm off.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod calib_common;

use calib::config::CalibConfig;
use calib::pipeline::calibrate;
use calib_common::*;
use sims::{CaptureOptions, SimOptions, Simulator};

const BIAS_M: f64 = 0.02;
/// Tolerance on the estimated bias: range noise is 5 mm + 1 mm/m per return, the
/// quantisation 1 mm, and the bias is fitted over thousands of plate returns, so its
/// standard deviation is a fraction of a millimetre.
const BIAS_TOLERANCE_M: f64 = 0.0015;

fn biased(mut scene: sims::Scene) -> sims::Scene {
    let mut sensor = scene.sensor().clone();
    sensor.range_bias_m = BIAS_M;
    scene.set_sensor(sensor);
    scene
}

#[test]
fn a_biased_lidar_is_calibrated_and_fused_back_onto_the_true_surface() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("biased-target.mcap");
    let sim = Simulator::with_options(
        biased(target_scene()),
        &SimOptions {
            seed: 21,
            frames: Some(16),
            ..SimOptions::default()
        },
    )
    .unwrap();
    let options = CaptureOptions {
        writer: texel::capture::WriterOptions {
            sync_to_disk: false,
            ..Default::default()
        },
        ..Default::default()
    };
    sims::render_capture(&sim, &capture, &options, &mut |_, _| {}).unwrap();
    let input = calib::capture::read_capture(&capture).unwrap();
    let c = calibrate(&input, &CalibConfig::default(), &mut |_, _, _| {}).unwrap();
    let text = c.sensor_file_text("biased-target.mcap");
    let model = texel::SensorModel::from_toml_str(&text, "calibrated").unwrap();
    println!(
        "estimated bias {:+.3} mm ± {:.3} mm (truth {:+.1} mm)",
        model.range_bias_m * 1e3,
        c.lidar.range_bias_std_m * 1e3,
        BIAS_M * 1e3
    );
    assert!(
        (model.range_bias_m - BIAS_M).abs() < BIAS_TOLERANCE_M,
        "bias {} m",
        model.range_bias_m
    );
    assert!(c.lidar.range_bias_std_m > 0.0 && c.lidar.range_bias_std_m < BIAS_TOLERANCE_M);

    // A lab frame rendered by the same biased camera, fused with the calibrated file,
    // with the true (biased) model, and with the calibrated file's bias dropped.
    let lab = texel_bench::calibration::simulate::simulator(
        biased(sims::Scene::load(&root().join("configs/scenes/lab.toml")).unwrap()),
        1,
        None,
    )
    .unwrap();
    let truth = texel_bench::calibration::simulate::fusion_errors(&lab, lab.sensor_model(), &[4]);
    let calibrated = texel_bench::calibration::simulate::fusion_errors(&lab, &model, &[4]);
    let unbiased_model = texel::SensorModel {
        range_bias_m: 0.0,
        ..model.clone()
    };
    let ignored = texel_bench::calibration::simulate::fusion_errors(&lab, &unbiased_model, &[4]);
    println!("true {truth:?}\ncalibrated {calibrated:?}\nbias ignored {ignored:?}");
    assert!(calibrated.points > 10_000);
    assert!(
        calibrated.point_rms_mm <= 1.10 * truth.point_rms_mm,
        "{calibrated:?} vs {truth:?}"
    );
    // Without the bias every point sits about 2 cm behind the surface.
    assert!(ignored.point_rms_mm > 15.0, "{ignored:?}");
}
