//! The window under a real X server (Xvfb on a free display): it opens on a capture
//! replayed in-process (no daemon), draws frames through the
//! swapchain, and the read-back frame is not blank.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use std::process::Command;

use support::*;
use texel::capture::PoseTopic;

/// The window on the box capture, replayed fast: its read-back frame once the model
/// holds all three scans (`extra`: more arguments of `open`).
fn screenshot(extra: &[&str]) -> image::RgbaImage {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    // Placed at the capture's own poses: this test is about the window, not registration.
    write_box_capture(&capture, PoseTopic::Texel);
    let shot = dir.path().join("shot.png");
    let (_xvfb, display) = start_xvfb();
    let out = Command::new(viewer_binary())
        .args([
            "open",
            capture.to_str().unwrap(),
            "--width",
            "320",
            "--height",
            "240",
            "--frames",
            "8",
            "--min-scans",
            "3",
            "--fast",
            "--screenshot",
            shot.to_str().unwrap(),
        ])
        .args(extra)
        .env("DISPLAY", &display)
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    image::open(&shot).unwrap().to_rgba8()
}

/// Pixels of the wall's blue or the box's red in the checkerboards.
fn model_pixels(img: &image::RgbaImage) -> usize {
    img.pixels().filter(|p| p[2] > 100 && p[0] < 90).count()
}

#[test]
fn window_opens_and_draws_the_model() {
    let img = screenshot(&[]);
    assert_eq!(img.dimensions(), (320, 240));
    // Not blank: many distinct colours (textured model and the overlay).
    let mut colours: Vec<[u8; 3]> = img.pixels().map(|p| [p[0], p[1], p[2]]).collect();
    colours.sort_unstable();
    colours.dedup();
    assert!(colours.len() > 50, "{} distinct colours", colours.len());
    // The model itself, not only the overlay.
    let model = model_pixels(&img);
    assert!(model > 1000, "{model} wall pixels");
}

#[test]
fn window_draws_the_model_by_view_dependent_texture_mapping() {
    // Replayed: scans arrive one by one, the surface is rebuilt in the background
    // (the EO camera fitted from the scans), and the screenshot waits for a build
    // that holds all three.
    let img = screenshot(&["--mode", "vdtm"]);
    let model = model_pixels(&img);
    assert!(model > 1000, "{model} wall pixels");
}

#[test]
fn window_draws_the_model_as_the_point_proxy() {
    // Replayed: each scan's points and acquisition depth map are built as it arrives.
    let img = screenshot(&["--mode", "points"]);
    let model = model_pixels(&img);
    assert!(model > 1000, "{model} wall pixels");
}

/// Frame pacing: once the full-quality frame is on screen and nothing changes, the
/// window submits nothing to the GPU (counted over 2 s by `--exit-when-idle`; a window
/// that kept drawing would count its frames there), and it starts quietly: one line
/// on stderr per thing worth saying, no warnings from the platform layers.
#[test]
fn an_idle_window_submits_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Texel);
    let (_xvfb, display) = start_xvfb();
    let out = Command::new(viewer_binary())
        .args([
            "open",
            capture.to_str().unwrap(),
            "--load",
            "--width",
            "320",
            "--height",
            "240",
            "--exit-when-idle",
            "2",
        ])
        .env("DISPLAY", &display)
        .env_remove("WAYLAND_DISPLAY")
        .env_remove("XDG_RUNTIME_DIR")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{}: {stderr}{stdout}", out.status);
    let line = stdout
        .lines()
        .find(|l| l.starts_with("idle "))
        .unwrap_or_else(|| panic!("no idle report in {stdout:?}"));
    assert!(
        line.contains(": 0 GPU submissions, 0 frames drawn"),
        "{line}"
    );
    assert!(!stderr.contains("XDG_RUNTIME_DIR"), "{stderr}");
}
