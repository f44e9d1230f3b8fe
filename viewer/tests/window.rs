//! The window under a real X server (Xvfb on a free display): it opens on a capture
//! replayed in-process (no daemon), draws frames through the
//! swapchain, and the read-back frame is not blank.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use std::process::Command;

use support::*;
use texel::capture::PoseTopic;

#[test]
fn window_opens_and_draws_the_model() {
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
        .env("DISPLAY", &display)
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let img = image::open(&shot).unwrap().to_rgba8();
    assert_eq!(img.dimensions(), (320, 240));
    // Not blank: many distinct colours (textured model and the overlay).
    let mut colours: Vec<[u8; 3]> = img.pixels().map(|p| [p[0], p[1], p[2]]).collect();
    colours.sort_unstable();
    colours.dedup();
    assert!(colours.len() > 50, "{} distinct colours", colours.len());
    // The model itself, not only the overlay: the checkerboard's red of the box or
    // blue of the wall appears.
    let model_pixels = img.pixels().filter(|p| p[2] > 100 && p[0] < 90).count();
    assert!(model_pixels > 1000, "{model_pixels} wall pixels");
}

#[test]
fn window_draws_the_model_by_view_dependent_texture_mapping() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Texel);
    let shot = dir.path().join("shot.png");
    let (_xvfb, display) = start_xvfb();
    // Replayed: scans arrive one by one, the surface is rebuilt in the background
    // (the EO camera fitted from the scans), and the screenshot waits for a build
    // that holds all three.
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
            "--mode",
            "vdtm",
            "--screenshot",
            shot.to_str().unwrap(),
        ])
        .env("DISPLAY", &display)
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let img = image::open(&shot).unwrap().to_rgba8();
    let model_pixels = img.pixels().filter(|p| p[2] > 100 && p[0] < 90).count();
    assert!(model_pixels > 1000, "{model_pixels} wall pixels");
}
