//! The renderer: holds the long-lived pipelines and each scan's GPU data, takes the
//! model's scans and poses as they arrive, and records a frame for a virtual camera
//! into a given target. Per frame only uniforms are written; scan data is uploaded
//! once.

use std::collections::{BTreeMap, BTreeSet};

use bytemuck::{Pod, Zeroable};
use nalgebra::Point3;
use texel::Pose;
use texel::model::{Model, ScanId};

use super::pipelines::Pipelines;
use super::scan_data::{GpuScan, ScanUniform};
use super::targets::{DepthTarget, KBufferTargets, NaiveTargets, TargetMemory};
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
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            composite: CompositeSettings::default(),
            range_gamma: 1.0,
            keep_stretched: false,
            strategy: Strategy::default(),
            hidden: BTreeSet::new(),
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

/// The k-buffer's phases, for profiling.
#[derive(Debug, Clone, Copy)]
enum Phase {
    Prepass = 0,
    Layers = 1,
    Merge = 2,
    Composite = 3,
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
struct FrameUniform {
    clip_from_view: [[f32; 4]; 4],
    background: [f32; 4],
    params: [f32; 4],
    counts: [u32; 4],
}

struct PlacedScan {
    gpu: GpuScan,
    world_from_scan: Pose,
}

pub struct Renderer {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pub(crate) pipelines: Pipelines,
    scans: BTreeMap<ScanId, PlacedScan>,
    pub(crate) frame_uniform: wgpu::Buffer,
    frame_bind_group: wgpu::BindGroup,
    depth: Option<DepthTarget>,
    kbuffer: Option<KBufferTargets>,
    pub(crate) naive: Option<NaiveTargets>,
    /// Submit and wait after each k-buffer phase and time it (slower; for `bench`).
    pub profile_phases: bool,
    phase_clock: std::cell::Cell<Option<(std::time::Instant, [f64; 4])>>,
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
            scans: BTreeMap::new(),
            frame_uniform,
            frame_bind_group,
            depth: None,
            kbuffer: None,
            naive: None,
            profile_phases: false,
            phase_clock: std::cell::Cell::new(None),
        }
    }

    /// When profiling, ends `phase`: submits what is encoded, waits for the GPU and
    /// books the time since the previous checkpoint to `phase`.
    fn checkpoint(&self, encoder: &mut wgpu::CommandEncoder, phase: Phase) {
        let Some((since, mut phases)) = self.phase_clock.get() else {
            return;
        };
        let done = std::mem::replace(
            encoder,
            self.device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("profiled frame"),
                }),
        );
        self.queue.submit(Some(done.finish()));
        let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
        let now = std::time::Instant::now();
        phases[phase as usize] += now.duration_since(since).as_secs_f64() * 1e3;
        self.phase_clock.set(Some((now, phases)));
    }

    /// Uploads a scan once; adding an id again only moves it.
    pub fn add_scan(
        &mut self,
        id: ScanId,
        scan: &texel::TexelScan,
        world_from_scan: Pose,
    ) -> Result<(), GpuError> {
        if let Some(placed) = self.scans.get_mut(&id) {
            placed.world_from_scan = world_from_scan;
            return Ok(());
        }
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
            },
        );
        Ok(())
    }

    /// A revised pose: only the scan's uniform changes (at the next frame).
    pub fn set_pose(&mut self, id: ScanId, world_from_scan: Pose) -> bool {
        match self.scans.get_mut(&id) {
            Some(p) => {
                p.world_from_scan = world_from_scan;
                true
            }
            None => false,
        }
    }

    /// Brings the GPU copy up to date with a model: uploads scans not seen yet and
    /// takes every current pose.
    pub fn sync_model(&mut self, model: &Model) -> Result<(), GpuError> {
        for s in model.scans() {
            self.add_scan(s.id, &s.scan, s.world_from_scan)?;
        }
        Ok(())
    }

    /// Forgets every scan (the source reset its model; ids will be reused).
    pub fn clear_scans(&mut self) {
        self.scans.clear();
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
            stats.scan_bytes += placed.gpu.bytes;
            if settings.hidden.contains(&id) {
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

    fn write_uniforms(
        &self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
        target: &RenderTarget<'_>,
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
            background: [bg[0], bg[1], bg[2], 1.0],
            params: [
                c.effective_threshold(),
                gamma,
                if target.format.is_srgb() { 1.0 } else { 0.0 },
                0.0,
            ],
            counts: [
                c.mode.code(),
                c.effective_k() as u32,
                visible.len() as u32,
                target.width,
            ],
        };
        self.queue
            .write_buffer(&self.frame_uniform, 0, bytemuck::bytes_of(&frame));
        let view_from_world = camera.view_from_world();
        for id in visible {
            let Some(placed) = self.scans.get(id) else {
                continue;
            };
            // f64 until here: the GPU sees the scan relative to the camera only.
            let view_from_scan = view_from_world * placed.world_from_scan;
            let m = view_from_scan.to_homogeneous();
            let mut cols = [[0.0f32; 4]; 4];
            for (c, col) in cols.iter_mut().enumerate() {
                for (r, v) in col.iter_mut().enumerate() {
                    *v = m[(r, c)] as f32;
                }
            }
            let cop = view_from_scan * Point3::from(placed.gpu.cop_scan);
            let uniform = ScanUniform {
                view_from_scan: cols,
                cop_view: [cop.x as f32, cop.y as f32, cop.z as f32, 1.0],
                noise: [
                    placed.gpu.noise.sigma_m.max(0.0) as f32,
                    placed.gpu.noise.sigma_per_m.max(0.0) as f32,
                    0.0,
                    0.0,
                ],
                ids: [u32::try_from(*id).unwrap_or(u32::MAX), 0, 0, 0],
            };
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

    fn ensure_depth(&mut self, width: u32, height: u32) -> u64 {
        if self
            .depth
            .as_ref()
            .is_none_or(|d| (d.width, d.height) != (width, height))
        {
            self.depth = Some(DepthTarget::new(&self.device, width, height));
        }
        self.depth.as_ref().map_or(0, DepthTarget::bytes)
    }

    fn ensure_kbuffer(
        &mut self,
        width: u32,
        height: u32,
        k: u32,
        batch: u32,
        batches: u32,
    ) -> Result<(), GpuError> {
        let bytes = KBufferTargets::kbuffer_bytes(width, height, k);
        let limits = self.device.limits();
        let limit = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        if bytes > limit {
            return Err(GpuError::TooLarge {
                what: "the k-buffer",
                bytes,
                limit,
            });
        }
        if batch > limits.max_texture_array_layers {
            return Err(GpuError::TooManyLayers {
                visible: batch as usize,
                limit: limits.max_texture_array_layers,
            });
        }
        let fits = self.kbuffer.as_ref().is_some_and(|t| {
            (t.width, t.height, t.k, t.batch) == (width, height, k, batch)
                && t.batch_slots >= batches
        });
        if !fits {
            let slots = batches.max(self.kbuffer.as_ref().map_or(1, |t| t.batch_slots));
            self.kbuffer = Some(KBufferTargets::new(
                &self.device,
                &self.pipelines.merge_layout,
                &self.pipelines.kbuffer_layout,
                &self.frame_uniform,
                width,
                height,
                k,
                batch,
                slots,
            ));
        }
        Ok(())
    }

    fn ensure_naive(&mut self, width: u32, height: u32, layers: u32) -> Result<(), GpuError> {
        let limit = self.device.limits().max_texture_array_layers;
        if layers > limit {
            return Err(GpuError::TooManyLayers {
                visible: layers as usize,
                limit,
            });
        }
        let fits = self.naive.as_ref().is_some_and(|t| {
            (t.width, t.height) == (width, height) && t.layers.count == layers.max(1)
        });
        if !fits {
            self.naive = Some(NaiveTargets::new(
                &self.device,
                &self.pipelines.naive_layout,
                &self.frame_uniform,
                width,
                height,
                layers,
            ));
        }
        Ok(())
    }

    /// Drops the size-dependent targets (e.g. to measure one strategy alone).
    pub fn release_targets(&mut self) {
        self.depth = None;
        self.kbuffer = None;
        self.naive = None;
    }

    /// Records and submits one frame into `target`.
    pub fn render(
        &mut self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
        target: &RenderTarget<'_>,
    ) -> Result<FrameStats, GpuError> {
        self.check_target(target.width, target.height)?;
        let (visible, mut stats) = self.cull(camera, settings);
        self.write_uniforms(camera, settings, target, &visible);
        let depth_bytes = self.ensure_depth(target.width, target.height);
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("frame"),
            });
        let strategy = if settings.composite.mode == Mode::Painter {
            None
        } else {
            Some(settings.strategy)
        };
        match strategy {
            None => {
                self.encode_painter(&mut encoder, settings, target, &visible);
                stats.target_memory = TargetMemory {
                    depth: depth_bytes,
                    ..Default::default()
                };
            }
            Some(Strategy::KBuffer { batch }) => {
                if self.profile_phases {
                    self.queue.submit(Some(
                        std::mem::replace(
                            &mut encoder,
                            self.device
                                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                                    label: Some("profiled frame"),
                                }),
                        )
                        .finish(),
                    ));
                    let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
                    self.phase_clock
                        .set(Some((std::time::Instant::now(), [0.0; 4])));
                }
                let batch = batch.clamp(1, 64);
                let batches = visible.len().div_ceil(batch as usize) as u32;
                let k = settings.composite.effective_k() as u32;
                self.ensure_kbuffer(target.width, target.height, k, batch, batches)?;
                self.encode_kbuffer(&mut encoder, settings, target, &visible)?;
                stats.phase_ms = self.phase_clock.take().map(|(_, p)| p);
                stats.target_memory = self
                    .kbuffer
                    .as_ref()
                    .map(|t| t.memory(depth_bytes))
                    .unwrap_or_default();
            }
            Some(Strategy::NaiveLayers) => {
                self.ensure_naive(target.width, target.height, visible.len() as u32)?;
                self.encode_naive(&mut encoder, settings, target, &visible);
                stats.target_memory = self
                    .naive
                    .as_ref()
                    .map(|t| t.memory(depth_bytes))
                    .unwrap_or_default();
            }
        }
        self.queue.submit(Some(encoder.finish()));
        Ok(stats)
    }

    fn depth_attachment(&self) -> Option<wgpu::RenderPassDepthStencilAttachment<'_>> {
        self.depth
            .as_ref()
            .map(|d| wgpu::RenderPassDepthStencilAttachment {
                view: &d.depth.view,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(0.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            })
    }

    fn draw_scans(
        &self,
        pass: &mut wgpu::RenderPass<'_>,
        settings: &RenderSettings,
        ids: &[ScanId],
    ) {
        pass.set_bind_group(0, &self.frame_bind_group, &[]);
        for id in ids {
            let Some(placed) = self.scans.get(id) else {
                continue;
            };
            let (indices, count) = placed.gpu.indices(settings.keep_stretched);
            if count == 0 {
                continue;
            }
            pass.set_bind_group(1, &placed.gpu.bind_group, &[]);
            pass.set_vertex_buffer(0, placed.gpu.vertices.slice(..));
            pass.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
            pass.draw_indexed(0..count, 0, 0..1);
        }
    }

    fn clear_colour(settings: &RenderSettings, format: wgpu::TextureFormat) -> wgpu::Color {
        let bg = settings.composite.background.map(|c| {
            let c = f64::from(c.clamp(0.0, 1.0));
            if format.is_srgb() {
                // Display values: the target encodes linear ones.
                if c <= 0.04045 {
                    c / 12.92
                } else {
                    ((c + 0.055) / 1.055).powf(2.4)
                }
            } else {
                c
            }
        });
        wgpu::Color {
            r: bg[0],
            g: bg[1],
            b: bg[2],
            a: 1.0,
        }
    }

    fn encode_painter(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        settings: &RenderSettings,
        target: &RenderTarget<'_>,
        visible: &[ScanId],
    ) {
        self.pipelines.ensure_output(&self.device, target.format);
        let Some(outputs) = self.pipelines.outputs_for(target.format) else {
            return;
        };
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("painter"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(Self::clear_colour(settings, target.format)),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: self.depth_attachment(),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&outputs.painter);
        self.draw_scans(&mut pass, settings, visible);
    }

    /// One scan into one layer (colour + data), its own depth test.
    fn encode_layer(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        settings: &RenderSettings,
        colour: &wgpu::TextureView,
        data: &wgpu::TextureView,
        id: ScanId,
    ) {
        let clear = |view| {
            Some(wgpu::RenderPassColorAttachment {
                view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                    store: wgpu::StoreOp::Store,
                },
            })
        };
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("scan layer"),
            color_attachments: &[clear(colour), clear(data)],
            depth_stencil_attachment: self.depth_attachment(),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipelines.layer);
        self.draw_scans(&mut pass, settings, &[id]);
    }

    fn encode_kbuffer(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        settings: &RenderSettings,
        target: &RenderTarget<'_>,
        visible: &[ScanId],
    ) -> Result<(), GpuError> {
        self.pipelines.ensure_output(&self.device, target.format);
        let Some(t) = self.kbuffer.as_ref() else {
            return Ok(());
        };
        // 1. Pre-pass: the nearest valid fragment's distance and sigma per pixel.
        {
            let infinity = f64::from(f32::INFINITY.to_bits());
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("pre-pass"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &t.nearest.view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color {
                            r: infinity,
                            g: 0.0,
                            b: 0.0,
                            a: 0.0,
                        }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: self.depth_attachment(),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.pipelines.prepass);
            self.draw_scans(&mut pass, settings, visible);
        }
        self.checkpoint(encoder, Phase::Prepass);
        // 2. Scans a batch at a time into the layers, each batch merged into the k-buffer.
        encoder.clear_buffer(&t.kbuffer, 0, None);
        for (b, chunk) in visible.chunks(t.batch as usize).enumerate() {
            let slot = u64::from(KBufferTargets::slot_offset(b as u32));
            self.queue.write_buffer(
                &t.batch_uniform,
                slot,
                bytemuck::bytes_of(&[chunk.len() as u32, 0, 0, 0]),
            );
            for (l, &id) in chunk.iter().enumerate() {
                self.encode_layer(
                    encoder,
                    settings,
                    &t.layers.colour_layers[l],
                    &t.layers.data_layers[l],
                    id,
                );
            }
            self.checkpoint(encoder, Phase::Layers);
            // The pass needs an attachment: the depth buffer, neither tested nor written.
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("merge"),
                color_attachments: &[],
                depth_stencil_attachment: self.depth_attachment(),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.pipelines.merge);
            pass.set_bind_group(
                0,
                &t.merge_bind_group,
                &[KBufferTargets::slot_offset(b as u32)],
            );
            pass.draw(0..3, 0..1);
            drop(pass);
            self.checkpoint(encoder, Phase::Merge);
        }
        // 3. Composite into the target.
        let Some(outputs) = self.pipelines.outputs_for(target.format) else {
            return Ok(());
        };
        Self::encode_fullscreen(
            encoder,
            target,
            &outputs.composite_kbuffer,
            &t.composite_bind_group,
            Self::clear_colour(settings, target.format),
        );
        self.checkpoint(encoder, Phase::Composite);
        Ok(())
    }

    fn encode_naive(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        settings: &RenderSettings,
        target: &RenderTarget<'_>,
        visible: &[ScanId],
    ) {
        self.pipelines.ensure_output(&self.device, target.format);
        let Some(t) = self.naive.as_ref() else {
            return;
        };
        if visible.is_empty() {
            // Layer 0 must not hold stale fragments: the composite reads 0 layers
            // anyway, but keep the stack clean for read-back.
            self.encode_clear_layer(
                encoder,
                &t.layers.colour_layers[0],
                &t.layers.data_layers[0],
            );
        }
        for (l, &id) in visible.iter().enumerate() {
            self.encode_layer(
                encoder,
                settings,
                &t.layers.colour_layers[l],
                &t.layers.data_layers[l],
                id,
            );
        }
        let Some(outputs) = self.pipelines.outputs_for(target.format) else {
            return;
        };
        Self::encode_fullscreen(
            encoder,
            target,
            &outputs.composite_naive,
            &t.composite_bind_group,
            Self::clear_colour(settings, target.format),
        );
    }

    fn encode_clear_layer(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        colour: &wgpu::TextureView,
        data: &wgpu::TextureView,
    ) {
        let clear = |view| {
            Some(wgpu::RenderPassColorAttachment {
                view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                    store: wgpu::StoreOp::Store,
                },
            })
        };
        encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("clear layer"),
            color_attachments: &[clear(colour), clear(data)],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
    }

    fn encode_fullscreen(
        encoder: &mut wgpu::CommandEncoder,
        target: &RenderTarget<'_>,
        pipeline: &wgpu::RenderPipeline,
        bind_group: &wgpu::BindGroup,
        clear: wgpu::Color,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("composite"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(clear),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        pass.draw(0..3, 0..1);
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
