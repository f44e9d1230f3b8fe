//! The `points` mode on the GPU: its per-view depth map against the CPU reference
//! (`texel_viewer::points::splat`) on the same points, and its image against the
//! analytic scene's true colours from a viewpoint no scan was taken from.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use texel::Pose;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::gpu::{RenderSettings, Renderer, read_depth_texture};
use texel_viewer::points::cloud::{lidar_pitch_rad, scan_points};
use texel_viewer::points::splat::{SplatCamera, SplatPoint, depth_map};
use texel_viewer::scenes;

const BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];

fn settings() -> RenderSettings {
    let mut s = RenderSettings {
        points: true,
        ..Default::default()
    };
    s.composite.background = BACKGROUND;
    s
}

fn box_model(offset: &Pose) -> texel::model::Model {
    scenes::model_of(
        &scenes::box_scene(),
        &scenes::test_sensor(),
        &scenes::box_scene_poses(),
        offset,
    )
}

fn camera(offset: &Pose) -> VirtualCamera {
    VirtualCamera::new(
        offset * scenes::look_at([0.9, -0.6, 0.2], [0.0, 0.0, 5.0]),
        52.0,
        160,
        120,
    )
    .unwrap()
}

fn render(model: &texel::model::Model, camera: &VirtualCamera) -> (Renderer, image::RgbaImage) {
    let mut renderer = Renderer::new(support::gpu());
    renderer.sync_model(model).unwrap();
    let mesh_bytes = renderer.scans_bytes();
    assert_eq!(renderer.prepare_points(model, None), model.len());
    // The proxy counts towards the scans' GPU bytes, which the residency budget holds.
    assert!(renderer.points_bytes() > 0);
    assert_eq!(renderer.scans_bytes(), mesh_bytes + renderer.points_bytes());
    // Built once: a second call finds nothing new.
    assert_eq!(renderer.prepare_points(model, None), 0);
    let (image, _) = renderer.render_to_image(camera, &settings()).unwrap();
    (renderer, image)
}

#[test]
fn the_gpu_depth_map_matches_the_cpu_reference() {
    let model = box_model(&Pose::identity());
    let cam = camera(&Pose::identity());
    let (renderer, _) = render(&model, &cam);
    let gpu = support::gpu();
    let got = read_depth_texture(
        &gpu.device,
        &gpu.queue,
        renderer.points_depth_map().unwrap(),
    )
    .unwrap();
    // The same points in the view's frame through the same pinhole, on the CPU.
    let view_from_world = cam.view_from_world();
    let mut points = Vec::new();
    for s in model.scans() {
        let scan = s.scan.as_ref().unwrap();
        let view_from_scan = view_from_world * s.world_from_scan;
        for p in scan_points(scan, lidar_pitch_rad(scan)) {
            let q = view_from_scan
                * nalgebra::Point3::new(
                    f64::from(p.position[0]),
                    f64::from(p.position[1]),
                    f64::from(p.position[2]),
                );
            let n = view_from_scan.rotation
                * nalgebra::Vector3::new(
                    f64::from(p.normal[0]),
                    f64::from(p.normal[1]),
                    f64::from(p.normal[2]),
                );
            points.push(SplatPoint {
                position: [q.x as f32, q.y as f32, q.z as f32],
                normal: [n.x as f32, n.y as f32, n.z as f32],
                radius_m: p.radius_m,
            });
        }
    }
    let f = cam.focal_px() as f32;
    let splat_camera = SplatCamera {
        width: cam.width,
        height: cam.height,
        fx: f,
        fy: f,
        cx: cam.width as f32 * 0.5 - 0.5,
        cy: cam.height as f32 * 0.5 - 0.5,
    };
    let (want, front, back) = depth_map(&points, &splat_camera);
    assert!(front > 0 && back > 0, "{front} front, {back} back");
    let (mut both, mut close, mut only_one) = (0usize, 0usize, 0usize);
    for (g, w) in got.iter().zip(&want) {
        assert!(g.is_finite() && *g >= 0.0, "{g}");
        match (*g > 0.0, w) {
            (true, Some(w)) => {
                both += 1;
                close += usize::from((g - w).abs() <= 0.01 * w);
            }
            (false, None) => {}
            _ => only_one += 1,
        }
    }
    let pixels = got.len();
    println!(
        "depth map: {both} pixels in both, {close} within 1 %, {only_one} in one only of {pixels}"
    );
    // Splat edges fall on pixel centres in both; rasterisation rounds them differently
    // at a few.
    assert!(both > pixels / 2, "{both} of {pixels}");
    assert!(close as f64 > 0.98 * both as f64, "{close} of {both}");
    assert!(
        (only_one as f64) < 0.02 * pixels as f64,
        "{only_one} of {pixels}"
    );
}

#[test]
fn points_render_the_scene_from_a_new_viewpoint_near_and_far_from_the_origin() {
    let tints: Vec<[f32; 3]> = (0..3).map(scenes::tint).collect();
    let mean_tint = [0, 1, 2].map(|k| tints.iter().map(|t| t[k]).sum::<f32>() / 3.0);
    let model = box_model(&Pose::identity());
    let cam = camera(&Pose::identity());
    let (_, image) = render(&model, &cam);
    let (error, covered) = support::box_scene_error(&image, &cam, mean_tint);
    // The meshes composited (Killpack & Budge) from the same scans, the same metric.
    let mut meshes = Renderer::new(support::gpu());
    meshes.sync_model(&model).unwrap();
    let mut blended = settings();
    blended.points = false;
    let (mesh_image, _) = meshes.render_to_image(&cam, &blended).unwrap();
    let (mesh_error, mesh_covered) = support::box_scene_error(&mesh_image, &cam, mean_tint);
    println!(
        "points: error mean {error:.2} / 255, {:.1} % covered; blended meshes {mesh_error:.2}, {:.1} %",
        100.0 * covered,
        100.0 * mesh_covered
    );
    assert!(covered > 0.95, "{covered}");
    // The three scans' exposure tints differ, so no blend reaches the mean tint
    // exactly: the point proxy must do as well as the meshes do.
    assert!(
        error < 1.25 * mesh_error && error < 20.0,
        "{error} vs {mesh_error}"
    );
    assert!(image.pixels().all(|p| p[3] == 255));

    // 5,000 km out: the same image, positions relative to the eye throughout.
    let offset = texel::pose::pose_from_parts([4.0e5, 5.0e6, 120.0], [0.0, 0.0, 0.0, 1.0]).unwrap();
    let (_, far) = render(&box_model(&offset), &camera(&offset));
    let within = support::fraction_within(&image, &far, 8);
    println!("5,000 km out: {:.2} % of pixels within 8", 100.0 * within);
    assert!(within > 0.99, "{within}");
}
