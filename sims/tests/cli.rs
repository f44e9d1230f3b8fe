//! The real `texel-sims` binary: render, view, effects, and its errors.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use std::process::Command;

use common::configs;

fn texel_sims(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_texel-sims"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn render_writes_a_capture_that_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("plane.mcap");
    let scene = configs().join("scenes/plane.toml");
    let o = texel_sims(&[
        "render",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--frames",
        "2",
        "--seed",
        "3",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("wrote 2 frames"));
    let mut frames = texel::capture::open_texel_frames(&out).unwrap();
    let mut pairs = 0;
    for item in frames.by_ref() {
        if let texel::capture::TexelItem::Pair { pair, .. } = item.unwrap() {
            assert_eq!((pair.range.width, pair.eo.width), (128, 640));
            assert!(pair.range.return_count() > 128 * 128 * 9 / 10);
            pairs += 1;
        }
    }
    assert_eq!(pairs, 2);
}

#[test]
fn view_writes_the_image_asked_for() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("v.png");
    let scene = configs().join("scenes/lab.toml");
    let o = texel_sims(&[
        "view",
        "--scene",
        scene.to_str().unwrap(),
        "--pose",
        "0 -2.2 1.5 -0.828 0 0 0.5606",
        "--out",
        out.to_str().unwrap(),
        "--width",
        "64",
        "--height",
        "48",
        "--fov-deg",
        "50",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let img = image::open(&out).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (64, 48));
    // The room is lit: not a black image.
    let mean: f64 =
        img.as_raw().iter().map(|&v| f64::from(v)).sum::<f64>() / img.as_raw().len() as f64;
    assert!(mean > 40.0, "{mean}");
}

#[test]
fn bad_input_is_named() {
    let scene = configs().join("scenes/plane.toml");
    let o = texel_sims(&[
        "render",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        "/nonexistent/x.mcap",
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("/nonexistent/x.mcap"), "{err}");
    let o = texel_sims(&[
        "view",
        "--scene",
        scene.to_str().unwrap(),
        "--pose",
        "1 2 3",
        "--out",
        "x.png",
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("pose"));
    let o = texel_sims(&["render", "--scene", "missing.toml", "--out", "x.mcap"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing.toml"));
}

#[test]
fn effects_lists_every_effect_with_defaults() {
    let o = texel_sims(&["effects"]);
    assert!(o.status.success());
    let text = String::from_utf8_lossy(&o.stdout);
    for name in sims::effects::EFFECT_NAMES {
        assert!(text.contains(name), "{name} missing");
    }
    assert!(text.contains("max_incidence_deg") && text.contains("85.0"));
}
