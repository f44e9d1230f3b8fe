//! Clean ranges against analytic ground truth computed independently in f64 from the
//! camera model: planes, spheres, boxes; fused points on the true surfaces.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use common::{fixed_camera_scene, scene, small};
use nalgebra::{Point3, Vector2, Vector3};
use sims::Simulator;

/// The f64 ray of lidar pixel `i` in world coordinates, from the camera model.
fn pixel_ray(sim: &Simulator, pose: &texel::Pose, i: usize) -> Option<(Point3<f64>, Vector3<f64>)> {
    let lidar = &sim.sensor_model().lidar;
    let (u, v) = (
        (i % lidar.width as usize) as f64,
        (i / lidar.width as usize) as f64,
    );
    let d = lidar.unproject_ray(Vector2::new(u, v)).ok()?;
    let world_from_lidar = sim.world_from_lidar(pose);
    Some((
        Point3::from(world_from_lidar.translation.vector),
        world_from_lidar.rotation * d,
    ))
}

fn check_against(
    sim: &Simulator,
    expected: impl Fn(Point3<f64>, Vector3<f64>) -> Option<f64>,
) -> usize {
    let mut checked = 0;
    for index in 0..sim.frame_count() {
        let frame = sim.frame(index).unwrap();
        for (i, &r) in frame.pair.range.ranges_m.iter().enumerate() {
            let (o, d) = pixel_ray(sim, &frame.world_from_eo, i).unwrap();
            match expected(o, d) {
                Some(want) => {
                    assert!(
                        (f64::from(r) - want).abs() < 1e-5,
                        "frame {index} pixel {i}: {r} vs {want}"
                    );
                    checked += 1;
                }
                None => assert!(r.is_nan(), "frame {index} pixel {i}: {r} where nothing is"),
            }
        }
    }
    checked
}

#[test]
fn a_plane_gives_the_exact_radial_range_per_pixel() {
    // Wall y = 4 (normal -y), unbounded.
    let text = fixed_camera_scene(
        "[[objects.plane]]\nmaterial = \"checks\"\nposition = [0.0, 4.0, 0.0]\nrotation_deg = [90.0, 0.0, 0.0]\n",
    );
    for effects in [&[][..], &["lens_distortion"][..]] {
        let sim = small(scene(&text), 1, Some(effects));
        let n = check_against(&sim, |o, d| {
            let t = (4.0 - o.y) / d.y;
            (t > 0.0).then_some(t)
        });
        assert_eq!(n, 2 * 32 * 32);
    }
}

#[test]
fn a_sphere_gives_the_exact_radial_range_per_pixel() {
    let text = fixed_camera_scene(
        "[[objects.sphere]]\nmaterial = \"grey\"\nposition = [0.2, 4.0, 1.1]\nradius = 0.9\n",
    );
    let sim = small(scene(&text), 1, Some(&["lens_distortion"]));
    let c = Vector3::new(0.2, 4.0, 1.1);
    let n = check_against(&sim, |o, d| {
        let oc = o.coords - c;
        let b = oc.dot(&d);
        let disc = b * b - (oc.norm_squared() - 0.81);
        (disc >= 0.0).then(|| -b - disc.sqrt())
    });
    assert!(n > 200, "{n} pixels saw the sphere");
}

#[test]
fn a_box_gives_the_exact_radial_range_per_pixel() {
    // Axis-aligned box, slab intersection in f64 as the reference.
    let text = fixed_camera_scene(
        "[[objects.box]]\nmaterial = \"checks\"\nposition = [0.1, 3.0, 1.0]\nsize = [1.2, 0.8, 1.0]\n",
    );
    let sim = small(scene(&text), 1, Some(&[]));
    let (lo, hi) = (Vector3::new(-0.5, 2.6, 0.5), Vector3::new(0.7, 3.4, 1.5));
    let n = check_against(&sim, |o, d| {
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for a in 0..3 {
            let (n, f) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
            t0 = t0.max(n.min(f));
            t1 = t1.min(n.max(f));
        }
        (t0 <= t1).then_some(t0)
    });
    assert!(n > 100, "{n} pixels saw the box");
}

