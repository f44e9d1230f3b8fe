//! The window under a real X server (Xvfb on a free display): it opens on a capture,
//! draws frames through the swapchain, and the read-back frame is not blank.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use support::*;
use texel::capture::PoseTopic;

struct Xvfb(Child);

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts Xvfb on the first display number whose lock file is free.
fn start_xvfb() -> (Xvfb, String) {
    for n in 90..140 {
        if std::path::Path::new(&format!("/tmp/.X{n}-lock")).exists() {
            continue;
        }
        let display = format!(":{n}");
        let child = Command::new("Xvfb")
            .args([&display, "-screen", "0", "800x600x24", "-nolisten", "tcp"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("Xvfb must be installed (scripts/setup.sh installs xvfb)");
        let xvfb = Xvfb(child);
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(10) {
            if std::path::Path::new(&format!("/tmp/.X11-unix/X{n}")).exists() {
                return (xvfb, display);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    panic!("no free X display for Xvfb");
}

#[test]
fn window_opens_and_draws_the_model() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Truth);
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
