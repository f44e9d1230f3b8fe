//! The rendered half of `texel-bench tradeoffs hdr`: the bracketed scans, fused and
//! placed at their true poses, drawn at the held-out poses by the viewer's `points`
//! mode with radiance (each scan's frame through the true response, blended per view
//! in half floats: the seed's second strategy as Texel renders it) and read back
//! before tone mapping, scored against the simulator's radiance truth on the pixels
//! where the scene has a surface.

use std::time::Instant;

use anyhow::{Context, Result};
use nalgebra::{Point3, Vector2, Vector3};
use sims::Scene;
use texel::PinholeCamera;
use texel::model::Model;
use texel::radiance::EoResponse;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::gpu::{GpuContext, RenderSettings, Renderer, read_radiance_texture};
use texel_viewer::tonemap::ToneMapSettings;

use super::hdr::Scores;
use crate::tradeoffs::rendering::HeldOutPose;

/// What the rendered HDR views gave.
pub struct RenderedHdr {
    /// Log errors over the pixels the render measured.
    pub scores: Scores,
    /// Pixels with a true surface, and of them those the render measured.
    pub surface_pixels: usize,
    pub measured_pixels: usize,
    /// Median frame time (render, tone map, read-back of the image), ms.
    pub frame_ms: f64,
    /// Building one scan's points, acquisition depth map and radiance texture, ms.
    pub prepare_ms_per_scan: f64,
    /// The GPU bytes the point proxy adds per scan (points, acquisition depth map,
    /// radiance texture).
    pub gpu_bytes_per_scan: f64,
}

pub fn render_hdr(
    gpu: &GpuContext,
    model: &Model,
    scene: &Scene,
    response: &EoResponse,
    held_out: &[HeldOutPose],
    view: &PinholeCamera,
) -> Result<RenderedHdr> {
    let mut renderer = Renderer::new(gpu);
    renderer.sync_model(model)?;
    let start = Instant::now();
    renderer.prepare_points(model, Some(response));
    renderer.wait_idle()?;
    let scans = model.len().max(1) as f64;
    let prepare_ms_per_scan = 1e3 * start.elapsed().as_secs_f64() / scans;
    let settings = RenderSettings {
        points: true,
        tone_map: Some(ToneMapSettings::default()),
        ..Default::default()
    };
    let fov = VirtualCamera::fov_y_deg_of(view);
    // The truth through the virtual camera's own pinhole (centre at the image's
    // middle, no distortion).
    let pinhole = PinholeCamera::from_vertical_fov(view.width, view.height, fov)?;
    let mut scores = Scores::default();
    let (mut surface_pixels, mut measured_pixels) = (0, 0);
    let mut times = Vec::new();
    for (i, pose) in held_out.iter().enumerate() {
        let camera = VirtualCamera::new(pose.world_from_eo, fov, view.width, view.height)?;
        if i == 0 {
            // Warm-up: pipelines and targets.
            renderer.render_to_image(&camera, &settings)?;
        }
        let start = Instant::now();
        renderer.render_to_image(&camera, &settings)?;
        times.push(1e3 * start.elapsed().as_secs_f64());
        let radiance = read_radiance_texture(
            &gpu.device,
            &gpu.queue,
            renderer.points_radiance().context("no radiance rendered")?,
        )?;
        let truth = scene.radiance_view(&pose.world_from_eo, &pinhole);
        let eye = Point3::from(pose.world_from_eo.translation.vector);
        for v in 0..pinhole.height {
            for u in 0..pinhole.width {
                let i = (v * pinhole.width + u) as usize;
                let (Some(t), Some(r)) = (truth.get(i), radiance.get(i)) else {
                    continue;
                };
                let Ok(ray) = pinhole.unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                else {
                    continue;
                };
                let dir: Vector3<f64> = pose.world_from_eo.rotation * ray;
                if scene.cast_ray(eye, dir).is_none() {
                    continue;
                }
                surface_pixels += 1;
                // Unmeasured pixels are mostly where the proxy has no points (ground
                // beyond the lidar's range): counted apart, not scored as radiance.
                if !(r[3] > 0.0) {
                    continue;
                }
                measured_pixels += 1;
                for (c, truth) in t.iter().enumerate() {
                    scores.add(r[c], true, *truth);
                }
            }
        }
    }
    Ok(RenderedHdr {
        scores,
        surface_pixels,
        measured_pixels,
        frame_ms: crate::tradeoffs::percentile(&times, 0.5),
        prepare_ms_per_scan,
        gpu_bytes_per_scan: renderer.points_bytes() as f64 / scans,
    })
}
