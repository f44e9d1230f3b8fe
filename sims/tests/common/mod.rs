//! Helpers shared by the simulator's integration tests.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;

use sims::{Effect, Scene, SimOptions, Simulator};

pub fn configs() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs")
}

/// A scene from text whose relative paths resolve from `configs/scenes`.
pub fn scene(text: &str) -> Scene {
    Scene::from_toml_str(text, "test.toml", &configs().join("scenes")).unwrap()
}

pub fn load(name: &str) -> Scene {
    Scene::load(&configs().join("scenes").join(format!("{name}.toml"))).unwrap()
}

pub fn effects(names: &[&str]) -> Vec<Effect> {
    names
        .iter()
        .map(|n| Effect::with_defaults(n).unwrap())
        .collect()
}

/// A small simulator: lidar 32x32, EO 80x60.
pub fn small(scene: Scene, seed: u64, effect_names: Option<&[&str]>) -> Simulator {
    Simulator::with_options(
        scene,
        &SimOptions {
            seed,
            effects: effect_names.map(effects),
            lidar_size: Some([32, 32]),
            eo_size: Some([80, 60]),
            ..SimOptions::default()
        },
    )
    .unwrap()
}

/// A scene header with the default sensor, a fixed camera at the origin looking
/// along +y, and the given body (materials, objects...).
pub fn fixed_camera_scene(body: &str) -> String {
    format!(
        r#"
sensor = "../sensors/texel-default.toml"
[trajectory]
rate_hz = 10.0
poses = [ {{ position = [0.0, 0.0, 1.0], look_at = [0.3, 5.0, 1.2] }},
          {{ position = [0.1, 0.2, 1.1], look_at = [-0.2, 5.0, 0.9] }} ]
[materials.grey]
color = [0.5, 0.5, 0.5]
[materials.checks]
checker = {{ square_m = 0.1, colors = [[0.9, 0.9, 0.9], [0.1, 0.1, 0.1]] }}
{body}
"#
    )
}
