//! The EO response curve recovered from a simulated bracket (Debevec & Malik, in
//! `calib::response`) against the simulator's true response, and the radiance merged
//! with it against the simulator's radiance truth.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use sims::{Effect, Scene, SimOptions, Simulator};
use texel::EoFrame;
use texel::radiance::{EoResponse, merge_exposures};

fn effect(name: &str, params: &str) -> Effect {
    let table: toml::Table = toml::from_str(params).unwrap();
    Effect::from_name_and_params(name, table).unwrap()
}

fn percentile(values: &mut [f64], p: f64) -> f64 {
    values.sort_by(f64::total_cmp);
    let i = ((values.len() - 1) as f64 * p).round() as usize;
    values[i]
}

/// `courtyard-hdr` with five exposures two stops apart (the S-curve) and sensor
/// noise, small images.
fn bracket_sim(seed: u64) -> Simulator {
    let scene =
        Scene::load(&texel_e2e::repo_root().join("configs/scenes/courtyard-hdr.toml")).unwrap();
    Simulator::with_options(
        scene,
        &SimOptions {
            seed,
            frames: Some(2),
            effects: Some(vec![
                effect(
                    "exposure",
                    "ev = -0.5\nbracket_ev = [-4.0, -2.0, 0.0, 2.0, 4.0]",
                ),
                effect("sensor_noise", ""),
            ]),
            lidar_size: Some([16, 16]),
            eo_size: Some([160, 120]),
            ..SimOptions::default()
        },
    )
    .unwrap()
}

#[test]
fn the_recovered_curve_matches_the_true_one_and_merges_to_the_radiance_truth() {
    // The bracket at one pose.
    let sim = bracket_sim(11);
    let pose = sim.true_pose(1);
    let frames: Vec<EoFrame> = (0..5).map(|k| sim.render_at(&pose, k, 0).eo).collect();
    let times: Vec<f64> = frames
        .iter()
        .map(|f| f.exposure.unwrap().exposure_time_s)
        .collect();
    let images: Vec<&[u8]> = frames.iter().map(|f| f.rgb.as_slice()).collect();
    let curves = calib::response::recover_rgb_response(&images, &times, 200, 50.0).unwrap();
    let recovered = calib::response::to_eo_response(&curves).unwrap();
    let truth = sim
        .effects()
        .exposure
        .as_ref()
        .unwrap()
        .true_response()
        .unwrap();

    // The curve, up to its arbitrary offset (g(128) = 0 in the recovery).
    let mut worst: f64 = 0.0;
    for c in 0..3 {
        let offset = truth.log_exposure(c, 128) - recovered.log_exposure(c, 128);
        for z in 16..=240u8 {
            let e = (recovered.log_exposure(c, z) + offset - truth.log_exposure(c, z)).abs();
            worst = worst.max(e);
        }
    }
    eprintln!("recovered curve: worst ln-exposure error over 16..=240: {worst:.4}");
    assert!(worst < 0.12, "{worst}");

    // The merge with either curve against the radiance truth (the recovered curve's
    // scale is fixed at its median log ratio to the truth, as its offset is arbitrary).
    let radiance_truth = sim.clean_radiance_at(&pose);
    let refs: Vec<&EoFrame> = frames.iter().collect();
    let errors = |response: &EoResponse, fit_scale: bool| -> (f64, f64) {
        let merged = merge_exposures(&refs, response).unwrap();
        let mut logs = Vec::new();
        for ((got, w), want) in merged.rgb.iter().zip(&merged.weight).zip(&radiance_truth) {
            for c in 0..3 {
                assert!(got[c].is_finite() && got[c] >= 0.0);
                if w[c] > 0.0 && want[c] > 0.0 && got[c] > 0.0 {
                    logs.push((f64::from(got[c]) / f64::from(want[c])).ln());
                }
            }
        }
        let offset = if fit_scale {
            percentile(&mut logs.clone(), 0.5)
        } else {
            0.0
        };
        let mut abs: Vec<f64> = logs.iter().map(|l| (l - offset).abs()).collect();
        (percentile(&mut abs, 0.5), percentile(&mut abs, 0.95))
    };
    let (true_median, true_p95) = errors(&truth, false);
    let (rec_median, rec_p95) = errors(&recovered, true);
    eprintln!(
        "merged radiance, ln error median / p95: true curve {true_median:.4} / {true_p95:.4}, \
         recovered curve {rec_median:.4} / {rec_p95:.4}"
    );
    assert!(true_median < 0.03 && true_p95 < 0.12);
    assert!(rec_median < 0.05 && rec_p95 < 0.15);
}

#[test]
fn texel_calib_recovers_the_curve_from_a_recorded_bracket() {
    // A still camera recording a five-exposure bracket: the frames carry their
    // exposure on /eo/exposure.
    let sim = bracket_sim(12);
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("bracket.mcap");
    let mut w = texel::capture::CaptureWriter::create(&capture, Default::default()).unwrap();
    w.write_sensor(sim.sensor_model(), 1).unwrap();
    let pose = sim.true_pose(1);
    // Two passes over the bracket: the second repeats exposures and is not used.
    for k in 0..10u64 {
        let pair = sim.render_at(&pose, k, 1_000_000_000 + k * 100_000_000);
        w.write_range(&pair.range, texel::capture::RangeEncoding::F32Metres)
            .unwrap();
        w.write_eo(&pair.eo, texel::capture::EoEncoding::Rgb8)
            .unwrap();
    }
    w.finish().unwrap();
    let csv = dir.path().join("response.csv");
    let out = std::process::Command::new(texel_e2e::workspace_binary("texel-calib"))
        .args(["response", "--capture"])
        .arg(&capture)
        .args(["--samples", "200", "--out"])
        .arg(&csv)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("a bracket of 5 exposures"), "{stdout}");
    let truth = sim
        .effects()
        .exposure
        .as_ref()
        .unwrap()
        .true_response()
        .unwrap();
    let rows: Vec<Vec<f64>> = std::fs::read_to_string(&csv)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    let mut worst: f64 = 0.0;
    for c in 0..3 {
        let offset = truth.log_exposure(c, 128) - rows[128][c + 1];
        for (z, row) in rows.iter().enumerate().take(241).skip(16) {
            worst = worst.max((row[c + 1] + offset - truth.log_exposure(c, z as u8)).abs());
        }
    }
    eprintln!("texel-calib response --capture: worst ln-exposure error over 16..=240: {worst:.4}");
    assert!(worst < 0.12, "{worst}");

    // A capture without /eo/exposure is refused by name.
    let plain = dir.path().join("plain.mcap");
    let mut w = texel::capture::CaptureWriter::create(&plain, Default::default()).unwrap();
    w.write_sensor(sim.sensor_model(), 1).unwrap();
    let mut pair = sim.render_at(&pose, 0, 1_000_000_000);
    pair.eo.exposure = None;
    w.write_range(&pair.range, texel::capture::RangeEncoding::F32Metres)
        .unwrap();
    w.write_eo(&pair.eo, texel::capture::EoEncoding::Rgb8)
        .unwrap();
    w.finish().unwrap();
    let out = std::process::Command::new(texel_e2e::workspace_binary("texel-calib"))
        .args(["response", "--capture"])
        .arg(&plain)
        .args(["--out"])
        .arg(&csv)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("/eo/exposure"),
        "{stderr}"
    );
}
