//! The `points` mode's frame (Lechelek et al. 2019): the virtual view's depth map from
//! the visible scans' points, every acquisition view's colour weighted and summed per
//! pixel, and the weighted mean into the target. Each scan's points and acquisition
//! depth map are built once, by [`Renderer::prepare_points`], as scans arrive.

use std::collections::HashMap;

use texel::model::{Model, ScanId};
use texel::radiance::EoResponse;

use super::{FrameStats, RenderSettings, RenderTarget, Renderer};
use crate::camera::VirtualCamera;
use crate::gpu::pipelines::Pipelines;
use crate::gpu::points::depth_map::{DepthMapTargets, DepthMapView, depth_map_texture};
use crate::gpu::points::pipelines::{POINT_ACCUMULATION_FORMAT, PointsPipelines};
use crate::gpu::points::scan::{GpuPoints, acquisition_map_size};
use crate::gpu::targets::{TargetMemory, Texture, colour_pass, pixels, texture};
use crate::gpu::tonemap::{RADIANCE_FORMAT, ToneMapPass};

/// The virtual view's targets, rebuilt when its size changes.
struct ViewTargets {
    depth_map: DepthMapTargets,
    resolved: Texture,
    accumulation: Texture,
    output: wgpu::BindGroup,
    /// The view's radiance, the tone-mapping pass's input (built on first use).
    radiance: Option<Texture>,
}

impl ViewTargets {
    fn new(device: &wgpu::Device, pipelines: &PointsPipelines, width: u32, height: u32) -> Self {
        let depth_map = DepthMapTargets::new(device, pipelines, width, height, true);
        let resolved = depth_map_texture(device, "points view depth map", width, height);
        let accumulation = texture(
            device,
            "points colour sums",
            width,
            height,
            1,
            POINT_ACCUMULATION_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            false,
        );
        let output = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("points output"),
            layout: &pipelines.output_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 1,
                resource: wgpu::BindingResource::TextureView(&accumulation.view),
            }],
        });
        Self {
            depth_map,
            resolved,
            accumulation,
            output,
            radiance: None,
        }
    }

    /// Bytes held: the depth map's targets, the filled map, the colour sums and,
    /// once used, the radiance.
    fn bytes(&self) -> u64 {
        let (w, h) = (self.depth_map.width, self.depth_map.height);
        let radiance = if self.radiance.is_some() { 8 } else { 0 };
        self.depth_map.bytes + pixels(w, h) * (4 + 8 + radiance)
    }
}

/// The mode's long-lived part: pipelines, the view's targets, and the targets that
/// fill acquisition depth maps (by map size).
pub(crate) struct PointsState {
    pipelines: PointsPipelines,
    view: Option<ViewTargets>,
    acquisition: HashMap<(u32, u32), DepthMapTargets>,
    tone_map: Option<ToneMapPass>,
}

impl PointsState {
    fn new(device: &wgpu::Device, shared: &Pipelines) -> Self {
        Self {
            pipelines: PointsPipelines::new(device, &shared.frame_layout, &shared.sampler),
            view: None,
            acquisition: HashMap::new(),
            tone_map: None,
        }
    }
}

impl PointsState {
    pub(crate) fn release_targets(&mut self) {
        self.view = None;
        self.acquisition.clear();
    }
}

impl Renderer {
    /// Builds the points and the acquisition depth map of every uploaded scan of
    /// `model` that has none yet (each scan once, as it arrives), and with `radiance`
    /// each such scan's radiance texture through that response where its EO frame
    /// records its exposure; returns how many scans' points were built.
    pub fn prepare_points(&mut self, model: &Model, radiance: Option<&EoResponse>) -> usize {
        let device = &self.device;
        let state = self
            .points
            .get_or_insert_with(|| PointsState::new(device, &self.pipelines));
        let mut built = 0;
        for (s, scan) in model.resident() {
            let Some(placed) = self.scans.get_mut(&s.id) else {
                continue;
            };
            if let Some(points) = placed.points.as_mut() {
                if let Some(response) = radiance {
                    points.ensure_radiance(device, &self.queue, &state.pipelines, scan, response);
                }
                continue;
            }
            let mut gpu = GpuPoints::upload(device, &state.pipelines, scan, &placed.gpu.eo_view);
            let (mw, mh) = acquisition_map_size(scan.texture.width, scan.texture.height);
            let targets = state
                .acquisition
                .entry((mw, mh))
                .or_insert_with(|| DepthMapTargets::new(device, &state.pipelines, mw, mh, false));
            gpu.fill_acquisition_depth(
                device,
                &self.queue,
                &state.pipelines,
                targets,
                &self.frame_bind_group,
                scan,
            );
            if let Some(response) = radiance {
                gpu.ensure_radiance(device, &self.queue, &state.pipelines, scan, response);
            }
            placed.points = Some(gpu);
            built += 1;
        }
        built
    }

    /// The last `points` frame's depth map (view-frame z per pixel, 0 where none;
    /// `POINT_DEPTH_FORMAT`), for reading back.
    pub fn points_depth_map(&self) -> Option<&wgpu::Texture> {
        Some(&self.points.as_ref()?.view.as_ref()?.resolved.texture)
    }

