//! The tone-mapping pass on the GPU (lavapipe in CI) against its CPU reference
//! (`texel_viewer::tonemap`), for every operator, with auto-exposure and a fixed
//! adaptation level, on radiance spanning 24 stops with black, non-finite and
//! beyond-half-float values.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use support::gpu;
use texel_viewer::gpu::{ToneMapPass, tone_map_headless};
use texel_viewer::tonemap::{ToneMapSettings, ToneOperator, log_average_luminance, tone_map_image};

/// 97 x 61 (odd, so the 16 x 16 tiles of the reduction overhang both edges): radiance
/// from 2^-12 to 2^12 along x, a hue per row band, and a few hostile values.
fn radiance() -> (u32, u32, Vec<[f32; 3]>) {
    let (w, h) = (97u32, 61u32);
    let mut r = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let level = (x as f32 / (w - 1) as f32 * 24.0 - 12.0).exp2();
            let tint = match (y / 8) % 4 {
                0 => [1.0, 1.0, 1.0],
                1 => [1.0, 0.4, 0.1],
                2 => [0.2, 0.9, 0.3],
                _ => [0.1, 0.3, 1.0],
            };
            r.push(tint.map(|t| t * level));
        }
    }
    r[0] = [0.0; 3];
    r[1] = [f32::NAN, f32::INFINITY, -3.0];
    r[2] = [1.0e6, 2.0e5, 7.0e4];
    (w, h, r)
}

/// What the GPU holds: half floats, hostile values cleaned as the upload does.
fn as_uploaded(r: &[[f32; 3]]) -> Vec<[f32; 3]> {
    r.iter()
        .map(|c| {
            c.map(|v| {
                let v = if v.is_finite() { v.max(0.0) } else { 0.0 };
                half::f16::from_f32(v.min(65504.0)).to_f32()
            })
        })
        .collect()
}

#[test]
fn the_gpu_pass_matches_the_cpu_reference() {
    let (w, h, r) = radiance();
    let uploaded = as_uploaded(&r);
    let mut pass = ToneMapPass::new(gpu());
    let want_l_a = log_average_luminance(&uploaded);
    for operator in ToneOperator::ALL {
        for adaptation in [None, Some(0.05)] {
            for exposure_ev in [0.0, -1.5] {
                let settings = ToneMapSettings {
                    operator,
                    exposure_ev,
                    adaptation,
                    ..Default::default()
                };
                let (image, l_a) =
                    tone_map_headless(gpu(), &mut pass, w, h, &r, &settings).unwrap();
                assert_eq!(image.dimensions(), (w, h));
                match adaptation {
                    None => assert!(
                        (l_a / want_l_a - 1.0).abs() < 1e-3,
                        "log-average {l_a} vs {want_l_a}"
                    ),
                    Some(a) => assert_eq!(l_a, a),
                }
                let (cpu, _) = tone_map_image(
                    &uploaded,
                    &ToneMapSettings {
                        adaptation: Some(l_a),
                        ..settings
                    },
                );
                let mut worst = 0u8;
                let mut off_by_more_than_one = 0;
                for (g, c) in image.as_raw().iter().zip(&cpu) {
                    let d = g.abs_diff(*c);
                    worst = worst.max(d);
                    off_by_more_than_one += usize::from(d > 1);
                }
                let label = format!("{} {adaptation:?} {exposure_ev}", operator.name());
                eprintln!(
                    "{label}: adaptation {l_a:.5} (CPU {want_l_a:.5}), worst difference {worst}, \
                     {off_by_more_than_one} of {} values off by more than 1",
                    cpu.len()
                );
                assert!(worst <= 2, "{label}: worst {worst}");
                assert!(
                    off_by_more_than_one * 1000 <= cpu.len(),
                    "{label}: {off_by_more_than_one} values off by 2"
                );
                // The picture spans the range: black at the dark end, bright at the
                // other (even 1.5 stops down).
                let px = |x: u32, y: u32| image.get_pixel(x, y).0;
                assert!(px(5, 0)[1] < 40 && px(95, 0)[1] > 120, "{label}");
            }
        }
    }
}

#[test]
fn a_black_image_and_an_image_of_one_pixel_tone_map_without_nan() {
    let mut pass = ToneMapPass::new(gpu());
    let settings = ToneMapSettings::default();
    let (image, l_a) =
        tone_map_headless(gpu(), &mut pass, 5, 3, &[[0.0; 3]; 15], &settings).unwrap();
    assert!((l_a - 1.0e-4).abs() < 1e-8, "{l_a}");
    assert!(image.pixels().all(|p| p.0 == [0, 0, 0, 255]));
    let (image, l_a) =
        tone_map_headless(gpu(), &mut pass, 1, 1, &[[2.0, 1.0, 0.5]], &settings).unwrap();
    assert!(l_a.is_finite() && l_a > 0.0);
    assert!(image.get_pixel(0, 0).0[0] > 0);
}

#[test]
fn the_tonemap_command_writes_what_the_pass_draws_and_names_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h, r) = radiance();
    let exr = dir.path().join("r.exr");
    texel::radiance::exr::write_radiance_exr(&exr, w, h, &r).unwrap();
    let png = dir.path().join("r.png");
    let run = |args: &[&str]| {
        std::process::Command::new(support::viewer_binary())
            .arg("tonemap")
            .args(args)
            .output()
            .unwrap()
    };
    let o = run(&[
        "--exr",
        exr.to_str().unwrap(),
        "--out",
        png.to_str().unwrap(),
        "--operator",
        "filmic",
        "--exposure-ev",
        "-1",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("filmic with adaptation level"), "{stdout}");
    let written = image::open(&png).unwrap().to_rgb8();
    let mut pass = ToneMapPass::new(gpu());
    let settings = ToneMapSettings {
        operator: ToneOperator::Filmic,
        exposure_ev: -1.0,
        ..Default::default()
    };
    // The file holds what was written (the EXR reader cleans hostile values to 0).
    let (drawn, _) = tone_map_headless(
        gpu(),
        &mut pass,
        w,
        h,
        &texel::radiance::exr::read_radiance_exr(&exr).unwrap().2,
        &settings,
    )
    .unwrap();
    for (a, b) in written.pixels().zip(drawn.pixels()) {
        assert_eq!(a.0[..3], b.0[..3]);
    }
    for (args, needle) in [
        (
            vec!["--exr", "missing.exr", "--out", "x.png"],
            "missing.exr",
        ),
        (
            vec![
                "--exr",
                exr.to_str().unwrap(),
                "--out",
                "x.png",
                "--operator",
                "drago",
            ],
            "unknown operator \"drago\"",
        ),
        (
            vec![
                "--exr",
                exr.to_str().unwrap(),
                "--out",
                "x.png",
                "--gamma",
                "0",
            ],
            "gamma = 0",
        ),
    ] {
        let o = run(&args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && stderr.contains(needle),
            "{args:?}: {stderr}"
        );
    }
}
