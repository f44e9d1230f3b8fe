//! Helpers shared by the calibration tests: scenes, simulators and the board's true
//! corners (from the calib-target scene file, never given to the calibration).
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

use nalgebra::{Point3, Vector2};
use sims::{Effect, Scene, Simulator};
use texel::{PinholeCamera, Pose};

pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

pub fn target_scene() -> Scene {
    Scene::load(&root().join("configs/scenes/calib-target.toml")).unwrap()
}

/// The calib-target scene with extra TOML appended (an occluder, say).
pub fn target_scene_with(extra: &str) -> Scene {
    let path = root().join("configs/scenes/calib-target.toml");
    let text = std::fs::read_to_string(&path).unwrap() + extra;
    Scene::from_toml_str(&text, "calib-target (test)", &root().join("configs/scenes")).unwrap()
}

pub fn sim(scene: Scene, seed: u64, effects: Option<Vec<Effect>>) -> Simulator {
    texel_bench::calibration::simulate::simulator(scene, seed, effects).unwrap()
}

/// The realistic effect list with the lens distortion scaled by `scale`.
pub fn effects_with_distortion(scale: f64) -> Vec<Effect> {
    let mut v: Vec<Effect> = [
        "mixed_pixels",
        "dropouts",
        "range_noise",
        "range_quantisation",
        "vignetting",
        "sensor_noise",
    ]
    .iter()
    .map(|n| Effect::with_defaults(n).unwrap())
    .collect();
    v.push(Effect::LensDistortion(sims::effects::LensDistortion {
        scale,
    }));
    v
}

/// World positions of the 9 x 6 inner corners of the scene's board, row-major over
/// (a along world x, b along world z).
pub fn true_corners() -> Vec<Point3<f64>> {
    let mut out = Vec::new();
    for b in 0..6 {
        for a in 0..9 {
            out.push(Point3::new(
                -0.2 + 0.05 * f64::from(a),
                0.0,
                1.2 - 0.125 + 0.05 * f64::from(b),
            ));
        }
    }
    out
}

/// Pixels of the true corners in a camera at `world_from_camera` (None when off-image).
pub fn true_pixels(camera: &PinholeCamera, world_from_camera: &Pose) -> Vec<Option<Vector2<f64>>> {
    let inv = world_from_camera.inverse();
    true_corners()
        .iter()
        .map(|p| camera.project(&(inv * p).coords).ok())
        .collect()
}

/// For each detected corner `(i, j, pixel)`: the index of the nearest true corner and
/// the distance to it.
pub fn match_corners(
    detected: &calib::detect::BoardCorners,
    truth: &[Option<Vector2<f64>>],
) -> Vec<((usize, usize), usize, f64)> {
    detected
        .iter()
        .map(|(i, j, p)| {
            let (k, d) = truth
                .iter()
                .enumerate()
                .filter_map(|(k, t)| t.map(|t| (k, (t - p).norm())))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            ((i, j), k, d)
        })
        .collect()
}
