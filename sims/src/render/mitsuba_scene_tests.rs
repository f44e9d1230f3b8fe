//! The export's texture mapping checked against our own renderer's.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::HashMap;
use std::path::Path;

use texel::PinholeCamera;

use crate::render::mitsuba::MitsubaRenderer;
use crate::render::{CameraRays, world_ray};
use crate::scene::Scene;

/// Texture coordinates are carried over exactly: at every pixel, Mitsuba's
/// albedo (point-sampled) equals our texture point-sampled at our own hit, on every
/// kind of shape; baked textures (noise, disk caps) within a stated error.
#[test]
fn textures_land_on_the_same_surface_points() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/scenes/backend-check.toml");
    let scene = Scene::load(&path).unwrap();
    let renderer = MitsubaRenderer::start(&scene.world).unwrap();
    let camera = PinholeCamera::from_vertical_fov(200, 150, 50.0).unwrap();
    let rays = CameraRays::new(&camera);
    // Per surface: pixels, pixels off by more than 1e-3, sum and max of |diff|.
    let mut stats: HashMap<String, (usize, usize, f64, f32)> = HashMap::new();
    let mut only_one = 0;
    for i in 0..3 {
        let pose = scene.trajectory.frame_pose(i);
        let hits = renderer.trace(&pose, &rays.rays).unwrap();
        for (r, m) in rays.rays.iter().zip(&hits) {
            let ours = world_ray(&pose, r).and_then(|ray| scene.world.trace(&ray));
            let (Some(ours), Some(m)) = (ours, m) else {
                // Only where the textured ground's rectangle ends, far beyond
                // any lidar range.
                if let Some(h) = ours.or(None) {
                    assert!(m.is_some() || h.distance_m > 500.0, "{h:?}");
                }
                only_one += usize::from(ours.is_some() != m.is_some());
                continue;
            };
            if ours.object != m.object {
                continue; // a silhouette
            }
            let material = &scene.world.materials[ours.material as usize];
            let want = material.albedo(ours.uv_m, 0.0);
            let d = (0..3)
                .map(|k| (want[k] - m.albedo[k]).abs())
                .fold(0.0, f32::max);
            let mut name = scene.objects[ours.object as usize].name.clone();
            if name == "drum" && ours.normal.z.abs() > 0.99 {
                name.push_str(" caps");
            }
            let s = stats.entry(name).or_default();
            s.0 += 1;
            s.1 += usize::from(d > 1e-3);
            s.2 += f64::from(d);
            s.3 = s.3.max(d);
        }
    }
    assert!(only_one < 3 * 200, "{only_one}");
    for (name, s) in &stats {
        let mean = s.2 / s.0.max(1) as f64;
        eprintln!(
            "{name}: {} px, {} off by > 1e-3, mean {mean:.5}, max {:.4}",
            s.0, s.1, s.3
        );
        assert!(s.0 > 100, "{name} is seen");
        match name.as_str() {
            // Baked textures: noise and the caps' polar bitmap.
            "slab" => assert!(mean < 0.005 && s.3 < 0.05, "{name}"),
            "drum caps" => assert!(mean < 0.03, "{name}"),
            // Exact: only rays within f32 rounding of a checker edge may differ.
            _ => assert!(s.1 * 1000 <= s.0, "{name}"),
        }
    }
    assert!(stats.len() >= 9, "{:?}", stats.keys());
}

/// A brick wall is baked per shape (as noise is): Mitsuba's albedo matches our
/// texture point-sampled at our hit, but near the joints, where the bake's bilinear
/// lookup blends brick and mortar.
#[test]
fn baked_bricks_match_ours_away_from_the_joints() {
    let text = r#"
sensor = "../sensors/texel-default.toml"
[trajectory]
poses = [{ position = [0.0, -1.5, 1.0], look_at = [0.0, 0.0, 1.0] }]
[materials.bricks]
bricks = { brick_m = [0.225, 0.075], mortar_m = 0.01, palette = [[0.5, 0.2, 0.1], [0.6, 0.3, 0.2], [0.4, 0.15, 0.1]], mortar_color = [0.8, 0.8, 0.75], seed = 4 }
[[objects.plane]]
name = "wall"
material = "bricks"
position = [0.0, 0.0, 1.0]
rotation_deg = [90.0, 0.0, 0.0]
size = [2.0, 1.5]
"#;
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/scenes");
    let scene = Scene::from_toml_str(text, "bricks.toml", &base).unwrap();
    let renderer = MitsubaRenderer::start(&scene.world).unwrap();
    let camera = PinholeCamera::from_vertical_fov(160, 120, 40.0).unwrap();
    let rays = CameraRays::new(&camera);
    let pose = scene.trajectory.frame_pose(0);
    let hits = renderer.trace(&pose, &rays.rays).unwrap();
    let (mut seen, mut off, mut sum) = (0usize, 0usize, 0.0f64);
    for (r, m) in rays.rays.iter().zip(&hits) {
        let ours = world_ray(&pose, r).and_then(|ray| scene.world.trace(&ray));
        let (Some(ours), Some(m)) = (ours, m) else {
            continue;
        };
        let want = scene.world.materials[ours.material as usize].albedo(ours.uv_m, 0.0);
        let d = (0..3)
            .map(|k| (want[k] - m.albedo[k]).abs())
            .fold(0.0, f32::max);
        seen += 1;
        off += usize::from(d > 0.01);
        sum += f64::from(d);
    }
    let mean = sum / seen.max(1) as f64;
    eprintln!("bricks: {seen} px, {off} off by > 0.01, mean {mean:.4}");
    assert!(seen > 5000, "{seen}");
    assert!(
        off * 10 < seen && mean < 0.02,
        "{off} of {seen}, mean {mean}"
    );
}
