//! The renderer's long-lived part: the pipelines, each scan's GPU data and pose (the
//! model sync), the frame uniform and the depth buffer; per frame it culls, writes
//! the uniforms and hands the frame to one compositing strategy (`painter.rs`,
//! `kbuffer.rs`, `naive_layers.rs`). Per frame only uniforms are written; scan data
//! is uploaded once and dropped when residency evicts it (`crate::residency`).

mod frame;
mod kbuffer;
mod naive_layers;
mod painter;
mod points;
mod progressive;

use std::collections::{BTreeMap, BTreeSet, HashMap};

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec4};
use nalgebra::Translation3;
use texel::Pose;
use texel::model::{Model, ScanId};

use self::frame::Frame;
use self::kbuffer::{KBufferShape, PhaseClock};
pub use self::progressive::{Progress, ProgressiveFrame};
use super::pipelines::{OutputPipelines, Pipelines};
use super::relative::{gpu_from_pose_relative, pose_relative};
use super::scan_data::{GpuScan, ScanUniform};
use super::targets::{DepthTarget, TargetMemory};
use super::{GpuContext, GpuError};
use crate::camera::VirtualCamera;
use crate::composite::{CompositeSettings, MAX_K, Mode};
use crate::cull::{Visibility, classify};

/// How per-scan fragments are gathered for compositing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Strategy {
    /// Per-pixel top-k after a depth pre-pass, scans rendered `batch` at a time:
    /// memory O((k + batch) x pixels), independent of the number of scans.
    KBuffer { batch: u32 },
    /// One layer per visible scan (the baseline): memory O(scans x pixels).
    NaiveLayers,
}

impl Default for Strategy {
    fn default() -> Self {
        Strategy::KBuffer { batch: 4 }
    }
}

/// Everything about a frame that is not the camera.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSettings {
    pub composite: CompositeSettings,
    /// Exponent of the range confidence `min(1, d_virtual / d_acquisition)^gamma`.
    pub range_gamma: f32,
    /// Draw stretched triangles too (the paper removes them).
    pub keep_stretched: bool,
    pub strategy: Strategy,
    /// Scans switched off by the user.
    pub hidden: BTreeSet<ScanId>,
    /// Draw only these scans (`None`: every scan): the scans below the finest
    /// level-of-detail tiles in a hybrid frame.
    pub only: Option<BTreeSet<ScanId>>,
    /// Fill a pixel no scan drew from its neighbours when at least 6 of its 8 hold
    /// scans (`composite_kbuffer.wgsl`; the k-buffer composite only): in a hybrid
    /// frame, a few chosen scans leave their dropouts and the gaps between their
    /// triangles as holes that every scan together would have covered.
    pub fill_enclosed_holes: bool,
    /// Render the point proxy (Lechelek et al. 2019) instead of compositing meshes;
    /// needs [`Renderer::prepare_points`] for the scans it shows.
    pub points: bool,
    /// With `points`: colour from the scans' radiance (their EO frames made radiance by
    /// the response given to [`Renderer::prepare_points`]; scans without an exposure
    /// colour nothing) and tone-map it with these settings. `None`: display values.
    pub tone_map: Option<crate::tonemap::ToneMapSettings>,
    /// Draw each scan's coarse triangles (a 2 x 2 block of lidar cells as two
    /// triangles where it is smooth): the interactive frame of adaptive quality.
    pub coarse: bool,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            composite: CompositeSettings::default(),
            range_gamma: 1.0,
            keep_stretched: false,
            strategy: Strategy::default(),
            hidden: BTreeSet::new(),
            only: None,
            fill_enclosed_holes: false,
            points: false,
            tone_map: None,
            coarse: false,
        }
    }
}

impl RenderSettings {
    pub fn with_mode(mode: Mode) -> Self {
        let mut s = Self::default();
        s.composite.mode = mode;
        s
    }
}

/// What a frame drew.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FrameStats {
    pub scans: usize,
    pub drawn: usize,
    pub culled_frustum: usize,
    pub culled_facing: usize,
    pub hidden: usize,
    /// Size-dependent targets used by this frame.
    pub target_memory: TargetMemory,
    /// GPU bytes of all uploaded scans (vertices, indices, textures).
    pub scan_bytes: u64,
    /// With [`Renderer::profile_phases`]: milliseconds spent in each k-buffer phase
    /// (pre-pass, scan layers, merges, composite), each submitted and waited for on
    /// its own.
    pub phase_ms: Option<[f64; 4]>,
}

