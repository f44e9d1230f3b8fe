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

/// A pose as `--pose` takes it.
fn pose_arg(world_from_eo: &texel::Pose) -> String {
    let (t, q) = pose_to_parts(world_from_eo);
    format!(
        "{} {} {} {} {} {} {}",
        t[0], t[1], t[2], q[0], q[1], q[2], q[3]
    )
}

#[test]
fn renders_a_capture_deterministically_and_as_the_library_does() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Truth);
    let cam = box_camera(&texel::Pose::identity());
    let pose = pose_arg(&cam.world_from_eo);
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
fn the_point_proxy_renders_and_hdr_asks_for_what_it_needs() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Truth);
    let pose = pose_arg(&box_camera(&texel::Pose::identity()).world_from_eo);
    let out = dir.path().join("points.png");
    let base = [
        "--capture",
        capture.to_str().unwrap(),
        "--pose",
        &pose,
        "--width",
        "80",
        "--height",
        "60",
        "--out",
        out.to_str().unwrap(),
    ];
    let points = render(&[&base[..], &["--mode", "points"]].concat());
    assert!(
        points.status.success(),
        "{}",
        String::from_utf8_lossy(&points.stderr)
    );
    let image = image::open(&out).unwrap().to_rgb8();
    // The box scene fills the view: the proxy coloured most of it.
    let coloured = image.pixels().filter(|p| p.0 != [0, 0, 0]).count();
    assert!(coloured * 10 > 9 * 80 * 60, "{coloured}");
    // HDR is the point proxy's, and needs frames that record their exposure.
    let meshes = render(&[&base[..], &["--mode", "blended", "--hdr"]].concat());
    let stderr = String::from_utf8_lossy(&meshes.stderr);
    assert!(
        !meshes.status.success() && stderr.contains("--mode points"),
        "{stderr}"
    );
    let unexposed = render(&[&base[..], &["--mode", "points", "--hdr"]].concat());
    let stderr = String::from_utf8_lossy(&unexposed.stderr);
    assert!(
        !unexposed.status.success() && stderr.contains("records its exposure"),
        "{stderr}"
    );
    let bad = render(&[&base[..], &["--mode", "points", "--hdr", "--gamma", "0"]].concat());
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(
        !bad.status.success() && stderr.contains("gamma"),
        "{stderr}"
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
/// drawn from the tiles the view selects, with the scans below the finest tiles the
/// view finds too coarse; `--lod-tiles-only` without them. Close to the box the
/// scans show: the frame is nearer the scans' own render than the tiles alone are.
#[test]
fn renders_a_capture_as_level_of_detail_tiles() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Truth);
    let cam = box_camera(&texel::Pose::identity());
    let pose = pose_arg(&cam.world_from_eo);
    let run = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec![
            "--capture",
            capture.to_str().unwrap(),
            "--pose",
            &pose,
            "--fov-deg",
            "55",
            // Large enough that the finest tiles (0.1 m voxels) are too coarse for
            // the view: their projected error exceeds 2 pixels.
            "--width",
            "640",
            "--height",
            "480",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let o = render(&args);
        let stderr = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(o.status.success(), "{stderr}");
        println!("{name}: {stderr}");
        (image::open(&out).unwrap().to_rgba8(), stderr)
    };
    let (hybrid, stderr) = run("lod.png", &["--lod"]);
    assert!(stderr.contains("hierarchy: "), "{stderr}");
    assert!(stderr.contains("tiles drawn"), "{stderr}");
    assert!(
        !stderr.contains(" 0 finest tiles show their scans"),
        "{stderr}"
    );
    assert!(!stderr.contains(" 0 scans drawn"), "{stderr}");
    let (tiles, stderr) = run("tiles.png", &["--lod", "--lod-tiles-only"]);
    assert!(stderr.contains(" 0 scans drawn"), "{stderr}");
    let (scans, _) = run("scans.png", &[]);
    let drawn = |p: &image::Rgba<u8>| p[0] != 0 || p[1] != 0 || p[2] != 0;
    let count = tiles.pixels().filter(|p| drawn(p)).count();
    // The box's fused surface (three scans at 0.1 m voxels) covers about a fifth of
    // the view.
    assert!(count > 640 * 480 / 10, "{count} pixels drawn");
    // Where the scans drew, the frame with the scans below the tiles matches them far
    // more often than the tiles alone do.
    let agree = |img: &image::RgbaImage| {
        let (mut n, mut ok) = (0usize, 0usize);
        for (p, q) in scans.pixels().zip(img.pixels()) {
            if drawn(p) {
                n += 1;
                ok += usize::from((0..3).all(|k| p[k].abs_diff(q[k]) <= 3));
            }
        }
        ok as f64 / n.max(1) as f64
    };
    let (with_scans, alone) = (agree(&hybrid), agree(&tiles));
    println!(
        "agreement with the scans' render: {with_scans:.3} with scans below, {alone:.3} alone"
    );
    assert!(with_scans > 0.9, "{with_scans}");
    assert!(with_scans > alone + 0.2, "{with_scans} against {alone}");
}

#[test]
fn renders_a_capture_by_view_dependent_texture_mapping() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    write_box_capture(&capture, PoseTopic::Truth);
    let cam = box_camera(&texel::Pose::identity());
    let pose = pose_arg(&cam.world_from_eo);
    let run = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec![
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
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let o = render(&args);
        let stderr = String::from_utf8_lossy(&o.stderr).to_string();
        println!("{name}: {stderr}");
        (
            o.status.success(),
            image::open(&out).ok().map(|i| i.to_rgba8()),
            stderr,
        )
    };
    let (ok, vdtm, stderr) = run("vdtm.png", &["--mode", "vdtm"]);
    assert!(ok, "{stderr}");
    assert!(stderr.contains("VDTM: 3 scans, 3 views"), "{stderr}");
    let (ok, blended, _) = run("blended.png", &["--mode", "blended"]);
    assert!(ok);
    let (vdtm, blended) = (vdtm.unwrap(), blended.unwrap());
    // Both draw the same scene: where the scans drew, the merged surface's colours
    // mostly agree (three views of a checkerboard, each with its own exposure tint).
    let drawn = |p: &image::Rgba<u8>| p[0] != 0 || p[1] != 0 || p[2] != 0;
    let (mut n, mut close) = (0usize, 0usize);
    for (a, b) in blended.pixels().zip(vdtm.pixels()) {
        if drawn(a) {
            n += 1;
            close += usize::from((0..3).all(|k| a[k].abs_diff(b[k]) <= 40));
        }
    }
    let share = close as f64 / n.max(1) as f64;
    println!(
        "vdtm agrees with blended on {:.1} % of {n} pixels",
        100.0 * share
    );
    assert!(n > 160 * 120 / 2 && share > 0.8, "{share} of {n}");
    // The switches beyond the paper run too; a bad one is named.
    let (ok, _, stderr) = run(
        "improved.png",
        &[
            "--mode",
            "vdtm",
            "--vdtm-resolution-term",
            "--vdtm-feather-px",
            "24",
        ],
    );
    assert!(ok, "{stderr}");
    let (ok, _, stderr) = run("bad.png", &["--mode", "vdtm", "--vdtm-feather-px=-1"]);
    assert!(!ok && stderr.contains("--vdtm-feather-px"), "{stderr}");
    let (ok, _, stderr) = run("bad.png", &["--mode", "vdtmx"]);
    assert!(!ok && stderr.contains("vdtm"), "{stderr}");
}
