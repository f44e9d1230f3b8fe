//! The VDTM pass: a long-lived pipeline (one per target format) that draws the
//! prepared model into a given colour and depth target the way the tile and scan
//! passes do (reverse z, display colours through `to_target`, positions relative to
//! a nearby origin composed in f64), and a one-call headless render.

use std::collections::HashMap;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec4};

use super::gpu::{GpuVdtm, VDTM_VERTEX_ATTRIBUTES, VdtmVertex};
use super::prepare::PreparedVdtm;
use crate::camera::VirtualCamera;
use crate::gpu::{GpuContext, GpuError, gpu_from_pose_relative, shaders, surface_pipeline};
use crate::tiles::image_target::ImageTarget;
use crate::tiles::pass::{PassTarget, SurfaceFrameUniform, uniform_buffer};

/// The switches beyond the paper (its §9) and the background.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VdtmSettings {
    /// Lower the weight of a view that saw the surface coarser than the frame needs
    /// (the footprint ratio, after Buehler et al. 2001).
    pub resolution_term: bool,
    /// Fade each view's weight to 0 over this many pixels at its image's border
    /// (0: off).
    pub feather_px: f32,
}

impl Default for VdtmSettings {
    /// The paper's method as published.
    fn default() -> Self {
        Self {
            resolution_term: false,
            feather_px: 0.0,
        }
    }
}

impl VdtmSettings {
    /// The width feathering uses when switched on, pixels.
    pub const FEATHER_PX: f32 = 24.0;

    /// Both switches on.
    pub fn improved() -> Self {
        Self {
            resolution_term: true,
            feather_px: Self::FEATHER_PX,
        }
    }

    /// A short name: `vdtm`, `vdtm+res`, `vdtm+feather`, `vdtm+res+feather`.
    pub fn label(&self) -> String {
        let mut l = String::from("vdtm");
        if self.resolution_term {
            l.push_str("+res");
        }
        if self.feather_px > 0.0 {
            l.push_str("+feather");
        }
        l
    }
}

/// `VdtmFrame` in `vdtm.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct VdtmFrameUniform {
    view_from_model: Mat4,
    eye_model: Vec4,
    params: Vec4,
}

fn layout_entry(binding: u32, ty: wgpu::BindingType) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT,
        ty,
        count: None,
    }
}

/// The VDTM pipelines and per-frame uniforms.
pub struct VdtmPass {
    device: wgpu::Device,
    queue: wgpu::Queue,
    module: wgpu::ShaderModule,
    layout: wgpu::BindGroupLayout,
    pipeline_layout: wgpu::PipelineLayout,
    pipelines: HashMap<wgpu::TextureFormat, wgpu::RenderPipeline>,
    frame_uniform: wgpu::Buffer,
    vdtm_uniform: wgpu::Buffer,
    sampler: wgpu::Sampler,
}

