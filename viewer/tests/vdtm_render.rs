//! The VDTM pass on the GPU against the analytic scene's exact colours: projective
//! texturing through a strongly distorted EO camera lands where the lens put each
//! point (per-fragment distortion), holes are filled, several views blend into one
//! consistent image, and the pass reaches the same result 5,000 km from the origin.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use texel::camera::{Distortion, PinholeCamera};
use texel::distortion::PlumbBob;
use texel::{Pose, Sensor};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::scenes;
use texel_viewer::vdtm::{
    GpuVdtm, VdtmPass, VdtmSettings, VdtmViewConfig, prepare, render_vdtm_to_image,
};

const BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];

/// The test sensor with a distorted, off-centre EO camera.
fn distorted_sensor() -> Sensor {
    let base = scenes::sensor(96, 72, 160, 120);
    let mut model = base.model.clone();
    model.eo = PinholeCamera {
        cx: model.eo.cx + 3.0,
        cy: model.eo.cy - 2.0,
        distortion: Distortion::PlumbBob(PlumbBob {
            k1: -0.22,
            k2: 0.05,
            p1: 0.002,
            p2: -0.001,
            k3: 0.0,
        }),
        ..model.eo.clone()
    };
    Sensor::new(model)
}

/// How far a render is from the scene's true colours under `tint`.
struct Score {
    /// Mean and median absolute difference (0..255) over the pixels both cover.
    mean: f64,
    median: f64,
    /// Share of the pixels the scene covers that the render covers.
    covered: f64,
}

fn score(
    image: &image::RgbaImage,
    camera: &VirtualCamera,
    scene: &scenes::Scene,
    tint: [f32; 3],
) -> Score {
    let eye = camera.centre_world();
    let (mut errors, mut hit) = (Vec::new(), 0usize);
    for y in 0..camera.height {
        for x in 0..camera.width {
            let dir = camera.world_from_eo.rotation * camera.pixel_ray_view(x, y);
            let Some((_, c)) = scene.cast(&eye, &dir) else {
                continue;
            };
            hit += 1;
            let px = image.get_pixel(x, y);
            if [px[0], px[1], px[2]] == [255, 0, 255] {
                continue;
            }
            let mut e = 0.0;
            for k in 0..3 {
                let want = (f32::from(c[k]) * tint[k]).round().clamp(0.0, 255.0);
                e += f64::from((f32::from(px[k]) - want).abs()) / 3.0;
            }
            errors.push(e);
        }
    }
    let n = errors.len();
    errors.sort_by(f64::total_cmp);
    Score {
        mean: errors.iter().sum::<f64>() / n.max(1) as f64,
        median: errors.get(n / 2).copied().unwrap_or(f64::INFINITY),
        covered: n as f64 / hit.max(1) as f64,
    }
}

fn render(
    model: &texel::model::Model,
    eo: &PinholeCamera,
    camera: &VirtualCamera,
    settings: &VdtmSettings,
) -> image::RgbaImage {
    let gpu = support::gpu();
    let prepared = prepare(model, eo, &VdtmViewConfig::default()).unwrap();
    let mut gpu_model = GpuVdtm::upload(&gpu.device, &gpu.queue, &prepared).unwrap();
    let mut pass = VdtmPass::new(gpu);
    render_vdtm_to_image(
        gpu,
        &mut pass,
        &prepared,
        &mut gpu_model,
        camera,
        settings,
        BACKGROUND,
    )
    .unwrap()
}

