//! Fusion against the simulator's ground truth: with no effects every fused point lies
//! on the true surface and every texture coordinate is the EO projection of the true
//! point; with range noise the points are unbiased along their rays; stretched
//! triangles appear at the checkered cube's silhouette in `lab` and never inside a flat
//! face.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use nalgebra::{Point3, Vector3};
use sims::{Effect, LidarTruth, Scene, SimOptions, Simulator};
use texel::fuse::pixel_of_tex_coord;
use texel::{FuseConfig, TexelScan, fuse};
use texel_e2e::repo_root;

fn lab() -> Scene {
    Scene::load(&repo_root().join("configs/scenes/lab.toml")).unwrap()
}

/// `lab` at reduced resolution with the given effects, so each test renders quickly.
fn simulator(effects: Vec<Effect>, seed: u64) -> Simulator {
    let options = SimOptions {
        seed,
        effects: Some(effects),
        lidar_size: Some([96, 96]),
        eo_size: Some([320, 240]),
        ..SimOptions::default()
    };
    Simulator::with_options(lab(), &options).unwrap()
}

fn fused(sim: &Simulator, index: usize) -> (TexelScan, LidarTruth, nalgebra::Isometry3<f64>) {
    let frame = sim.frame(index).unwrap();
    let scan = fuse(
        &frame.pair.range,
        frame.pair.eo,
        sim.sensor(),
        &FuseConfig::default(),
    )
    .unwrap();
    (scan, sim.lidar_truth(index), frame.world_from_eo)
}

fn vertex(scan: &TexelScan, k: usize) -> Point3<f64> {
    let v = scan.vertices[k];
    Point3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]))
}

/// Points on the true surfaces within 1e-4 m; texture coordinates within 0.05 px of
/// the EO projection of the true point. Checked for the ideal camera and with the
/// sensor's lens distortion on (the capture then carries the distorted EO model).
#[test]
fn without_effects_points_and_texture_coordinates_match_the_truth() {
    for effects in [
        vec![],
        vec![Effect::with_defaults("lens_distortion").unwrap()],
    ] {
        let distorted = !effects.is_empty();
        let sim = simulator(effects, 1);
        let eo = sim.sensor_model().eo.clone();
        for index in [0, 9, 23] {
            let (scan, truth, world_from_eo) = fused(&sim, index);
            assert!(scan.vertex_count() > 5000, "frame {index}: too few points");
            let (mut worst_m, mut worst_px, mut textured) = (0.0f64, 0.0f64, 0usize);
            for k in 0..scan.vertex_count() {
                let pixel = scan.vertex_pixel[k] as usize;
                let hit = truth.hits[pixel].as_ref().expect("a return has a true hit");
                let p_world = world_from_eo * vertex(&scan, k);
                // Distance to the true surface (its tangent plane at the true point)
                // and to the true point itself.
                let off_surface = hit.normal.dot(&(p_world - hit.point)).abs();
                let off_point = (p_world - hit.point).norm();
                worst_m = worst_m.max(off_surface).max(off_point);
                if scan.vertex_textured[k] {
                    textured += 1;
                    let p_eo = world_from_eo.inverse() * hit.point;
                    let want = eo.project(&p_eo.coords).unwrap();
                    let got = pixel_of_tex_coord(scan.tex_coords[k], eo.width, eo.height);
                    worst_px = worst_px.max((got - want).norm());
                }
            }
            eprintln!(
                "frame {index} (distortion {distorted}): {} points, worst {worst_m:e} m off the \
                 truth, worst texture coordinate {worst_px:.2e} px off",
                scan.vertex_count()
            );
            assert!(
                worst_m < 1e-4,
                "frame {index} (distortion {distorted}): a fused point is {worst_m:e} m off the true surface"
            );
            assert!(
                worst_px < 0.05,
                "frame {index} (distortion {distorted}): a texture coordinate is {worst_px} px off"
            );
            assert!(textured * 10 > scan.vertex_count() * 9);
        }
    }
}