impl VdtmPass {
    pub fn new(gpu: &GpuContext) -> Self {
        let device = gpu.device.clone();
        let storage = wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only: true },
            has_dynamic_offset: false,
            min_binding_size: None,
        };
        let uniform = wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("vdtm"),
            entries: &[
                layout_entry(0, uniform),
                layout_entry(1, uniform),
                layout_entry(2, storage),
                layout_entry(3, storage),
                layout_entry(
                    4,
                    wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2Array,
                        multisampled: false,
                    },
                ),
                layout_entry(
                    5,
                    wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                ),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("vdtm"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("vdtm.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::source(shaders::VDTM).into()),
        });
        let frame_uniform = uniform_buffer(
            &device,
            "vdtm frame uniform",
            std::mem::size_of::<SurfaceFrameUniform>() as u64,
        );
        let vdtm_uniform = uniform_buffer(
            &device,
            "vdtm uniform",
            std::mem::size_of::<VdtmFrameUniform>() as u64,
        );
        // Bilinear, clamped at the border: a polygon wholly seen by a view projects
        // inside its image, the clamp only catches rounding at the edge.
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("vdtm images"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        Self {
            device,
            queue: gpu.queue.clone(),
            module,
            layout,
            pipeline_layout,
            pipelines: HashMap::new(),
            frame_uniform,
            vdtm_uniform,
            sampler,
        }
    }

    fn pipeline(&mut self, format: wgpu::TextureFormat) -> &wgpu::RenderPipeline {
        let (device, layout, module) = (&self.device, &self.pipeline_layout, &self.module);
        self.pipelines.entry(format).or_insert_with(|| {
            surface_pipeline(
                device,
                "vdtm",
                layout,
                module,
                ("vs_vdtm", "fs_vdtm"),
                wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<VdtmVertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &VDTM_VERTEX_ATTRIBUTES,
                },
                format,
            )
        })
    }

    /// Records the pass: the blends for this eye (§8), then holes first and the
    /// textured polygons after, into `target` (its `scans` is not read). The uniforms
    /// are written now: one pass per submission.
    pub fn encode(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        target: &PassTarget<'_>,
        camera: &VirtualCamera,
        settings: &VdtmSettings,
        prepared: &PreparedVdtm,
        model: &mut GpuVdtm,
    ) {
        let eye = camera.centre_world();
        model.update_blends(&self.queue, prepared, &eye);
        let colour = &target.colour;
        let frame = SurfaceFrameUniform::new(camera, colour, target.clear.unwrap_or([0.0; 3]));
        let view_from_world = camera.view_from_world();
        let eye_model = eye - model.world_from_model.translation.vector;
        let feather_px = if settings.feather_px.is_finite() {
            settings.feather_px.max(0.0)
        } else {
            0.0
        };
        let uniform = VdtmFrameUniform {
            view_from_model: gpu_from_pose_relative(&view_from_world, &model.world_from_model),
            eye_model: Vec4::new(
                eye_model.x as f32,
                eye_model.y as f32,
                eye_model.z as f32,
                1.0,
            ),
            params: Vec4::new(
                camera.focal_px() as f32,
                feather_px,
                if settings.resolution_term { 1.0 } else { 0.0 },
                0.0,
            ),
        };
        self.queue
            .write_buffer(&self.frame_uniform, 0, bytemuck::bytes_of(&frame));
        self.queue
            .write_buffer(&self.vdtm_uniform, 0, bytemuck::bytes_of(&uniform));
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("vdtm"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: self.frame_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: self.vdtm_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: model.views.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: model.blends.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: wgpu::BindingResource::TextureView(&model.images),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: wgpu::BindingResource::Sampler(&self.sampler),
                },
            ],
        });
        let clear = target.clear;
        let format = colour.format;
        let pipeline = self.pipeline(format).clone();
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("vdtm"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: colour.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: clear.map_or(wgpu::LoadOp::Load, |c| {
                        wgpu::LoadOp::Clear(crate::tiles::pass::clear_colour(c, format))
                    }),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: target.depth,
                depth_ops: Some(wgpu::Operations {
                    load: if clear.is_some() {
                        wgpu::LoadOp::Clear(0.0)
                    } else {
                        wgpu::LoadOp::Load
                    },
                    store: wgpu::StoreOp::Store,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.set_vertex_buffer(0, model.vertices.slice(..));
        // §8: the hole-filled polygons first, then the textured ones.
        let holes_end = model.holes.saturating_mul(3).min(model.vertex_count());
        if holes_end > 0 {
            pass.draw(0..holes_end, 0..1);
        }
        pass.draw(holes_end..model.vertex_count(), 0..1);
    }
}

/// Renders the prepared model from `camera` into a new image (headless).
pub fn render_vdtm_to_image(
    gpu: &GpuContext,
    pass: &mut VdtmPass,
    prepared: &PreparedVdtm,
    model: &mut GpuVdtm,
    camera: &VirtualCamera,
    settings: &VdtmSettings,
    background: [f32; 3],
) -> Result<image::RgbaImage, GpuError> {
    let target = ImageTarget::new(gpu, camera.width, camera.height)?;
    let mut encoder = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("vdtm"),
        });
    pass.encode(
        &mut encoder,
        &PassTarget {
            colour: target.target(),
            depth: target.depth_view(),
            clear: Some(background),
            scans: None,
        },
        camera,
        settings,
        prepared,
        model,
    );
    crate::gpu::submit(&gpu.queue, Some(encoder.finish()));
    target.read(gpu)
}
