//! `texel-calib response` on a bracket of PNG images of a radiance ramp through the
//! sRGB curve: the CSV it writes holds the true inverse log response; misaligned or
//! malformed inputs are refused by name.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::path::{Path, PathBuf};
use std::process::Command;

const TIMES_S: [f64; 4] = [0.125, 0.5, 2.0, 8.0];

fn srgb_encode(x: f64) -> f64 {
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

fn srgb_decode(v: f64) -> f64 {
    if v <= 0.040_45 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// The bracket's images: a radiance ramp over three and a half decades.
fn write_bracket(dir: &Path, width: u32, height: u32) -> Vec<PathBuf> {
    TIMES_S
        .iter()
        .enumerate()
        .map(|(k, t)| {
            let img = image::RgbImage::from_fn(width, height, |x, y| {
                let s = f64::from(x + width * y) / f64::from(width * height);
                let e = (0.002f64.ln() + s * (6.0f64 / 0.002).ln()).exp() * t;
                let v = (srgb_encode(e.clamp(0.0, 1.0)) * 255.0).round() as u8;
                image::Rgb([v, v, v])
            });
            let path = dir.join(format!("bracket-{k}.png"));
            img.save(&path).unwrap();
            path
        })
        .collect()
}

fn texel_calib(args: &[String]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_texel-calib"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn image_args(paths: &[PathBuf]) -> Vec<String> {
    paths
        .iter()
        .zip(TIMES_S)
        .flat_map(|(p, t)| ["--image".to_string(), format!("{}@{t}", p.display())])
        .collect()
}

#[test]
fn the_response_command_writes_the_true_curve() {
    let dir = tempfile::tempdir().unwrap();
    let images = write_bracket(dir.path(), 96, 64);
    let csv = dir.path().join("response.csv");
    let sensor_out = dir.path().join("sensor.toml");
    let sensor_in =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/sensors/texel-default.toml");
    let mut args = vec!["response".to_string()];
    args.extend(image_args(&images));
    args.extend(["--out".into(), csv.display().to_string()]);
    args.extend(["--sensor-in".into(), sensor_in.display().to_string()]);
    args.extend(["--sensor-out".into(), sensor_out.display().to_string()]);
    let (ok, stdout, stderr) = texel_calib(&args);
    assert!(ok, "{stderr}");
    println!("{stdout}");
    // The sensor file carries the curve, and is otherwise the one it was made from.
    let sensor = texel::SensorModel::load(&sensor_out).unwrap();
    let curve = sensor
        .eo_response
        .clone()
        .expect("the sensor file's [eo_response]");
    let mut plain = sensor.clone();
    plain.eo_response = None;
    assert_eq!(plain, texel::SensorModel::load(&sensor_in).unwrap());
    let text = std::fs::read_to_string(&csv).unwrap();
    let rows: Vec<Vec<f64>> = text
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 256);
    for (z, row) in rows.iter().enumerate() {
        for c in 0..3 {
            let g = curve.log_exposure(c, z as u8);
            assert!(
                (g - row[c + 1]).abs() < 1e-6,
                "{z} {c}: {g} vs {}",
                row[c + 1]
            );
        }
    }
    let truth = |z: usize| srgb_decode(z as f64 / 255.0).ln() - srgb_decode(128.0 / 255.0).ln();
    let mut worst: f64 = 0.0;
    for (z, row) in rows.iter().enumerate().take(241).skip(16) {
        for g in &row[1..=3] {
            worst = worst.max((g - truth(z)).abs());
        }
    }
    println!("worst error in ln exposure over 16..=240: {worst:.4}");
    assert!(worst < 0.05, "{worst}");
}

#[test]
fn misaligned_or_malformed_brackets_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let mut images = write_bracket(dir.path(), 32, 16);
    let small_dir = dir.path().join("small");
    std::fs::create_dir_all(&small_dir).unwrap();
    let small = write_bracket(&small_dir, 16, 16);
    images[2] = dir.path().join("small.png");
    std::fs::copy(&small[2], &images[2]).unwrap();
    let csv = dir.path().join("response.csv");
    let mut args = vec!["response".to_string()];
    args.extend(image_args(&images));
    args.extend(["--out".into(), csv.display().to_string()]);
    let (ok, _, stderr) = texel_calib(&args);
    assert!(!ok && stderr.contains("small.png is 16x16"), "{stderr}");
    // One exposure time for every image: equal times carry no bracket.
    let mut args = vec!["response".to_string()];
    for p in &small {
        args.extend(["--image".into(), format!("{}@0.5", p.display())]);
    }
    args.extend(["--out".into(), csv.display().to_string()]);
    let (ok, _, stderr) = texel_calib(&args);
    assert!(!ok && stderr.contains("distinct exposure time"), "{stderr}");
    let (ok, _, stderr) = texel_calib(&[
        "response".into(),
        "--image".into(),
        "a.png".into(),
        "--out".into(),
        csv.display().to_string(),
    ]);
    assert!(!ok && stderr.contains("FILE@SECONDS"), "{stderr}");
    // A sensor file to carry the curve needs a place to be written.
    let mut args = vec!["response".to_string()];
    args.extend(image_args(&write_bracket(dir.path(), 32, 16)));
    args.extend(["--out".into(), csv.display().to_string()]);
    args.extend(["--sensor-in".into(), "in.toml".into()]);
    let (ok, _, stderr) = texel_calib(&args);
    assert!(!ok && stderr.contains("--sensor-out"), "{stderr}");
    assert!(!csv.exists());
}