#[test]
fn cast_ray_reports_distance_point_normal_and_object() {
    let text = fixed_camera_scene(
        "[[objects.plane]]\nmaterial = \"grey\"\nposition = [0.0, 6.0, 0.0]\nrotation_deg = [90.0, 0.0, 0.0]\n\
         [[objects.sphere]]\nname = \"ball\"\nmaterial = \"grey\"\nposition = [0.0, 3.0, 0.0]\nradius = 0.5\n",
    );
    let s = scene(&text);
    let hit = s
        .cast_ray(Point3::new(0.0, 0.0, 0.0), Vector3::new(0.0, 2.0, 0.0))
        .unwrap();
    assert!((hit.distance_m - 2.5).abs() < 1e-12);
    assert!((hit.point - Point3::new(0.0, 2.5, 0.0)).norm() < 1e-12);
    assert!((hit.normal - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
    assert_eq!(s.objects[hit.object as usize].name, "ball");
    let wall = s
        .cast_ray(Point3::new(2.0, 0.0, 0.0), Vector3::y())
        .unwrap();
    assert_eq!(s.objects[wall.object as usize].kind, "plane");
    assert!((wall.distance_m - 6.0).abs() < 1e-12);
    assert!(s.cast_ray(Point3::origin(), -Vector3::y()).is_none());
    assert!(s.cast_ray(Point3::origin(), Vector3::zeros()).is_none());
}

#[test]
fn fused_clean_frames_lie_on_the_true_surfaces_and_project_into_the_eo_image() {
    let text = fixed_camera_scene(
        "[[objects.plane]]\nmaterial = \"checks\"\nposition = [0.0, 4.0, 0.0]\nrotation_deg = [90.0, 0.0, 0.0]\n\
         [[objects.box]]\nmaterial = \"checks\"\nposition = [0.3, 2.5, 1.0]\nrotation_deg = [10.0, 20.0, 30.0]\nsize = [0.6, 0.6, 0.6]\n",
    );
    let sim = small(scene(&text), 3, Some(&["lens_distortion"]));
    let frame = sim.frame(1).unwrap();
    let truth = sim.lidar_truth(1);
    let scan = texel::fuse(
        &frame.pair.range,
        frame.pair.eo.clone(),
        sim.sensor(),
        &Default::default(),
    )
    .unwrap();
    let eo = &sim.sensor_model().eo;
    let mut checked = 0;
    for (v, &pixel) in scan.vertex_pixel.iter().enumerate() {
        let true_point = truth.hits[pixel as usize].unwrap().point;
        let p = scan.vertices[v];
        let world =
            frame.world_from_eo * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        assert!((world - true_point).norm() < 1e-4, "vertex {v}");
        if scan.vertex_textured[v] {
            let in_eo = frame.world_from_eo.inverse_transform_point(&true_point);
            let px = eo.project(&in_eo.coords).unwrap();
            let t = scan.tex_coords[v];
            let u = f64::from(t[0]) * f64::from(eo.width) - 0.5;
            let w = f64::from(t[1]) * f64::from(eo.height) - 0.5;
            assert!(
                (u - px.x).abs() < 0.05 && (w - px.y).abs() < 0.05,
                "vertex {v}"
            );
            checked += 1;
        }
    }
    assert!(checked > 500, "{checked}");
}

#[test]
fn tile_culled_rendering_equals_tracing_every_ray_through_the_bvh() {
    let lab = common::load("lab");
    let sim = small(lab.clone(), 0, Some(&["lens_distortion"]));
    let mut camera = sim.sensor_model().eo.clone();
    camera = sims::rescale_camera(&camera, 160, 120);
    let tiled = sims::render::CameraRays::new(&camera);
    assert!(tiled.tiles.iter().filter(|t| t.planes.is_some()).count() > tiled.tiles.len() * 9 / 10);
    let mut brute = tiled.clone();
    brute.tiles.clear();
    for i in [0, 7, 20, 31] {
        let pose = sim.true_pose(i);
        let a = lab.render_view_with(&pose, &tiled);
        let b = lab.render_view_with(&pose, &brute);
        assert_eq!(a.rgb, b.rgb, "frame {i}");
    }
}
