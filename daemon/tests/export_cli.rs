//! `texeld export` read back by real readers (trimesh and Open3D): counts and bounds
//! match the fused scan, in the scan's frame and in a world 5000 km from the origin.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::ffi::OsStr;
use std::path::Path;
use std::process::Command;

use nalgebra::{Point3, Vector2};
use serde_json::Value;
use texel::capture::{CaptureWriter, EoEncoding, PoseTopic, RangeEncoding, WriterOptions};
use texel::pose::pose_from_parts;
use texel::{
    EoFrame, FuseConfig, PinholeCamera, Pose, RangeFrame, RangeNoise, Sensor, SensorModel, fuse,
};
use texel_e2e::run_python;

fn model() -> SensorModel {
    SensorModel {
        name: "export test".into(),
        lidar: PinholeCamera::from_vertical_fov(32, 24, 30.0).unwrap(),
        eo: PinholeCamera::from_vertical_fov(160, 120, 40.0).unwrap(),
        eo_from_lidar: pose_from_parts([0.02, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]).unwrap(),
        range_noise: RangeNoise {
            sigma_m: 0.005,
            sigma_per_m: 0.0,
        },
        range_bias_m: 0.0,
        min_range_m: 0.3,
        max_range_m: 30.0,
        eo_response: None,
    }
}

/// A wall 3 m away with a box 2 m away over the left third of the view.
fn frame(m: &SensorModel, t: u64) -> (RangeFrame, EoFrame) {
    let mut r = RangeFrame::empty(32, 24, t, 0);
    for v in 0..24u32 {
        for u in 0..32u32 {
            let ray = m
                .lidar
                .unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                .unwrap();
            let depth = if u < 11 { 2.0 } else { 3.0 };
            r.ranges_m[(v * 32 + u) as usize] = (depth / ray.z) as f32;
        }
    }
    let eo = EoFrame {
        width: 160,
        height: 120,
        rgb: (0..160 * 120 * 3).map(|i| (i % 200) as u8).collect(),
        timestamp_ns: t,
        exposure: None,
    };
    (r, eo)
}

fn world_pose() -> Pose {
    pose_from_parts([5.0e6, 4.2e6, 120.0], [0.1, -0.2, 0.3, 0.9]).unwrap()
}

fn write_capture(path: &Path, with_pose: bool) {
    let m = model();
    let mut w = CaptureWriter::create(path, WriterOptions::default()).unwrap();
    w.write_sensor(&m, 1).unwrap();
    for i in 0..3u64 {
        let t = 1_000 + i;
        let (r, eo) = frame(&m, t);
        w.write_range(&r, RangeEncoding::F32Metres).unwrap();
        w.write_eo(&eo, EoEncoding::Rgb8).unwrap();
        if with_pose {
            w.write_pose(PoseTopic::Truth, t, &world_pose()).unwrap();
        }
    }
    w.finish().unwrap();
}

fn texeld(args: &[&OsStr]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    )
}

fn check(file: &Path) -> Value {
    let out = run_python("check_export.py", &[file.as_os_str()]);
    serde_json::from_slice(&out.stdout).unwrap()
}

fn close(got: &Value, want: [f64; 3], tol: f64) {
    for (g, w) in got.as_array().unwrap().iter().zip(want) {
        let g = g.as_f64().unwrap();
        assert!((g - w).abs() <= tol, "{g} vs {w}");
    }
}

#[test]
fn exports_read_back_with_matching_counts_and_bounds() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("c.mcap");
    write_capture(&capture, true);
    let m = model();
    let sensor = Sensor::new(m.clone());
    let (r, eo) = frame(&m, 1_001);
    let scan = fuse(&r, eo, &sensor, &FuseConfig::default()).unwrap();
    let usable = scan.usable_triangle_count() as u64;
    assert!(
        usable > 0 && scan.stretched_count() > 0,
        "the box edge is stretched"
    );
    let (lo, hi) = scan.bounds().unwrap();
    let (lo, hi) = (lo.map(f64::from), hi.map(f64::from));
    // World bounds from the f64 pose.
    let pose = world_pose();
    let world: Vec<Point3<f64>> = scan
        .vertices
        .iter()
        .map(|v| pose * Point3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])))
        .collect();
    let wlo = [0, 1, 2].map(|k| world.iter().map(|p| p[k]).fold(f64::INFINITY, f64::min));
    let whi = [0, 1, 2].map(|k| world.iter().map(|p| p[k]).fold(f64::NEG_INFINITY, f64::max));

    for (name, format, world_flag) in [
        ("scan.ply", "ply", false),
        ("world.ply", "ply", true),
        ("scan.gltf", "gltf", false),
        ("world.glb", "gltf", true),
    ] {
        let out = dir.path().join(name);
        let mut args = vec![
            OsStr::new("export"),
            capture.as_os_str(),
            OsStr::new("--frame"),
            OsStr::new("1"),
            OsStr::new("--format"),
            OsStr::new(format),
            OsStr::new("--out"),
            out.as_os_str(),
        ];
        if world_flag {
            args.push(OsStr::new("--world"));
        }
        let (ok, text) = texeld(&args);
        assert!(ok, "{text}");
        let got = check(&out);
        let t = &got["trimesh"];
        let (want_lo, want_hi, tol) = if world_flag {
            (wlo, whi, 1e-3)
        } else {
            (lo, hi, 1e-6)
        };
        if format == "ply" {
            assert_eq!(t["vertices"], scan.vertex_count() as u64, "{name}");
            assert_eq!(t["faces"], usable, "{name}");
            assert_eq!(t["colours"], true);
            let o = &got["open3d"];
            assert_eq!(o["points"], scan.vertex_count() as u64);
            assert_eq!(o["triangles"], usable);
            close(&o["min"], want_lo, tol);
            close(&o["max"], want_hi, tol);
        } else {
            assert_eq!(t["meshes"], 1);
            assert_eq!(t["vertices"], scan.vertex_count() as u64, "{name}");
            assert_eq!(t["faces"], usable, "{name}");
            assert_eq!(t["textured"], true);
            assert_eq!(t["texture_sizes"][0], serde_json::json!([160, 120]));
        }
        close(&t["min"], want_lo, tol);
        close(&t["max"], want_hi, tol);
    }
}

#[test]
fn export_names_a_missing_frame_and_a_missing_pose() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("nopose.mcap");
    write_capture(&capture, false);
    let out = dir.path().join("x.ply");
    let base = |frame: &'static str| {
        vec![
            OsStr::new("export").to_owned(),
            capture.as_os_str().to_owned(),
            OsStr::new("--frame").to_owned(),
            OsStr::new(frame).to_owned(),
            OsStr::new("--format").to_owned(),
            OsStr::new("ply").to_owned(),
            OsStr::new("--out").to_owned(),
            out.as_os_str().to_owned(),
        ]
    };
    let args = base("7");
    let (ok, text) = texeld(&args.iter().map(|a| a.as_os_str()).collect::<Vec<_>>());
    assert!(!ok);
    assert!(
        text.contains("has 3 texel frames; frame 7 does not exist"),
        "{text}"
    );
    let mut args = base("0");
    args.push(OsStr::new("--world").to_owned());
    let (ok, text) = texeld(&args.iter().map(|a| a.as_os_str()).collect::<Vec<_>>());
    assert!(!ok);
    assert!(text.contains("no /texel/pose or /truth/pose"), "{text}");
}