    /// The last HDR `points` frame's radiance before tone mapping (`RADIANCE_FORMAT`,
    /// alpha 0 where no view measured the pixel), for reading back.
    pub fn points_radiance(&self) -> Option<&wgpu::Texture> {
        Some(
            &self
                .points
                .as_ref()?
                .view
                .as_ref()?
                .radiance
                .as_ref()?
                .texture,
        )
    }

    /// GPU bytes of the scans' points and acquisition depth maps.
    pub fn points_bytes(&self) -> u64 {
        self.scans
            .values()
            .filter_map(|p| p.points.as_ref())
            .map(|p| p.bytes)
            .sum()
    }

    /// Records and submits a `points` frame: `visible` scans splat the view's depth
    /// map; every scan not hidden may colour it.
    pub(super) fn render_points(
        &mut self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
        target: &RenderTarget<'_>,
        visible: &[ScanId],
        mut stats: FrameStats,
    ) -> Result<FrameStats, super::GpuError> {
        let device = &self.device;
        let state = self
            .points
            .get_or_insert_with(|| PointsState::new(device, &self.pipelines));
        let (width, height) = (target.width, target.height);
        let view = match state.view.take() {
            Some(v) if (v.depth_map.width, v.depth_map.height) == (width, height) => v,
            _ => ViewTargets::new(device, &state.pipelines, width, height),
        };
        let view = state.view.insert(view);
        let f = camera.focal_px() as f32;
        view.depth_map.write_view(
            &self.queue,
            &DepthMapView {
                intrinsics: [f, f, width as f32 * 0.5 - 0.5, height as f32 * 0.5 - 0.5],
                at_texture_coordinates: false,
            },
        );
        let world_from_view = camera.world_from_eo;
        let shown = |id: &ScanId| {
            !settings.hidden.contains(id) && settings.only.as_ref().is_none_or(|o| o.contains(id))
        };
        // With tone mapping the views colour in radiance: only scans that have it.
        let hdr = settings.tone_map;
        let mut colouring = Vec::new();
        for (id, placed) in self.scans.iter().filter(|(id, _)| shown(id)) {
            if let Some(points) = &placed.points {
                points.write_frame(&self.queue, &world_from_view, &placed.world_from_scan);
                colouring.push((*id, points));
            }
        }
        let splatted: Vec<&GpuPoints> = colouring
            .iter()
            .filter(|(id, _)| visible.binary_search(id).is_ok())
            .map(|(_, p)| *p)
            .collect();
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("points frame"),
        });
        let targets = view.depth_map.encode(
            device,
            &state.pipelines,
            &mut encoder,
            &self.frame_bind_group,
            &splatted,
            true,
            &view.resolved.view,
        );
        {
            let mut pass = colour_pass(
                &mut encoder,
                "points colour",
                &view.accumulation.view,
                wgpu::Color::TRANSPARENT,
            );
            pass.set_pipeline(&state.pipelines.colour);
            pass.set_bind_group(0, &self.frame_bind_group, &[]);
            pass.set_bind_group(1, view.depth_map.view_bind_group(), &[]);
            pass.set_bind_group(3, &targets, &[]);
            for (_, points) in colouring.iter().filter(|(_, p)| p.camera.is_some()) {
                let group = if hdr.is_some() {
                    points.radiance_bind_group.as_ref()
                } else {
                    Some(&points.bind_group)
                };
                if let Some(group) = group {
                    pass.set_bind_group(2, group, &[]);
                    pass.draw(0..3, 0..1);
                }
            }
        }
        match &hdr {
            // Radiance into the view's float target, then tone-mapped into the target.
            Some(tone) => {
                let radiance = view.radiance.get_or_insert_with(|| {
                    texture(
                        device,
                        "points radiance",
                        width,
                        height,
                        1,
                        RADIANCE_FORMAT,
                        wgpu::TextureUsages::RENDER_ATTACHMENT
                            | wgpu::TextureUsages::TEXTURE_BINDING
                            | wgpu::TextureUsages::COPY_SRC,
                        false,
                    )
                });
                let clear = wgpu::Color::TRANSPARENT;
                let mut pass = colour_pass(&mut encoder, "points radiance", &radiance.view, clear);
                pass.set_pipeline(&state.pipelines.radiance_output);
                pass.set_bind_group(0, &self.frame_bind_group, &[]);
                pass.set_bind_group(1, &view.output, &[]);
                pass.draw(0..3, 0..1);
                drop(pass);
                let pass = state
                    .tone_map
                    .get_or_insert_with(|| ToneMapPass::with_device(device, &self.queue));
                pass.background = settings.composite.background;
                let size = (width, height);
                pass.record(
                    &mut encoder,
                    &radiance.view,
                    size,
                    tone,
                    target.view,
                    target.format,
                );
            }
            None => {
                let output = state.pipelines.output(device, target.format);
                let clear = wgpu::Color::BLACK;
                let mut pass = colour_pass(&mut encoder, "points output", target.view, clear);
                pass.set_pipeline(output);
                pass.set_bind_group(0, &self.frame_bind_group, &[]);
                pass.set_bind_group(1, &view.output, &[]);
                pass.draw(0..3, 0..1);
            }
        }
        crate::gpu::submit(&self.queue, Some(encoder.finish()));
        stats.target_memory = TargetMemory {
            layers: view.bytes(),
            ..Default::default()
        };
        self.nearest_ready = false;
        Ok(stats)
    }
}