/// Where a frame goes: a view of a texture of `format` and size.
#[derive(Debug, Clone, Copy)]
pub struct RenderTarget<'a> {
    pub view: &'a wgpu::TextureView,
    pub format: wgpu::TextureFormat,
    pub width: u32,
    pub height: u32,
}

/// The frame uniform (`Frame` in `common.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct FrameUniform {
    pub(crate) clip_from_view: Mat4,
    /// rgb: background colour (display values); a: 1.
    pub(crate) background: Vec4,
    /// x: blend threshold, y: range-confidence exponent, z: 1 if the target is sRGB.
    pub(crate) params: Vec4,
    /// x: mode, y: k, z: visible scans (the naive composite's layers), w: target width.
    pub(crate) counts: UVec4,
}

/// An uploaded scan and where the model currently places it.
struct PlacedScan {
    gpu: GpuScan,
    world_from_scan: Pose,
    /// Built when the `points` mode first needs the scan.
    points: Option<crate::gpu::points::scan::GpuPoints>,
}

impl PlacedScan {
    /// Its GPU bytes: the scan's data and, once built, its point proxy.
    fn bytes(&self) -> u64 {
        self.gpu.bytes + self.points.as_ref().map_or(0, |p| p.bytes)
    }

    /// This scan's uniform for a camera at `view_from_world`: only poses relative to the
    /// camera reach the GPU.
    fn uniform(&self, id: ScanId, view_from_world: &Pose) -> ScanUniform {
        let view_from_scan = gpu_from_pose_relative(view_from_world, &self.world_from_scan);
        // The acquisition COP as the origin of a frame placed in the scan: its position
        // in the view frame is that frame's translation.
        let cop = self.gpu.cop_scan;
        let world_from_cop = self.world_from_scan * Translation3::new(cop.x, cop.y, cop.z);
        let view_from_cop = gpu_from_pose_relative(view_from_world, &world_from_cop);
        ScanUniform {
            view_from_scan,
            cop_view: view_from_cop.w_axis,
            noise: Vec4::new(
                self.gpu.noise.sigma_m.max(0.0) as f32,
                self.gpu.noise.sigma_per_m.max(0.0) as f32,
                0.0,
                0.0,
            ),
            ids: UVec4::new(u32::try_from(id).unwrap_or(u32::MAX), 0, 0, 0),
        }
    }
}

pub struct Renderer {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pipelines: Pipelines,
    /// Pipelines writing into the caller's target, built on first use of a format.
    outputs: HashMap<wgpu::TextureFormat, OutputPipelines>,
    scans: BTreeMap<ScanId, PlacedScan>,
    frame_uniform: wgpu::Buffer,
    frame_bind_group: wgpu::BindGroup,
    depth: Option<DepthTarget>,
    kbuffer: Option<kbuffer::KBufferTargets>,
    pub(crate) naive: Option<naive_layers::NaiveTargets>,
    /// Submit and wait after each k-buffer phase and time it (slower; for `bench`).
    pub profile_phases: bool,
    /// Clear, draw and merge each k-buffer layer only inside its scan's pixel
    /// rectangle (`crate::footprint`); off, over the whole target, as before there
    /// were footprints (for `bench`: same image, more time).
    pub layer_footprints: bool,
    /// Merge each batch only at the pixels where one of its scans kept a fragment (the
    /// layer passes mark them in the stencil); off, over the batch's whole rectangle.
    pub merge_marks: bool,
    /// The last frame went through the k-buffer, so its pre-pass target holds that
    /// frame's nearest scan distances.
    nearest_ready: bool,
    /// The `points` mode's pipelines and targets, built on its first use.
    points: Option<points::PointsState>,
    /// Counts frames begun and changes to the scans: a progressive frame that began
    /// in an older generation is stale.
    generation: u64,
}

