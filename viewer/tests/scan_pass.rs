//! The scan pass against analytic truth (reliability formulas, distances), culling
//! counts, and memory of the k-buffer against the naive layers.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use support::*;
use texel::Pose;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{RenderSettings, Renderer, Strategy};
use texel_viewer::reliability::{pov_confidence, range_confidence, reliability};
use texel_viewer::scenes;

/// One scan of the wall z = 5.05, read back from a virtual view: per pixel the GPU's
/// reliability and distance match the formulas evaluated in f64 at the true surface
/// point (normal accuracy = cosine to the acquisition COP on the flat wall).
#[test]
fn scan_pass_reliability_matches_the_formulas() {
    let sensor = scenes::test_sensor();
    let model = scenes::corridor(&sensor, 1);
    let acquisition = model.scans()[0].world_from_scan;
    let c_a = acquisition.translation.vector;
    let mut r = Renderer::new(gpu());
    r.sync_model(&model).unwrap();
    for (eye, gamma) in [
        ([0.0, 0.0, 0.0], 1.0),
        ([-0.8, 0.3, 2.0], 1.0),
        ([0.7, -0.2, 3.0], 2.0),
    ] {
        let pose = scenes::look_at(eye, [0.4, 0.0, 5.05]);
        let cam = VirtualCamera::new(pose, 45.0, 96, 72).unwrap();
        let mut s = RenderSettings::with_mode(Mode::Best);
        s.range_gamma = gamma;
        let (layers, _) = r.read_layers(&cam, &s).unwrap();
        let c_v = pose.translation.vector;
        let (mut checked, mut good) = (0, 0);
        for y in 0..cam.height {
            for x in 0..cam.width {
                let Some(f) = layers.fragments_at(x, y).first().copied() else {
                    continue;
                };
                let dir = pose.rotation * cam.pixel_ray_view(x, y);
                let t = (5.05 - c_v.z) / dir.z;
                let p = c_v + dir * t;
                let accuracy = (p.z - c_a.z) / (p - c_a).norm();
                let d_a = (p - c_a).norm();
                let want = reliability(
                    accuracy,
                    pov_confidence(p.into(), c_a.into(), c_v.into()),
                    range_confidence(t, d_a, f64::from(gamma)),
                );
                checked += 1;
                assert!(
                    (f64::from(f.distance_m) - t).abs() < 1e-3 * t,
                    "distance {} vs {t}",
                    f.distance_m
                );
                assert!((f64::from(f.sigma_m) - 0.01).abs() < 1e-6);
                if (f64::from(f.reliability) - want).abs() < 0.01 {
                    good += 1;
                }
            }
        }
        assert!(checked > 2000, "{checked} pixels covered");
        assert!(
            f64::from(good) >= 0.99 * f64::from(checked),
            "eye {eye:?}: {good}/{checked}"
        );
    }
}

#[test]
fn culling_counts_frustum_and_facing_away() {
    let id = Pose::identity();
    let mut r = box_renderer(&id);
    let s = RenderSettings::with_mode(Mode::Blended);
    // Looking away from the scene: every scan is outside the frustum.
    let away = VirtualCamera::new(
        scenes::look_at([0.0, 0.0, -3.0], [0.0, 0.0, -9.0]),
        50.0,
        64,
        48,
    )
    .unwrap();
    let (img, stats) = r.render_to_image(&away, &s).unwrap();
    assert_eq!(
        (stats.drawn, stats.culled_frustum, stats.culled_facing),
        (0, 3, 0),
        "{stats:?}"
    );
    assert!(img.pixels().all(|p| p[0] == 0 && p[1] == 0 && p[2] == 0));
    // Far behind the wall looking back at it: the front scan faces away (every point
    // of it lies in the ball spanned by the two COPs). The two oblique scans reach far
    // along the wall, where their POV confidence is still positive: they are drawn,
    // and their back faces are culled per triangle, so the image is background.
    let behind = VirtualCamera::new(
        scenes::look_at([0.0, 0.0, 40.0], [0.0, 0.0, 5.0]),
        50.0,
        64,
        48,
    )
    .unwrap();
    let (img, stats) = r.render_to_image(&behind, &s).unwrap();
    assert_eq!(
        (stats.drawn, stats.culled_frustum, stats.culled_facing),
        (2, 0, 1),
        "{stats:?}"
    );
    assert!(img.pixels().all(|p| p[0] == 0 && p[1] == 0 && p[2] == 0));
    // Hidden scans are counted apart.
    let mut hidden = s.clone();
    hidden.hidden.insert(1);
    let (_, stats) = r.render_to_image(&box_camera(&id), &hidden).unwrap();
    assert_eq!((stats.drawn, stats.hidden), (2, 1));
    // A corridor of 12 scans seen from near its start: the far ones are culled, and
    // the image equals the one with only the drawn scans uploaded.
    let sensor = scenes::test_sensor();
    let corridor = scenes::corridor(&sensor, 12);
    let mut rc = Renderer::new(gpu());
    rc.sync_model(&corridor).unwrap();
    let cam = VirtualCamera::new(
        scenes::look_at([1.5, 0.0, 1.0], [1.5, 0.0, 5.0]),
        50.0,
        64,
        48,
    )
    .unwrap();
    let (all, stats) = rc.render_to_image(&cam, &s).unwrap();
    assert!(stats.culled_frustum >= 3 && stats.drawn >= 2, "{stats:?}");
    let (visible, _) = rc.cull(&cam, &s);
    let mut only = Renderer::new(gpu());
    for scan in corridor.scans().iter().filter(|m| visible.contains(&m.id)) {
        only.add_scan(scan.id, scan.scan.as_ref().unwrap(), scan.world_from_scan)
            .unwrap();
    }
    let mut wide = VirtualCamera::new(cam.world_from_eo, 50.0, 64, 48).unwrap();
    wide.near_m = cam.near_m;
    let (same, _) = only.render_to_image(&wide, &s).unwrap();
    assert_eq!(all.as_raw(), same.as_raw());
}

