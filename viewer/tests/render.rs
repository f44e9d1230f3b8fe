//! GPU rendering against the CPU reference and goldens, on small targets.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use support::*;
use texel::Pose;
use texel::pose::pose_from_parts;
use texel_viewer::composite::{Mode, composite_pixel};
use texel_viewer::gpu::{RenderSettings, Strategy};

#[test]
fn golden_images_per_mode() {
    let id = Pose::identity();
    let mut r = box_renderer(&id);
    let cam = box_camera(&id);
    for mode in Mode::ALL {
        let (img, stats) = r
            .render_to_image(&cam, &RenderSettings::with_mode(mode))
            .unwrap();
        assert_eq!(stats.drawn, 3, "{mode}");
        check_golden(&format!("box-{mode}"), &img);
    }
}

fn composite_modes() -> [Mode; 4] {
    [
        Mode::Best,
        Mode::Blended,
        Mode::ScanColour,
        Mode::Reliability,
    ]
}

/// The GPU composite equals the CPU reference applied to the GPU's own per-scan
/// layers, read back (>= 99 % of pixels within 2/255).
#[test]
fn gpu_composite_matches_the_cpu_reference() {
    let id = Pose::identity();
    let mut r = box_renderer(&id);
    let cam = box_camera(&id);
    for mode in composite_modes() {
        let settings = RenderSettings::with_mode(mode);
        let (layers, naive_img) = r.read_layers(&cam, &settings).unwrap();
        assert_eq!(layers.scans, vec![0, 1, 2]);
        let cpu = image::RgbaImage::from_fn(cam.width, cam.height, |x, y| {
            let c = composite_pixel(&layers.fragments_at(x, y), &settings.composite);
            image::Rgba(
                [c[0], c[1], c[2]]
                    .map(|v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
                    .into_iter()
                    .chain([255])
                    .collect::<Vec<_>>()
                    .try_into()
                    .unwrap(),
            )
        });
        let within = fraction_within(&cpu, &naive_img, 2);
        assert!(within >= 0.99, "{mode}: naive vs CPU {within}");
        let (kbuf_img, _) = r.render_to_image(&cam, &settings).unwrap();
        let within = fraction_within(&cpu, &kbuf_img, 2);
        assert!(within >= 0.99, "{mode}: k-buffer vs CPU {within}");
    }
}

/// The k-buffer (any batch size, k) gives the naive layers' image.
#[test]
fn kbuffer_equals_naive_layers() {
    let id = Pose::identity();
    let mut r = box_renderer(&id);
    let cam = box_camera(&id);
    for mode in composite_modes() {
        for (k, batch) in [(1, 1), (2, 2), (4, 3)] {
            let mut s = RenderSettings::with_mode(mode);
            s.composite.k = k;
            s.composite.blend_threshold = 0.5;
            s.strategy = Strategy::NaiveLayers;
            let (naive, n_stats) = r.render_to_image(&cam, &s).unwrap();
            s.strategy = Strategy::KBuffer { batch };
            let (kbuf, k_stats) = r.render_to_image(&cam, &s).unwrap();
            let within = fraction_within(&naive, &kbuf, 1);
            assert!(within >= 0.999, "{mode} k={k} batch={batch}: {within}");
            assert_eq!(n_stats.drawn, k_stats.drawn);
        }
    }
}

/// Clearing, drawing and merging each layer only inside its scan's footprint changes
/// no pixel, also when the layers still hold the previous view's scans (the clear
/// must cover what each layer's last scan wrote), for every batch size.
#[test]
fn footprints_change_no_pixel() {
    use texel_viewer::camera::VirtualCamera;
    use texel_viewer::gpu::Renderer;
    use texel_viewer::scenes;
    let sensor = scenes::sensor(32, 24, 64, 48);
    let model = scenes::corridor(&sensor, 30);
    let camera = |eye: [f64; 3], target: [f64; 3]| {
        VirtualCamera::new(scenes::look_at(eye, target), 50.0, 240, 160).unwrap()
    };
    // Along the corridor (small rectangles), then across it from further out.
    let views = [
        camera([0.0, 0.0, -3.0], [6.0, 0.0, 5.05]),
        camera([9.0, 1.0, -1.0], [3.0, 0.0, 5.05]),
        camera([4.5, 0.0, -8.0], [4.5, 0.0, 5.05]),
    ];
    for batch in [1, 3, 4] {
        let mut s = RenderSettings::with_mode(Mode::Blended);
        s.strategy = Strategy::KBuffer { batch };
        let mut with = Renderer::new(gpu());
        with.sync_model(&model).unwrap();
        let mut without = Renderer::new(gpu());
        without.sync_model(&model).unwrap();
        without.layer_footprints = false;
        for (i, cam) in views.iter().enumerate() {
            let (a, stats) = with.render_to_image(cam, &s).unwrap();
            let (b, _) = without.render_to_image(cam, &s).unwrap();
            assert!(
                stats.drawn > batch as usize,
                "view {i}: {} drawn",
                stats.drawn
            );
            let differ = a.pixels().zip(b.pixels()).filter(|(p, q)| p != q).count();
            assert_eq!(differ, 0, "batch {batch}, view {i}: {differ} pixels differ");
        }
    }
}

/// Merging only the pixels a batch's layers marked in the stencil changes no pixel:
/// every batch size, views near and far, and more batches than there are marks (the
/// marks wrap around after 255 batches).
#[test]
fn merge_marks_change_no_pixel() {
    use texel_viewer::camera::VirtualCamera;
    use texel_viewer::gpu::Renderer;
    use texel_viewer::scenes;
    assert!(
        texel_viewer::gpu::marks_supported(&gpu().device),
        "lavapipe offers {:?}: the marks go untested",
        texel_viewer::gpu::MARK_FEATURES
    );
    let sensor = scenes::sensor(16, 12, 32, 24);
    let model = scenes::corridor(&sensor, 300);
    let camera = |eye: [f64; 3], target: [f64; 3]| {
        VirtualCamera::new(scenes::look_at(eye, target), 50.0, 240, 160).unwrap()
    };
    let views = [
        (camera([0.0, 0.0, -3.0], [6.0, 0.0, 5.05]), 1),
        (camera([9.0, 1.0, -1.0], [3.0, 0.0, 5.05]), 3),
        // The whole corridor from far off: 300 scans, one a batch.
        (camera([149.5, 0.0, -330.0], [149.5, 0.0, 5.05]), 1),
    ];
    let mut marked = Renderer::new(gpu());
    marked.sync_model(&model).unwrap();
    let mut unmarked = Renderer::new(gpu());
    unmarked.sync_model(&model).unwrap();
    unmarked.merge_marks = false;
    for (i, (cam, batch)) in views.iter().enumerate() {
        let mut s = RenderSettings::with_mode(Mode::Blended);
        s.strategy = Strategy::KBuffer { batch: *batch };
        let (a, stats) = marked.render_to_image(cam, &s).unwrap();
        let (b, _) = unmarked.render_to_image(cam, &s).unwrap();
        if i == 2 {
            assert!(stats.drawn > 255, "{} drawn", stats.drawn);
        }
        let drawn = a.pixels().filter(|p| p.0 != a.get_pixel(0, 0).0).count();
        assert!(drawn > 200, "view {i}: only {drawn} pixels drawn");
        let differ = a.pixels().zip(b.pixels()).filter(|(p, q)| p != q).count();
        assert_eq!(differ, 0, "view {i}, batch {batch}: {differ} pixels differ");
    }
}

/// Model and camera translated by 5e6 m (and rotated): the same image.
#[test]
fn large_coordinates_render_the_same_image() {
    let near = Pose::identity();
    let far = pose_from_parts([5.0e6, -4.0e6, 1234.5], [0.1, 0.2, -0.05, 0.97]).unwrap();
    let (mut a, mut b) = (box_renderer(&near), box_renderer(&far));
    for mode in [Mode::Painter, Mode::Blended, Mode::ScanColour] {
        let s = RenderSettings::with_mode(mode);
        let (ia, _) = a.render_to_image(&box_camera(&near), &s).unwrap();
        let (ib, _) = b.render_to_image(&box_camera(&far), &s).unwrap();
        let within = fraction_within(&ia, &ib, 2);
        assert!(within >= 0.99, "{mode}: {within}");
    }
}

/// Fig. 8: a more reliable far scan must not show through a nearer surface.
#[test]
fn range_compliance_keeps_the_nearer_surface() {
    use texel_viewer::composite::{Fragment, scan_colour};
    let sensor = texel_viewer::scenes::test_sensor();
    let poses = [
        texel_viewer::scenes::look_at([0.0, 0.0, -4.0], [0.0, 0.0, 6.0]),
        texel_viewer::scenes::look_at([1.8, 0.0, 2.0], [0.0, 0.0, 6.05]),
    ];
    let model = texel_viewer::scenes::model_of(
        &texel_viewer::scenes::box_scene(),
        &sensor,
        &poses,
        &Pose::identity(),
    );
    let mut r = texel_viewer::gpu::Renderer::new(gpu());
    r.sync_model(&model).unwrap();
    let cam = texel_viewer::camera::VirtualCamera::new(
        texel_viewer::scenes::look_at([0.0, 0.0, 0.5], [0.0, 0.0, 6.0]),
        50.0,
        160,
        120,
    )
    .unwrap();
    let settings = RenderSettings::with_mode(Mode::ScanColour);
    let (layers, _) = r.read_layers(&cam, &settings).unwrap();
    let (img, _) = r.render_to_image(&cam, &settings).unwrap();
    let want = scan_colour(0).map(|v| (v * 255.0).round() as u8);
    // Pixels where the far wall of scan 1 is more reliable than the box of scan 0.
    let mut cases = 0;
    for y in 0..cam.height {
        for x in 0..cam.width {
            let f: Vec<Fragment> = layers.fragments_at(x, y);
            let (Some(a), Some(b)) = (
                f.iter().find(|f| f.scan == 0),
                f.iter().find(|f| f.scan == 1),
            ) else {
                continue;
            };
            if b.distance_m > a.distance_m + 1.0 && b.reliability > a.reliability {
                cases += 1;
                let p = img.get_pixel(x, y);
                assert!(
                    (0..3).all(|k| p[k].abs_diff(want[k]) <= 2),
                    "pixel {x},{y}: {p:?}"
                );
            }
        }
    }
    assert!(
        cases > 200,
        "the scene must exercise the case ({cases} pixels)"
    );
}

/// Identical scans at the same pose: the lower id wins everywhere, in every mode.
#[test]
fn ties_go_to_the_lower_scan_id() {
    use std::sync::Arc;
    use texel::model::{Model, ModelEvent};
    let sensor = texel_viewer::scenes::test_sensor();
    let pose = texel_viewer::scenes::box_scene_poses()[0];
    let scene = texel_viewer::scenes::box_scene();
    let mut model = Model::new();
    for (i, tint) in [[1.0, 1.0, 1.0], [0.5, 0.7, 1.2]].into_iter().enumerate() {
        let mut scan = texel_viewer::scenes::scan(&scene, &sensor, &pose, tint, 0);
        scan.seq = i as u32;
        model
            .apply(ModelEvent::ScanAdded {
                id: i as u64,
                scan: Arc::new(scan),
                world_from_scan: pose,
            })
            .unwrap();
    }
    let mut only_first = model.clone();
    let mut r = texel_viewer::gpu::Renderer::new(gpu());
    r.sync_model(&model).unwrap();
    let mut r0 = texel_viewer::gpu::Renderer::new(gpu());
    only_first = {
        // Scan 0's listing and its data.
        let mut m = Model::new();
        for e in only_first.snapshot().take(2) {
            m.apply(e).unwrap();
        }
        assert_eq!(m.resident_len(), 1);
        m
    };
    r0.sync_model(&only_first).unwrap();
    let cam = box_camera(&Pose::identity());
    for mode in Mode::ALL {
        let s = RenderSettings {
            composite: texel_viewer::composite::CompositeSettings {
                mode,
                k: 1,
                ..Default::default()
            },
            ..Default::default()
        };
        let (both, _) = r.render_to_image(&cam, &s).unwrap();
        let (first, _) = r0.render_to_image(&cam, &s).unwrap();
        assert_eq!(both.as_raw(), first.as_raw(), "{mode}");
    }
}

/// A scan whose every triangle has zero normal accuracy composites to background.
#[test]
fn zero_reliability_shows_the_background() {
    use std::sync::Arc;
    use texel::model::{Model, ModelEvent};
    let sensor = texel_viewer::scenes::test_sensor();
    let pose = texel_viewer::scenes::box_scene_poses()[0];
    let mut scan = texel_viewer::scenes::scan(
        &texel_viewer::scenes::box_scene(),
        &sensor,
        &pose,
        [1.0; 3],
        0,
    );
    scan.triangle_accuracy.iter_mut().for_each(|a| *a = 0.0);
    let mut model = Model::new();
    model
        .apply(ModelEvent::ScanAdded {
            id: 0,
            scan: Arc::new(scan),
            world_from_scan: pose,
        })
        .unwrap();
    let mut r = texel_viewer::gpu::Renderer::new(gpu());
    r.sync_model(&model).unwrap();
    let cam = box_camera(&Pose::identity());
    for mode in composite_modes() {
        let mut s = RenderSettings::with_mode(mode);
        s.composite.background = [0.2, 0.4, 0.6];
        let (img, stats) = r.render_to_image(&cam, &s).unwrap();
        assert_eq!(stats.drawn, 1);
        assert!(
            img.pixels()
                .all(|p| p[0] == 51 && p[1] == 102 && p[2] == 153),
            "{mode}"
        );
    }
    // The painter still shows the texture.
    let (img, _) = r
        .render_to_image(&cam, &RenderSettings::with_mode(Mode::Painter))
        .unwrap();
    assert!(
        img.pixels()
            .filter(|p| p[0] != 0 || p[1] != 0 || p[2] != 0)
            .count()
            > 5000
    );
}
