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
fn view_to_exr_writes_the_radiance_truth_that_develops_into_the_png() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = configs().join("scenes/interior-window.toml");
    let pose = "0 -1.8 1.5 -0.77 0 0 0.64";
    let args = |out: &str| {
        vec![
            "view".to_string(),
            "--scene".into(),
            scene_path.to_str().unwrap().into(),
            "--pose".into(),
            pose.into(),
            "--out".into(),
            out.into(),
            "--width".into(),
            "64".into(),
            "--height".into(),
            "48".into(),
        ]
    };
    let exr = dir.path().join("v.exr");
    let png = dir.path().join("v.png");
    for out in [&exr, &png] {
        let a = args(out.to_str().unwrap());
        let o = texel_sims(&a.iter().map(String::as_str).collect::<Vec<_>>());
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let (w, h, radiance) = texel::radiance::exr::read_radiance_exr(&exr).unwrap();
    assert_eq!((w, h), (64, 48));
    // Exactly the library's radiance for that view.
    let scene = sims::Scene::load(&scene_path).unwrap();
    let eo = &scene.sensor().eo;
    let fov = 2.0 * (0.5 * f64::from(eo.height) / eo.fy).atan().to_degrees();
    let camera = texel::PinholeCamera::from_vertical_fov(64, 48, fov).unwrap();
    let world_from_eo = texel::pose::parse_pose(pose).unwrap();
    assert_eq!(radiance, scene.radiance_view(&world_from_eo, &camera));
    // The clean PNG is that radiance clipped at 1 and sRGB-encoded; the window's view
    // is beyond 1 (what an 8-bit image loses), finite and non-negative everywhere.
    let img = image::open(&png).unwrap().to_rgb8();
    let mut beyond_white = 0;
    for (l, p) in radiance.iter().zip(img.pixels()) {
        for c in 0..3 {
            assert!(l[c].is_finite() && l[c] >= 0.0);
            beyond_white += usize::from(l[c] > 1.0);
            let x = l[c].clamp(0.0, 1.0);
            let srgb = if x <= 0.0031308 {
                12.92 * x
            } else {
                1.055 * x.powf(1.0 / 2.4) - 0.055
            };
            assert!(
                (f32::from(p[c]) - 255.0 * srgb).abs() <= 1.0,
                "{l:?} vs {p:?}"
            );
        }
    }
    assert!(
        beyond_white > 100,
        "{beyond_white} channel values beyond white"
    );
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
