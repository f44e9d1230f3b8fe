//! `texeld info` on real files: a capture written by the Python tooling, a file that is
//! not MCAP, a truncated capture and one that breaks the spec.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::ffi::OsStr;
use std::process::Command;

use texel::capture::{CameraRole, CaptureWriter, RangeEncoding, WriterOptions};
use texel::{Distortion, PinholeCamera, RangeFrame};
use texel_e2e::run_python;

fn texeld(args: &[&OsStr]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn info_lists_a_python_written_capture() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("py.mcap");
    let expected = dir.path().join("py.json");
    run_python(
        "write_capture.py",
        &[capture.as_os_str(), expected.as_os_str()],
    );
    let (ok, out, err) = texeld(&[OsStr::new("info"), capture.as_os_str()]);
    assert!(ok, "{out}{err}");
    for needle in [
        "/lidar/range",
        "16x12 32FC1",
        "16x12 16UC1",
        "32x24 yuyv",
        "/eo/image/compressed",
        "frames: 7 range, 7 EO",
        "poses: 7 on /truth/pose",
        "duration: 0.700 s",
        "lidar: 16x12  fx 20.0000  fy 20.5000  cx 7.5000  cy 5.5000",
        "distortion plumb_bob [-0.12, 0.03, 0.001, -0.002, 0.0]",
        "eo_from_lidar: translation_m [0.031, -0.002, 0.0105]",
        "\"name\": \"python interop\"",
        "/vendor/debug",
    ] {
        assert!(out.contains(needle), "missing {needle:?} in\n{out}");
    }
}

#[test]
fn info_names_a_file_that_is_not_mcap() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("notes.txt");
    std::fs::write(&path, "just some text, not a capture\n").unwrap();
    let (ok, out, _) = texeld(&[OsStr::new("info"), path.as_os_str()]);
    assert!(!ok);
    assert!(out.contains("not an MCAP file"), "{out}");
    let (ok, _, err) = texeld(&[
        OsStr::new("info"),
        dir.path().join("missing.mcap").as_os_str(),
    ]);
    assert!(!ok);
    assert!(err.contains("missing.mcap"), "{err}");
}

fn small_capture(path: &std::path::Path, frames: u32, calibrated: bool) {
    let camera = PinholeCamera {
        width: 4,
        height: 3,
        fx: 5.0,
        fy: 5.0,
        cx: 1.5,
        cy: 1.0,
        skew: 0.0,
        distortion: Distortion::None,
    };
    let mut w = CaptureWriter::create(
        path,
        WriterOptions {
            chunk_size_bytes: 64,
            ..WriterOptions::default()
        },
    )
    .unwrap();
    if calibrated {
        w.write_calibration(CameraRole::Lidar, &camera, 1).unwrap();
    }
    for i in 0..frames {
        let mut f = RangeFrame::empty(4, 3, 1_000 + u64::from(i), i);
        f.ranges_m[0] = 1.0;
        w.write_range(&f, RangeEncoding::F32Metres).unwrap();
    }
    w.finish().unwrap();
}

#[test]
fn info_lists_what_a_truncated_capture_holds_then_says_where_it_ends() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cut.mcap");
    small_capture(&path, 20, true);
    let bytes = std::fs::read(&path).unwrap();
    let cut = bytes.len() * 2 / 3;
    std::fs::write(&path, &bytes[..cut]).unwrap();
    let (ok, out, _) = texeld(&[OsStr::new("info"), path.as_os_str()]);
    assert!(!ok);
    assert!(out.contains("/lidar/range"), "{out}");
    assert!(
        out.contains(&format!("truncated: the file ends at byte {cut}")),
        "{out}"
    );
}

#[test]
fn info_names_the_topic_and_log_time_of_a_spec_violation() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("uncalibrated.mcap");
    small_capture(&path, 2, false);
    let (ok, out, _) = texeld(&[OsStr::new("info"), path.as_os_str()]);
    assert!(!ok);
    assert!(out.contains("spec violations: 2"), "{out}");
    assert!(
        out.contains("topic /lidar/range at log time 1000 ns: frame before any /lidar/calibration"),
        "{out}"
    );
}