/// The k-buffer's memory does not depend on the number of scans; the naive layers'
/// grows with it.
#[test]
fn kbuffer_memory_is_bounded() {
    let sensor = scenes::test_sensor();
    let mut r = Renderer::new(gpu());
    r.sync_model(&scenes::corridor(&sensor, 16)).unwrap();
    let s = RenderSettings::with_mode(Mode::Blended);
    let narrow = VirtualCamera::new(
        scenes::look_at([2.0, 0.0, 0.0], [2.0, 0.0, 5.0]),
        40.0,
        64,
        48,
    )
    .unwrap();
    let wide = VirtualCamera::new(
        scenes::look_at([7.5, 0.0, -8.0], [7.5, 0.0, 5.0]),
        70.0,
        64,
        48,
    )
    .unwrap();
    let memory = |r: &mut Renderer, cam: &VirtualCamera, strategy| {
        let mut s = s.clone();
        s.strategy = strategy;
        r.release_targets();
        let (_, stats) = r.render_to_image(cam, &s).unwrap();
        (stats.drawn, stats.target_memory.total())
    };
    let kb = Strategy::KBuffer { batch: 4 };
    let (few, kb_few) = memory(&mut r, &narrow, kb);
    let (many, kb_many) = memory(&mut r, &wide, kb);
    assert!(many >= few + 6, "{few} vs {many} drawn");
    assert_eq!(kb_few, kb_many);
    let (_, naive_few) = memory(&mut r, &narrow, Strategy::NaiveLayers);
    let (_, naive_many) = memory(&mut r, &wide, Strategy::NaiveLayers);
    let per_layer = 64 * 48 * 20;
    assert_eq!(naive_many - naive_few, (many - few) as u64 * per_layer);
}

/// Scans joining between frames are uploaded once; a pose revision only moves a scan
/// (the same image as a renderer that got the revised pose from the start).
#[test]
fn model_growth_and_pose_revisions() {
    use std::sync::Arc;
    use texel::model::{Model, ModelEvent};
    let sensor = scenes::test_sensor();
    let scene = scenes::box_scene();
    let poses = scenes::box_scene_poses();
    let cam = box_camera(&Pose::identity());
    let s = RenderSettings::with_mode(Mode::Blended);
    let mut model = Model::new();
    let mut r = Renderer::new(gpu());
    for (i, pose) in poses.iter().enumerate() {
        model
            .apply(ModelEvent::ScanAdded {
                id: i as u64,
                scan: Arc::new(scenes::scan(
                    &scene,
                    &sensor,
                    pose,
                    scenes::tint(i as u32),
                    i as u32,
                )),
                world_from_scan: *pose,
            })
            .unwrap();
        r.sync_model(&model).unwrap();
        let (_, stats) = r.render_to_image(&cam, &s).unwrap();
        assert_eq!((stats.scans, stats.drawn), (i + 1, i + 1));
    }
    let moved =
        texel::pose::pose_from_parts([0.3, 0.0, 0.1], [0.0, 0.05, 0.0, 1.0]).unwrap() * poses[1];
    model
        .apply(ModelEvent::PoseRevised {
            id: 1,
            world_from_scan: moved,
        })
        .unwrap();
    let (before, _) = r.render_to_image(&cam, &s).unwrap();
    r.sync_model(&model).unwrap();
    let (after, _) = r.render_to_image(&cam, &s).unwrap();
    assert!(
        fraction_within(&before, &after, 2) < 0.95,
        "the revision must show"
    );
    let mut fresh = Renderer::new(gpu());
    fresh.sync_model(&model).unwrap();
    let (want, _) = fresh.render_to_image(&cam, &s).unwrap();
    assert_eq!(after.as_raw(), want.as_raw());
}

/// Stretched triangles (over the box's silhouette) are removed unless kept: keeping
/// them covers more pixels with the front scan's texture smeared from box to wall.
#[test]
fn stretched_triangles_are_removed_unless_kept() {
    let id = Pose::identity();
    let mut r = box_renderer(&id);
    let cam = VirtualCamera::new(
        scenes::look_at([2.5, -0.5, 0.5], [0.0, 0.0, 5.0]),
        55.0,
        128,
        96,
    )
    .unwrap();
    let mut hidden = RenderSettings::with_mode(Mode::ScanColour);
    hidden.hidden.extend([1, 2]);
    let front = texel_viewer::composite::scan_colour(0).map(|v| (v * 255.0).round() as u8);
    let covered = |img: &image::RgbaImage| {
        img.pixels()
            .filter(|p| (0..3).all(|k| p[k].abs_diff(front[k]) <= 2))
            .count()
    };
    let (without, _) = r.render_to_image(&cam, &hidden).unwrap();
    hidden.keep_stretched = true;
    let (with, _) = r.render_to_image(&cam, &hidden).unwrap();
    assert!(
        covered(&with) > covered(&without) + 100,
        "{} vs {}",
        covered(&with),
        covered(&without)
    );
}