impl Renderer {
    pub fn new(gpu: &GpuContext) -> Self {
        let device = gpu.device.clone();
        let pipelines = Pipelines::new(&device);
        let frame_uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("frame uniform"),
            size: std::mem::size_of::<FrameUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let frame_bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("frame"),
            layout: &pipelines.frame_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: frame_uniform.as_entire_binding(),
            }],
        });
        Self {
            device,
            queue: gpu.queue.clone(),
            pipelines,
            outputs: HashMap::new(),
            scans: BTreeMap::new(),
            frame_uniform,
            frame_bind_group,
            depth: None,
            kbuffer: None,
            naive: None,
            profile_phases: false,
            layer_footprints: true,
            merge_marks: true,
            nearest_ready: false,
            points: None,
            generation: 0,
        }
    }

    /// Uploads a scan once; adding an id again only moves it.
    pub fn add_scan(
        &mut self,
        id: ScanId,
        scan: &texel::TexelScan,
        world_from_scan: Pose,
    ) -> Result<(), GpuError> {
        if let Some(placed) = self.scans.get_mut(&id) {
            if placed.world_from_scan != world_from_scan {
                placed.world_from_scan = world_from_scan;
                self.generation += 1;
            }
            return Ok(());
        }
        self.generation += 1;
        let gpu = GpuScan::upload(
            &self.device,
            &self.queue,
            &self.pipelines.scan_layout,
            &self.pipelines.sampler,
            id,
            scan,
        )?;
        self.scans.insert(
            id,
            PlacedScan {
                gpu,
                world_from_scan,
                points: None,
            },
        );
        Ok(())
    }

    /// A revised pose: only the scan's uniform changes (at the next frame).
    pub fn set_pose(&mut self, id: ScanId, world_from_scan: Pose) -> bool {
        match self.scans.get_mut(&id) {
            Some(p) => {
                if p.world_from_scan != world_from_scan {
                    p.world_from_scan = world_from_scan;
                    self.generation += 1;
                }
                true
            }
            None => false,
        }
    }

    /// Brings the GPU copy up to date with a model: uploads scans not seen yet and
    /// takes every current pose.
    pub fn sync_model(&mut self, model: &Model) -> Result<(), GpuError> {
        for (s, scan) in model.resident() {
            self.add_scan(s.id, scan, s.world_from_scan)?;
        }
        Ok(())
    }

    /// Forgets every scan (the source reset its model; ids will be reused).
    pub fn clear_scans(&mut self) {
        self.scans.clear();
        self.generation += 1;
    }

    /// Drops a scan's GPU data (its buffers and texture are freed when no frame in
    /// flight uses them any more). Returns the bytes it held, if it was uploaded.
    pub fn remove_scan(&mut self, id: ScanId) -> Option<u64> {
        let removed = self.scans.remove(&id)?;
        self.generation += 1;
        Some(removed.bytes())
    }

    pub fn has_scan(&self, id: ScanId) -> bool {
        self.scans.contains_key(&id)
    }

    /// The GPU bytes of an uploaded scan (buffers and texture, exactly; with its
    /// point proxy once the `points` mode built it).
    pub fn scan_bytes(&self, id: ScanId) -> Option<u64> {
        self.scans.get(&id).map(PlacedScan::bytes)
    }

    /// The GPU bytes of every uploaded scan (what the residency budget holds).
    pub fn scans_bytes(&self) -> u64 {
        self.scans.values().map(PlacedScan::bytes).sum()
    }

    pub fn scan_count(&self) -> usize {
        self.scans.len()
    }

    pub fn scan_ids(&self) -> impl Iterator<Item = ScanId> + '_ {
        self.scans.keys().copied()
    }

    /// The scans to draw (ascending id) and the counts of those that are not.
    pub fn cull(
        &self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
    ) -> (Vec<ScanId>, FrameStats) {
        let mut stats = FrameStats {
            scans: self.scans.len(),
            ..Default::default()
        };
        let mut visible = Vec::new();
        for (&id, placed) in &self.scans {
            stats.scan_bytes += placed.bytes();
            let left_out = settings
                .only
                .as_ref()
                .is_some_and(|only| !only.contains(&id));
            if left_out || settings.hidden.contains(&id) {
                stats.hidden += 1;
                continue;
            }
            let Some(bounds) = placed.gpu.bounds else {
                // An empty scan has nothing to draw; it counts as outside the view.
                stats.culled_frustum += 1;
                continue;
            };
            match classify(
                &bounds,
                placed.gpu.cop_scan,
                &placed.world_from_scan,
                camera,
            ) {
                Visibility::Visible => visible.push(id),
                Visibility::OutsideFrustum => stats.culled_frustum += 1,
                Visibility::FacingAway => stats.culled_facing += 1,
            }
        }
        stats.drawn = visible.len();
        (visible, stats)
    }

    /// The frame uniform for a `format` target `width` pixels wide, and each visible
    /// scan's.
    fn write_uniforms(
        &self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
        format: wgpu::TextureFormat,
        width: u32,
        visible: &[ScanId],
    ) {
        let c = &settings.composite;
        let gamma = if settings.range_gamma.is_finite() && settings.range_gamma > 0.0 {
            settings.range_gamma
        } else {
            1.0
        };
        let bg = c.background;
        let frame = FrameUniform {
            clip_from_view: camera.clip_from_view(),
            background: Vec4::new(bg[0], bg[1], bg[2], 1.0),
            params: Vec4::new(
                c.effective_threshold(),
                gamma,
                if format.is_srgb() { 1.0 } else { 0.0 },
                if settings.fill_enclosed_holes {
                    1.0
                } else {
                    0.0
                },
            ),
            counts: UVec4::new(
                c.mode.code(),
                c.effective_k() as u32,
                visible.len() as u32,
                width,
            ),
        };
        self.queue
            .write_buffer(&self.frame_uniform, 0, bytemuck::bytes_of(&frame));
        let view_from_world = camera.view_from_world();
        for &id in visible {
            let Some(placed) = self.scans.get(&id) else {
                continue;
            };
            let uniform = placed.uniform(id, &view_from_world);
            self.queue
                .write_buffer(&placed.gpu.uniform, 0, bytemuck::bytes_of(&uniform));
        }
    }

    fn check_target(&self, width: u32, height: u32) -> Result<(), GpuError> {
        let limit = self.device.limits().max_texture_dimension_2d;
        if width == 0 || height == 0 || width > limit || height > limit {
            return Err(GpuError::TargetSize {
                width,
                height,
                limit,
            });
        }
        Ok(())
    }

    /// Drops the size-dependent targets (e.g. to measure one strategy alone).
    pub fn release_targets(&mut self) {
        self.generation += 1;
        self.depth = None;
        self.kbuffer = None;
        self.naive = None;
        if let Some(p) = self.points.as_mut() {
            p.release_targets();
        }
    }

    /// Records and submits one frame into `target`.
    pub fn render(
        &mut self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
        target: &RenderTarget<'_>,
    ) -> Result<FrameStats, GpuError> {
        let (width, height) = (target.width, target.height);
        self.check_target(width, height)?;
        // A progressive frame under way is stale: its uniforms are overwritten.
        self.generation += 1;
        let (visible, mut stats) = self.cull(camera, settings);
        self.write_uniforms(camera, settings, target.format, target.width, &visible);
        if settings.points {
            return self.render_points(camera, settings, target, &visible, stats);
        }
        let depth = match self.depth.take() {
            Some(d) if (d.width, d.height) == (width, height) => d,
            _ => DepthTarget::new(&self.device, width, height, self.pipelines.scan_depth),
        };
        let depth = &*self.depth.insert(depth);
        let depth_bytes = depth.bytes();
        let outputs = self
            .outputs
            .entry(target.format)
            .or_insert_with(|| OutputPipelines::new(&self.device, &self.pipelines, target.format));
        let frame = Frame {
            device: &self.device,
            queue: &self.queue,
            pipelines: &self.pipelines,
            outputs,
            frame_bind_group: &self.frame_bind_group,
            depth,
            scans: &self.scans,
            settings,
            target: *target,
        };
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("frame"),
            });
        // The painter is a mode of its own: it composites nothing, so it ignores the
        // strategy.
        let strategy = if settings.composite.mode == Mode::Painter {
            None
        } else {
            Some(settings.strategy)
        };
        self.nearest_ready = false;
        match strategy {
            None => {
                painter::encode(&frame, &mut encoder, &visible);
                stats.target_memory = TargetMemory {
                    depth: depth_bytes,
                    ..Default::default()
                };
            }
            Some(Strategy::KBuffer { batch }) => {
                let mut clock = self
                    .profile_phases
                    .then(|| PhaseClock::start(&frame, &mut encoder));
                let batch = batch.clamp(1, kbuffer::MAX_BATCH);
                let shape = KBufferShape {
                    width,
                    height,
                    k: settings.composite.effective_k() as u32,
                    batch,
                };
                let batches = visible.len().div_ceil(batch as usize) as u32;
                let targets = kbuffer::prepare(
                    &mut self.kbuffer,
                    &self.device,
                    &self.pipelines,
                    &self.frame_uniform,
                    shape,
                    batches,
                )?;
                targets.marked = self.merge_marks;
                let layered = layered(&self.scans, &visible, camera, self.layer_footprints);
                kbuffer::encode(
                    &frame,
                    &mut encoder,
                    targets,
                    &visible,
                    &layered,
                    clock.as_mut(),
                );
                self.nearest_ready = true;
                stats.phase_ms = clock.map(|c| c.phase_ms());
                stats.target_memory = targets.memory(depth_bytes);
            }
            Some(Strategy::NaiveLayers) => {
                let targets = naive_layers::prepare(
                    &mut self.naive,
                    &self.device,
                    &self.pipelines,
                    &self.frame_uniform,
                    (width, height),
                    visible.len() as u32,
                )?;
                naive_layers::encode(&frame, &mut encoder, targets, &visible);
                stats.target_memory = targets.memory(depth_bytes);
            }
        }
        crate::gpu::submit(&self.queue, Some(encoder.finish()));
        Ok(stats)
    }

    /// The last frame's nearest valid scan fragment per pixel (distance from the eye
    /// and its range sigma, `NEAREST_FORMAT`, the target's size), for drawing other
    /// geometry over the scans with their depth (the level-of-detail tiles). `None`
    /// unless the last frame went through the k-buffer (the painter and the naive
    /// layers keep no such target).
    pub fn scan_nearest(&self) -> Option<&wgpu::TextureView> {
        if !self.nearest_ready {
            return None;
        }
        self.kbuffer.as_ref().map(|t| t.nearest_view())
    }

    /// Waits for the GPU to finish.
    pub fn wait_idle(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Readback(e.to_string()))
    }

    pub fn max_k() -> u32 {
        MAX_K
    }
}

