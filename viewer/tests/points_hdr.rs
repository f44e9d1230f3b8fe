//! HDR through the `points` mode: scans of one scene taken at different exposures
//! (one underexposed, one overexposed and saturating) blend in radiance into the
//! scene's own colours, which the 8-bit blend of the same scans cannot; a model whose
//! every pixel saturated renders its background and nothing else, finite.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use std::sync::Arc;

use texel::EoExposure;
use texel::model::{Model, ModelEvent};
use texel::radiance::EoResponse;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::gpu::{RenderSettings, Renderer, read_radiance_texture};
use texel_viewer::scenes;
use texel_viewer::tonemap::{ToneMapSettings, ToneOperator};

const BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];

/// The box scene's three scans, scan `i` exposed `scales[i]` times the reference
/// (pixel values `scale × colour`, clipped at 255) and recording that exposure.
fn exposed_model(scales: [f64; 3]) -> Model {
    let scene = scenes::box_scene();
    let sensor = scenes::test_sensor();
    let mut model = Model::new();
    for (i, (pose, scale)) in scenes::box_scene_poses().iter().zip(scales).enumerate() {
        let s = scale as f32;
        let mut scan = scenes::scan(&scene, &sensor, pose, [s, s, s], i as u32);
        let mut eo = (*scan.texture).clone();
        eo.exposure = Some(EoExposure {
            exposure_time_s: scale,
            gain: 1.0,
        });
        scan.texture = Arc::new(eo);
        model
            .apply(ModelEvent::ScanAdded {
                id: model.next_id(),
                scan: Arc::new(scan),
                world_from_scan: *pose,
            })
            .unwrap();
    }
    model
}

fn camera() -> VirtualCamera {
    VirtualCamera::new(
        scenes::look_at([0.9, -0.6, 0.2], [0.0, 0.0, 5.0]),
        52.0,
        160,
        120,
    )
    .unwrap()
}

/// Radiance shown as it is: clipping, no exposure change, gamma 1, adaptation fixed
/// at the key (so the scale is 1).
fn identity_tone_map() -> ToneMapSettings {
    ToneMapSettings {
        operator: ToneOperator::Clip,
        key: 0.18,
        exposure_ev: 0.0,
        gamma: 1.0,
        adaptation: Some(0.18),
    }
}

fn render(model: &Model, tone_map: Option<ToneMapSettings>) -> image::RgbaImage {
    render_with(model, tone_map).0
}

/// The image, and with tone mapping the radiance it was mapped from.
fn render_with(
    model: &Model,
    tone_map: Option<ToneMapSettings>,
) -> (image::RgbaImage, Option<Vec<[f32; 4]>>) {
    let mut settings = RenderSettings {
        points: true,
        tone_map,
        ..Default::default()
    };
    settings.composite.background = BACKGROUND;
    let mut renderer = Renderer::new(support::gpu());
    renderer.sync_model(model).unwrap();
    // A linear camera: value z / 255 is exposure z / 255.
    let response = EoResponse::from_linear(|x| x);
    renderer.prepare_points(model, Some(&response));
    let image = renderer.render_to_image(&camera(), &settings).unwrap().0;
    let gpu = support::gpu();
    let radiance = renderer
        .points_radiance()
        .map(|t| read_radiance_texture(&gpu.device, &gpu.queue, t).unwrap());
    (image, radiance)
}

#[test]
fn exposures_blend_in_radiance_into_the_scene_colours() {
    // Half, once and twice the reference: the last saturates the bright checks.
    let model = exposed_model([0.5, 1.0, 2.0]);
    let (hdr, radiance) = render_with(&model, Some(identity_tone_map()));
    // The radiance the image was mapped from: finite, not negative, alpha 0 or 1.
    let radiance = radiance.unwrap();
    assert_eq!(radiance.len(), 160 * 120);
    for r in &radiance {
        assert!(r.iter().all(|v| v.is_finite() && *v >= 0.0), "{r:?}");
        assert!(r[3] == 0.0 || r[3] == 1.0, "{r:?}");
    }
    let ldr = render(&model, None);
    let (hdr_error, hdr_covered) = support::box_scene_error(&hdr, &camera(), [1.0; 3]);
    let (ldr_error, ldr_covered) = support::box_scene_error(&ldr, &camera(), [1.0; 3]);
    println!(
        "exposures 0.5/1/2: HDR error {hdr_error:.2} / 255 ({:.1} % coloured), 8-bit blend {ldr_error:.2} ({:.1} %)",
        100.0 * hdr_covered,
        100.0 * ldr_covered
    );
    assert!(hdr_covered > 0.9, "{hdr_covered}");
    // What remains is resampling at the checks' edges and the 8-bit steps of the
    // underexposed scan, as in every mode (the blended meshes of one exposure score
    // about 15 on this view in `points_render.rs`).
    assert!(hdr_error < 0.5 * ldr_error, "{hdr_error} vs {ldr_error}");
    assert!(hdr_error < 14.0, "{hdr_error}");
    assert!(hdr.pixels().all(|p| p[3] == 255));

    // Reinhard with auto-exposure: a finite image of the same coverage.
    let auto = render(&model, Some(ToneMapSettings::default()));
    let covered = auto.pixels().filter(|p| p.0[0..3] != [255, 0, 255]).count();
    let hdr_pixels = hdr.pixels().filter(|p| p.0[0..3] != [255, 0, 255]).count();
    assert!(
        covered.abs_diff(hdr_pixels) <= hdr_pixels / 100,
        "{covered} vs {hdr_pixels}"
    );
}

#[test]
fn a_model_saturated_everywhere_shows_only_its_background() {
    // Every value 255 in every scan: nothing measured, nothing coloured, no NaN.
    let model = exposed_model([40.0, 40.0, 40.0]);
    for tone_map in [identity_tone_map(), ToneMapSettings::default()] {
        let image = render(&model, Some(tone_map));
        assert!(
            image.pixels().all(|p| p.0 == [255, 0, 255, 255]),
            "a saturated pixel was coloured"
        );
    }
}