/// With `range_noise` alone, the signed error of each point along its lidar ray has
/// mean within 3 standard errors of zero and a spread matching the sensor's sigma(r).
#[test]
fn with_range_noise_points_are_unbiased_along_their_rays() {
    let sim = simulator(vec![Effect::with_defaults("range_noise").unwrap()], 5);
    let noise = sim.sensor_model().range_noise;
    let (mut sum, mut sum_var, mut sum_z2, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
    for index in [2, 14] {
        let (scan, truth, world_from_eo) = fused(&sim, index);
        let lidar_origin = truth.world_from_lidar.translation.vector;
        for k in 0..scan.vertex_count() {
            let pixel = scan.vertex_pixel[k] as usize;
            let Some(hit) = truth.hits[pixel].as_ref() else {
                continue;
            };
            let p_world = world_from_eo * vertex(&scan, k);
            let ray: Vector3<f64> = (hit.point.coords - lidar_origin).normalize();
            let error = (p_world.coords - lidar_origin).dot(&ray) - hit.distance_m;
            let sigma = noise.sigma_at(hit.distance_m);
            sum += error;
            sum_var += sigma * sigma;
            sum_z2 += (error / sigma).powi(2);
            n += 1;
        }
    }
    eprintln!(
        "{n} points: mean signed error along the ray {:e} m, normalised RMS {:.4}",
        sum / n as f64,
        (sum_z2 / n as f64).sqrt()
    );
    assert!(n > 10_000, "only {n} points");
    let mean = sum / n as f64;
    let standard_error = sum_var.sqrt() / n as f64;
    assert!(
        mean.abs() < 3.0 * standard_error,
        "mean signed error {mean:e} m exceeds 3 standard errors ({standard_error:e} m)"
    );
    // The normalised errors have unit variance when the noise is sigma(r).
    let z_rms = (sum_z2 / n as f64).sqrt();
    assert!(
        (0.95..1.05).contains(&z_rms),
        "normalised error RMS {z_rms}"
    );
}

/// Stretched triangles: every triangle that joins the cube to a surface far behind it
/// is stretched; no triangle whose vertices all lie on one flat face is.
#[test]
fn stretched_triangles_mark_the_cube_silhouette_and_never_a_flat_face() {
    let sim = simulator(vec![Effect::with_defaults("range_noise").unwrap()], 9);
    let cube = sim
        .scene()
        .objects
        .iter()
        .position(|o| o.name == "checkered cube")
        .unwrap() as u32;
    let (mut silhouette, mut silhouette_stretched, mut flat, mut flat_stretched) = (0, 0, 0, 0);
    for index in [0, 12, 27] {
        let (scan, truth, _) = fused(&sim, index);
        for (t, flags) in scan.triangles.iter().zip(&scan.triangle_flags) {
            let hits: Vec<_> = t
                .iter()
                .map(|&v| {
                    truth.hits[scan.vertex_pixel[v as usize] as usize]
                        .as_ref()
                        .unwrap()
                })
                .collect();
            let on_cube = hits.iter().filter(|h| h.object == cube).count();
            let ranges: Vec<f64> = hits.iter().map(|h| h.distance_m).collect();
            let jump = ranges.iter().cloned().fold(f64::MIN, f64::max)
                - ranges.iter().cloned().fold(f64::MAX, f64::min);
            if on_cube > 0 && on_cube < 3 && jump > 0.3 {
                silhouette += 1;
                silhouette_stretched += usize::from(flags.is_stretched());
            }
            let one_face = hits
                .iter()
                .all(|h| h.object == hits[0].object && h.normal.dot(&hits[0].normal) > 1.0 - 1e-9);
            let planar_object = sim.scene().objects[hits[0].object as usize].kind != "sphere"
                && sim.scene().objects[hits[0].object as usize].kind != "cylinder";
            if one_face && planar_object {
                flat += 1;
                flat_stretched += usize::from(flags.is_stretched());
            }
        }
    }
    eprintln!(
        "silhouette triangles {silhouette} ({silhouette_stretched} stretched), flat-face \
         triangles {flat} ({flat_stretched} stretched)"
    );
    assert!(
        silhouette > 50,
        "only {silhouette} silhouette triangles seen"
    );
    assert_eq!(
        silhouette_stretched, silhouette,
        "silhouette triangles not flagged stretched"
    );
    assert!(flat > 10_000, "only {flat} flat-face triangles seen");
    assert_eq!(flat_stretched, 0, "stretched triangles inside flat faces");
}