/// The visible scans that reach the k-buffer's layers, each with the pixels it can
/// draw (those that draw none are left out), in the order the batches take them; with
/// `footprints` off, all of them over the whole target, by id.
fn layered(
    scans: &BTreeMap<ScanId, PlacedScan>,
    visible: &[ScanId],
    camera: &VirtualCamera,
    footprints: bool,
) -> Vec<kbuffer::Layered> {
    if !footprints {
        return visible
            .iter()
            .map(|&id| kbuffer::Layered { id, rect: None })
            .collect();
    }
    let view_from_world = camera.view_from_world();
    let mut layered: Vec<kbuffer::Layered> = visible
        .iter()
        .filter_map(|&id| {
            let placed = scans.get(&id)?;
            let view_from_scan = pose_relative(&view_from_world, &placed.world_from_scan);
            let rect = placed.gpu.footprint.screen_rect(&view_from_scan, camera)?;
            Some(kbuffer::Layered {
                id,
                rect: Some(rect),
            })
        })
        .collect();
    kbuffer::order_on_screen(&mut layered);
    layered
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::scan_data::{VERTEX_ATTRIBUTES, Vertex};
    use crate::gpu::shaders;

    /// The size in bytes of struct `name` as WGSL lays it out in module `own`.
    fn wgsl_size(own: &str, name: &str) -> u32 {
        let module = naga::front::wgsl::parse_str(&shaders::source(own)).unwrap();
        module
            .types
            .iter()
            .find_map(|(_, ty)| match &ty.inner {
                naga::TypeInner::Struct { span, .. } if ty.name.as_deref() == Some(name) => {
                    Some(*span)
                }
                _ => None,
            })
            .unwrap()
    }

    /// The glam-typed uniforms and vertex keep the shaders' layouts (Pod already rules
    /// out padding; this rules out a size the WGSL does not declare).
    #[test]
    fn uniforms_and_vertices_match_the_shaders() {
        let size = |bytes: usize| u32::try_from(bytes).unwrap();
        assert_eq!(
            size(std::mem::size_of::<FrameUniform>()),
            wgsl_size(shaders::SCAN, "Frame")
        );
        assert_eq!(
            size(std::mem::size_of::<ScanUniform>()),
            wgsl_size(shaders::SCAN, "Scan")
        );
        let last = VERTEX_ATTRIBUTES[VERTEX_ATTRIBUTES.len() - 1];
        assert_eq!(
            last.offset + last.format.size(),
            std::mem::size_of::<Vertex>() as u64
        );
    }
}
