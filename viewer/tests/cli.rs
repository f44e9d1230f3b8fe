//! `texel-viewer render` end to end: a real capture file in, PNGs out; deterministic;
//! bad input named.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use std::process::Command;

use support::*;
use texel::capture::PoseTopic;
use texel::pose::pose_to_parts;
use texel_viewer::scenes;

fn render(args: &[&str]) -> std::process::Output {
    Command::new(viewer_binary())
        .arg("render")
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn renders_a_capture_deterministically_and_as_the_library_does() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Truth);
    let cam = box_camera(&texel::Pose::identity());
    let (t, q) = pose_to_parts(&cam.world_from_eo);
    let pose = format!(
        "{} {} {} {} {} {} {}",
        t[0], t[1], t[2], q[0], q[1], q[2], q[3]
    );
    let out = |name: &str| dir.path().join(name).display().to_string();
    let base = [
        "--capture",
        capture.to_str().unwrap(),
        "--pose",
        &pose,
        "--fov-deg",
        "55",
        "--width",
        "160",
        "--height",
        "120",
        "--mode",
        "blended",
    ];
    let a = render(&[&base[..], &["--out", &out("a.png")]].concat());
    assert!(a.status.success(), "{}", String::from_utf8_lossy(&a.stderr));
    let stderr = String::from_utf8_lossy(&a.stderr);
    assert!(stderr.contains("3 scans placed by /truth/pose"), "{stderr}");
    let b = render(&[&base[..], &["--out", &out("b.png")]].concat());
    assert!(b.status.success());
    let (pa, pb) = (
        std::fs::read(out("a.png")).unwrap(),
        std::fs::read(out("b.png")).unwrap(),
    );
    assert_eq!(pa, pb, "rendering is deterministic");
    // Same image as the library's renderer on the same scans (the capture round trip
    // keeps f32 ranges and RGB8 exactly).
    let mut r = box_renderer(&texel::Pose::identity());
    let (lib, _) = r
        .render_to_image(
            &cam,
            &texel_viewer::gpu::RenderSettings::with_mode(texel_viewer::composite::Mode::Blended),
        )
        .unwrap();
    let cli = image::open(out("a.png")).unwrap().to_rgba8();
    assert!(fraction_within(&lib, &cli, 2) >= 0.99);
    // Views file and acquisition views.
    let views = dir.path().join("views.txt");
    std::fs::write(
        &views,
        format!(
            "# two views\n{} {pose}\n{} 0 0 0 0 0 0 1 60\n",
            out("v1.png"),
            out("v2.png")
        ),
    )
    .unwrap();
    let v = render(&[
        "--capture",
        capture.to_str().unwrap(),
        "--views",
        views.to_str().unwrap(),
        "--width",
        "64",
        "--height",
        "48",
        "--mode",
        "scan-colour",
    ]);
    assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stderr));
    assert_eq!(image::open(out("v2.png")).unwrap().width(), 64);
    let acq = render(&[
        "--capture",
        capture.to_str().unwrap(),
        "--acquisition",
        "1",
        "--width",
        "64",
        "--height",
        "48",
        "--mode",
        "painter",
        "--out",
        &out("acq.png"),
    ]);
    assert!(
        acq.status.success(),
        "{}",
        String::from_utf8_lossy(&acq.stderr)
    );
}

#[test]
fn registered_poses_win_over_truth() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("reg.mcap");
    write_box_capture(&capture, PoseTopic::Texel);
    let out = dir.path().join("x.png");
    let o = render(&[
        "--capture",
        capture.to_str().unwrap(),
        "--acquisition",
        "0",
        "--width",
        "32",
        "--height",
        "24",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("placed by /texel/pose"));
}

#[test]
fn bad_input_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.mcap");
    let o = render(&[
        "--capture",
        missing.to_str().unwrap(),
        "--acquisition",
        "0",
        "--width",
        "32",
        "--height",
        "24",
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing.mcap"));
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Truth);
    let cases: [(&[&str], &str); 4] = [
        (
            &["--pose", "1 2 3", "--width", "32", "--height", "24"],
            "x y z qx qy qz qw",
        ),
        (
            &["--acquisition", "7", "--width", "32", "--height", "24"],
            "--acquisition 7",
        ),
        (
            &["--acquisition", "0", "--width", "0", "--height", "24"],
            "image size",
        ),
        (
            &[
                "--acquisition",
                "0",
                "--width",
                "32",
                "--height",
                "24",
                "--mode",
                "fancy",
            ],
            "unknown mode",
        ),
    ];
    for (args, want) in cases {
        let o = render(&[&["--capture", capture.to_str().unwrap()][..], args].concat());
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && stderr.contains(want),
            "{args:?}: {stderr}"
        );
    }
    // A truncated capture still renders what came before the cut.
    let bytes = std::fs::read(&capture).unwrap();
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let o = render(&[
        "--capture",
        cut.to_str().unwrap(),
        "--acquisition",
        "0",
        "--width",
        "32",
        "--height",
        "24",
        "--out",
        dir.path().join("cut.png").to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("cut.mcap"), "{stderr}");
    let _ = scenes::tint(0);
}

/// `render --lod`: the capture's scans fused into a level-of-detail hierarchy and
/// drawn from the tiles the view selects.
#[test]
fn renders_a_capture_as_level_of_detail_tiles() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Truth);
    let cam = box_camera(&texel::Pose::identity());
    let (t, q) = pose_to_parts(&cam.world_from_eo);
    let pose = format!(
        "{} {} {} {} {} {} {}",
        t[0], t[1], t[2], q[0], q[1], q[2], q[3]
    );
    let out = dir.path().join("lod.png");
    let o = render(&[
        "--capture",
        capture.to_str().unwrap(),
        "--pose",
        &pose,
        "--fov-deg",
        "55",
        "--width",
        "160",
        "--height",
        "120",
        "--lod",
        "--out",
        out.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(stderr.contains("hierarchy: "), "{stderr}");
    assert!(stderr.contains("tiles drawn"), "{stderr}");
    let img = image::open(&out).unwrap().to_rgba8();
    let drawn = img
        .pixels()
        .filter(|p| p[0] != 0 || p[1] != 0 || p[2] != 0)
        .count();
    println!("{stderr}{drawn} pixels drawn");
    // The box's fused surface (three scans at 0.1 m voxels) covers about a fifth of
    // the view.
    assert!(drawn > 160 * 120 / 10, "{drawn} pixels drawn");
}
