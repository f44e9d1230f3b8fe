//! `texeld register` on simulator captures: poses land in the output capture, the
//! report's errors against `/truth/pose` are small, bad configs are named.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
// The simulated sources are the `sim` feature (on by default).
#![cfg(feature = "sim")]

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;
use texel::capture::{PoseTopic, TexelItem, open_texel_frames};

fn capture(dir: &Path, scene: &str, frames: usize) -> PathBuf {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../configs/scenes/{scene}.toml"));
    capture_of(dir, &path, frames)
}

fn capture_of(dir: &Path, path: &Path, frames: usize) -> PathBuf {
    let scene = sims::Scene::load(path).unwrap();
    let options = sims::SimOptions {
        seed: 5,
        frames: Some(frames),
        lidar_size: Some([64, 64]),
        eo_size: Some([160, 120]),
        ..Default::default()
    };
    let sim = sims::Simulator::with_options(scene, &options).unwrap();
    let out = dir.join("in.mcap");
    sims::render_capture(&sim, &out, &Default::default(), &mut |_, _| {}).unwrap();
    out
}

fn texeld(args: &[&str]) -> (bool, String, String) {
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

fn poses(path: &Path, topic: PoseTopic) -> Vec<(u64, texel::Pose)> {
    open_texel_frames(path)
        .unwrap()
        .filter_map(|i| match i.unwrap() {
            TexelItem::Pose {
                topic: t,
                timestamp_ns,
                world_from_eo,
            } if t == topic => Some((timestamp_ns, world_from_eo)),
            _ => None,
        })
        .collect()
}

#[test]
fn lab_capture_is_registered_with_poses_and_a_report() {
    let dir = tempfile::tempdir().unwrap();
    let input = capture(dir.path(), "lab", 8);
    let out = dir.path().join("out.mcap");
    let report = dir.path().join("report.json");
    let (ok, stdout, stderr) = texeld(&[
        "register",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(ok, "{stdout}\n{stderr}");
    assert!(stdout.contains("registered 8 of 8 frames"), "{stdout}");
    // Every frame has a /texel/pose at its timestamp, and the truth is still there.
    let texel = poses(&out, PoseTopic::Texel);
    let truth = poses(&out, PoseTopic::Truth);
    assert_eq!(texel.len(), 8);
    assert_eq!(truth.len(), 8);
    for ((t_est, est), (t_true, tr)) in texel.iter().zip(&truth) {
        assert_eq!(t_est, t_true);
        // Anchored at the first truth pose: errors are small in the world frame too.
        let (angle, dist) = texel::pose::pose_difference(est, tr);
        assert!(
            angle.to_degrees() < 0.5 && dist < 0.02,
            "{angle} rad {dist} m"
        );
    }
    let json: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(json["frames"], 8);
    assert_eq!(json["per_frame"][0]["status"], "anchor");
    assert_eq!(json["per_frame"][1]["status"], "registered");
    let ate = json["ate_rmse_mm"].as_f64().unwrap();
    assert!(ate < 20.0, "ATE {ate} mm");
    for f in json["per_frame"].as_array().unwrap() {
        assert!(f["translation_error_mm"].as_f64().unwrap() < 20.0, "{f}");
        assert!(f["time_ms"].as_f64().unwrap() >= 0.0);
    }
    // Registering the output again replaces its /texel/pose rather than adding more.
    let again = dir.path().join("again.mcap");
    let (ok, _, stderr) = texeld(&[
        "register",
        out.to_str().unwrap(),
        "--out",
        again.to_str().unwrap(),
    ]);
    assert!(ok, "{stderr}");
    assert_eq!(poses(&again, PoseTopic::Texel).len(), 8);
}

#[test]
fn plane_capture_is_pinned_by_the_eo_by_default_and_named_degenerate_without_it() {
    let dir = tempfile::tempdir().unwrap();
    let input = capture(dir.path(), "plane", 4);
    let register = |name: &str, config: Option<&str>| {
        let out = dir.path().join(format!("{name}.mcap"));
        let report = dir.path().join(format!("{name}.json"));
        let mut args = vec![
            "register".to_string(),
            input.to_str().unwrap().to_string(),
            "--out".into(),
            out.to_str().unwrap().to_string(),
            "--report".into(),
            report.to_str().unwrap().to_string(),
        ];
        if let Some(text) = config {
            let path = dir.path().join(format!("{name}.toml"));
            std::fs::write(&path, text).unwrap();
            args.extend(["--config".into(), path.to_str().unwrap().to_string()]);
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let (ok, stdout, stderr) = texeld(&args);
        assert!(ok, "{stdout}\n{stderr}");
        let json: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        json
    };
    // Defaults: the floor's texture fixes the three directions its plane leaves
    // free; the poses follow the truth.
    let json = register("eo", None);
    for f in &json["per_frame"].as_array().unwrap()[1..] {
        assert_eq!(f["status"], "registered", "{f}");
        assert_eq!(f["degenerate"].as_array().map_or(0, Vec::len), 0, "{f}");
        assert!(f["photometric"]["residuals"].as_u64().unwrap() > 0, "{f}");
        assert!(f["translation_error_mm"].as_f64().unwrap() < 5.0, "{f}");
    }
    // Geometry alone: the three directions are named.
    let json = register("geometry", Some("[align.photometric]\nmode = \"off\"\n"));
    for f in &json["per_frame"].as_array().unwrap()[1..] {
        let n = f["degenerate"].as_array().map_or(0, Vec::len);
        assert!(f["status"] == "failed" || n == 3, "{f}");
        assert_eq!(f["photometric"]["residuals"], 0, "{f}");
    }
}

#[test]
fn bad_configs_and_inputs_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("reg.toml");
    std::fs::write(&config, "[align]\npyramid_levles = 2\n").unwrap();
    let out = dir.path().join("out.mcap");
    let (ok, _, stderr) = texeld(&[
        "register",
        "missing.mcap",
        "--out",
        out.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
    ]);
    assert!(!ok);
    assert!(
        stderr.contains("pyramid_levles") && stderr.contains("reg.toml"),
        "{stderr}"
    );
    // A bad configuration exits 2, as for every command.
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(["register", "missing.mcap", "--out"])
        .arg(&out)
        .arg("--config")
        .arg(&config)
        .output()
        .unwrap()
        .status;
    assert_eq!(status.code(), Some(2));
    std::fs::write(&config, "[align]\npyramid_levels = 2\n").unwrap();
    let (ok, _, stderr) = texeld(&[
        "register",
        "missing.mcap",
        "--out",
        out.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
    ]);
    assert!(!ok);
    assert!(stderr.contains("missing.mcap"), "{stderr}");
}

#[test]
fn every_shipped_scene_registers() {
    // Whatever a scene holds (effects, trajectory, degenerate geometry), `texeld
    // register` finishes, anchors the first frame and places every registered frame
    // near the truth; frames it cannot place are reported, not given a wrong pose.
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/scenes");
    let mut names: Vec<PathBuf> = std::fs::read_dir(&scenes)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    names.sort();
    assert!(names.len() >= 6, "{names:?}");
    for scene in &names {
        let dir = tempfile::tempdir().unwrap();
        let input = capture_of(dir.path(), scene, 3);
        let out = dir.path().join("out.mcap");
        let report = dir.path().join("report.json");
        let (ok, stdout, stderr) = texeld(&[
            "register",
            input.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ]);
        let name = scene.display();
        assert!(ok, "{name}: {stdout}\n{stderr}");
        let json: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        assert_eq!(json["frames"], 3, "{name}");
        let frames = json["per_frame"].as_array().unwrap();
        assert_eq!(frames[0]["status"], "anchor", "{name}");
        let placed = frames
            .iter()
            .filter(|f| f["status"] == "anchor" || f["status"] == "registered")
            .count();
        assert_eq!(poses(&out, PoseTopic::Texel).len(), placed, "{name}");
        for f in frames.iter().filter(|f| f["status"] == "registered") {
            let err = f["translation_error_mm"].as_f64().unwrap();
            let rot = f["rotation_error_deg"].as_f64().unwrap();
            assert!(err.is_finite() && rot.is_finite(), "{name}: {f}");
            // Where every direction is observable the pose is near the truth; along
            // an unobservable one the estimate keeps the prior (here the standing
            // start), so the error is the motion along it and the result names it.
            let degenerate = f["degenerate"].as_array().unwrap();
            if degenerate.is_empty() {
                assert!(err < 50.0 && rot < 1.0, "{name}: {f}");
            }
        }
    }
}