#[test]
fn one_view_is_textured_through_its_distortion_exactly() {
    let sensor = distorted_sensor();
    let scene = scenes::box_scene();
    let pose = scenes::box_scene_poses()[0];
    let model = scenes::model_of(&scene, &sensor, &[pose], &Pose::identity());
    let camera = VirtualCamera::new(pose, 52.0, 160, 120).unwrap();
    let image = render(&model, &sensor.model.eo, &camera, &VdtmSettings::default());
    let got = score(&image, &camera, &scene, scenes::tint(0));

    // What ignoring the distortion would give: the image sampled at the pinhole
    // projection of each pixel's ray (same COP, so the surface does not matter).
    let eo = &sensor.model.eo;
    let scan_image = &model.scans()[0].scan.as_ref().unwrap().texture;
    let pinhole = PinholeCamera {
        distortion: Distortion::None,
        ..eo.clone()
    };
    let mut naive = image.clone();
    for y in 0..camera.height {
        for x in 0..camera.width {
            let ray = camera.pixel_ray_view(x, y);
            let Ok(p) = pinhole.project(&ray) else {
                continue;
            };
            let (u, v) = (p.x.round(), p.y.round());
            if u < 0.0 || v < 0.0 || u >= f64::from(eo.width) || v >= f64::from(eo.height) {
                continue;
            }
            let i = 3 * (v as usize * eo.width as usize + u as usize);
            let px = naive.get_pixel_mut(x, y);
            if px.0[0..3] != [255, 0, 255] {
                px.0[0..3].copy_from_slice(&scan_image.rgb[i..i + 3]);
            }
        }
    }
    let naive = score(&naive, &camera, &scene, scenes::tint(0));
    println!(
        "one distorted view: error mean {:.2} median {:.2} / 255, {:.1} % covered; ignoring distortion: mean {:.2} median {:.2}",
        got.mean,
        got.median,
        100.0 * got.covered,
        naive.mean,
        naive.median
    );
    // Depth edges of the merged surface leave a rim uncovered; resampling the
    // checker's edges is the rest of the error.
    assert!(got.covered > 0.85, "{}", got.covered);
    assert!(got.median < 2.0, "{}", got.median);
    assert!(
        got.mean < 0.35 * naive.mean,
        "{} vs {}",
        got.mean,
        naive.mean
    );
    // Far from the origin the f64-relative transforms keep the same texturing (the
    // voxel grid falls differently there, so only pixels both cover are compared).
    let offset = texel::pose::pose_from_parts([4.0e5, 5.0e6, 120.0], [0.0, 0.0, 0.0, 1.0]).unwrap();
    let far_model = scenes::model_of(&scene, &sensor, &[pose], &offset);
    let far_camera = VirtualCamera::new(offset * pose, 52.0, 160, 120).unwrap();
    let far = render(
        &far_model,
        &sensor.model.eo,
        &far_camera,
        &VdtmSettings::default(),
    );
    // The scene itself is not moved: the same pixel rays from the unmoved camera.
    let far_score = score(&far, &camera, &scene, scenes::tint(0));
    let magenta = |p: &image::Rgba<u8>| p.0[0..3] == [255, 0, 255];
    let (mut both, mut differing) = (0usize, 0usize);
    for (a, b) in image.pixels().zip(far.pixels()) {
        if !magenta(a) && !magenta(b) {
            both += 1;
            differing += usize::from((0..3).any(|k| a[k].abs_diff(b[k]) > 8));
        }
    }
    println!(
        "5,000 km out: {differing} of {both} pixels differ, {:.1} % covered",
        100.0 * far_score.covered
    );
    assert!(far_score.covered > 0.85, "{}", far_score.covered);
    assert!(
        differing * 200 < both,
        "{differing} of {both} pixels differ"
    );
}

#[test]
fn three_views_blend_into_the_scene_from_a_new_viewpoint() {
    let sensor = scenes::test_sensor();
    let scene = scenes::box_scene();
    let model = scenes::model_of(
        &scene,
        &sensor,
        &scenes::box_scene_poses(),
        &Pose::identity(),
    );
    let camera = VirtualCamera::new(
        scenes::look_at([0.9, -0.6, 0.2], [0.0, 0.0, 5.0]),
        52.0,
        160,
        120,
    )
    .unwrap();
    // Every scan has its own exposure tint; the truth takes their mean.
    let tints: Vec<[f32; 3]> = (0..3).map(scenes::tint).collect();
    let mean_tint = [0, 1, 2].map(|k| tints.iter().map(|t| t[k]).sum::<f32>() / 3.0);
    for settings in [
        VdtmSettings::default(),
        VdtmSettings::improved(),
        VdtmSettings {
            resolution_term: true,
            feather_px: 0.0,
        },
    ] {
        let image = render(&model, &sensor.model.eo, &camera, &settings);
        let got = score(&image, &camera, &scene, mean_tint);
        println!(
            "{}: error mean {:.2} median {:.2} / 255, {:.1} % covered",
            settings.label(),
            got.mean,
            got.median,
            100.0 * got.covered
        );
        // Holes are filled in object space: the surface covers the view.
        assert!(got.covered > 0.95, "{}: {}", settings.label(), got.covered);
        assert!(got.median < 14.0, "{}: {}", settings.label(), got.median);
        let finite = image.pixels().all(|p| p[3] == 255);
        assert!(finite);
    }
    // The eye exactly at an acquisition centre and behind the surface: still an image.
    let behind = VirtualCamera::new(
        scenes::look_at([0.0, -0.3, 9.0], [0.0, 0.0, 5.0]),
        52.0,
        160,
        120,
    )
    .unwrap();
    let image = render(&model, &sensor.model.eo, &behind, &VdtmSettings::improved());
    assert!(image.pixels().any(|p| p.0[0..3] != [255, 0, 255]));
}
