//! The tone-mapping pass: long-lived pipelines (the two auto-exposure reductions and
//! one full-screen draw per target format) that turn a radiance texture
//! ([`RADIANCE_FORMAT`]) into display values in a given target, with
//! [`crate::tonemap`]'s settings; and the upload of a radiance image into such a
//! texture. `tonemap.rs` is the CPU reference it is tested against.

use std::collections::HashMap;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec4};

use super::pipelines::fullscreen_pipeline;
use super::renderer::FrameUniform;
use super::targets::colour_pass;
use super::{GpuContext, GpuError, shaders};
use crate::tonemap::{LOG_AVERAGE_EPSILON, ToneMapSettings};

/// Radiance on the GPU: half floats, which every backend (lavapipe included) samples
/// and renders. Values beyond its range (65504) are stored as its largest.
pub const RADIANCE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;

/// The largest value [`RADIANCE_FORMAT`] holds.
pub const RADIANCE_MAX: f32 = 65504.0;

const TILE: u32 = 16;

/// `ToneMap` in `tonemap.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct ToneUniform {
    params: Vec4,
    adapt: Vec4,
    size: UVec4,
}

fn entry(
    binding: u32,
    visibility: wgpu::ShaderStages,
    ty: wgpu::BindingType,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty,
        count: None,
    }
}

fn buffer_binding(ty: wgpu::BufferBindingType) -> wgpu::BindingType {
    wgpu::BindingType::Buffer {
        ty,
        has_dynamic_offset: false,
        min_binding_size: None,
    }
}

const RADIANCE_BINDING: wgpu::BindingType = wgpu::BindingType::Texture {
    sample_type: wgpu::TextureSampleType::Float { filterable: false },
    view_dimension: wgpu::TextureViewDimension::D2,
    multisampled: false,
};

/// The pipelines, uniforms and the adaptation buffer of the tone-mapping pass.
pub struct ToneMapPass {
    device: wgpu::Device,
    queue: wgpu::Queue,
    module: wgpu::ShaderModule,
    compute_layout: wgpu::BindGroupLayout,
    draw_layout: wgpu::BindGroupLayout,
    draw_pipeline_layout: wgpu::PipelineLayout,
    partial_pipeline: wgpu::ComputePipeline,
    final_pipeline: wgpu::ComputePipeline,
    draw_pipelines: HashMap<wgpu::TextureFormat, wgpu::RenderPipeline>,
    frame_uniform: wgpu::Buffer,
    tone_uniform: wgpu::Buffer,
    adaptation: wgpu::Buffer,
    /// Per 16 x 16 tile sums; grown to the largest image seen.
    partials: wgpu::Buffer,
    partial_tiles: u64,
    /// Display colour of the pixels no surface covers (radiance alpha 0); they do not
    /// count towards auto-exposure either.
    pub background: [f32; 3],
}

impl ToneMapPass {
    pub fn new(gpu: &GpuContext) -> Self {
        Self::with_device(&gpu.device, &gpu.queue)
    }

    /// The pass on a device and queue already held (the renderer's).
    pub fn with_device(device: &wgpu::Device, queue: &wgpu::Queue) -> Self {
        let device = device.clone();
        let queue = queue.clone();
        let compute = wgpu::ShaderStages::COMPUTE;
        let fragment = wgpu::ShaderStages::FRAGMENT;
        let uniform = buffer_binding(wgpu::BufferBindingType::Uniform);
        let read_write = buffer_binding(wgpu::BufferBindingType::Storage { read_only: false });
        let read_only = buffer_binding(wgpu::BufferBindingType::Storage { read_only: true });
        let compute_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tonemap reduce"),
            entries: &[
                entry(1, compute, uniform),
                entry(2, compute, RADIANCE_BINDING),
                entry(3, compute, read_write),
                entry(4, compute, read_write),
            ],
        });
        let draw_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tonemap draw"),
            entries: &[
                entry(0, fragment, uniform),
                entry(1, fragment, uniform),
                entry(2, fragment, RADIANCE_BINDING),
                entry(5, fragment, read_only),
            ],
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("tonemap.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::source(shaders::TONEMAP).into()),
        });
        let compute_pipeline_layout =
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("tonemap reduce"),
                bind_group_layouts: &[Some(&compute_layout)],
                immediate_size: 0,
            });
        let compute_pipeline = |entry_point: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry_point),
                layout: Some(&compute_pipeline_layout),
                module: &module,
                entry_point: Some(entry_point),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let partial_pipeline = compute_pipeline("cs_partial");
        let final_pipeline = compute_pipeline("cs_final");
        let draw_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("tonemap draw"),
            bind_group_layouts: &[Some(&draw_layout)],
            immediate_size: 0,
        });
        let buffer = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        let uniform_usage = wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST;
        let storage_usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let frame_uniform = buffer(
            "tonemap frame",
            std::mem::size_of::<FrameUniform>() as u64,
            uniform_usage,
        );
        let tone_uniform = buffer(
            "tonemap settings",
            std::mem::size_of::<ToneUniform>() as u64,
            uniform_usage,
        );
        let adaptation = buffer("tonemap adaptation", 16, storage_usage);
        let partials = buffer("tonemap partials", 8, storage_usage);
        Self {
            queue,
            background: [0.0; 3],
            module,
            compute_layout,
            draw_layout,
            draw_pipeline_layout,
            partial_pipeline,
            final_pipeline,
            draw_pipelines: HashMap::new(),
            frame_uniform,
            tone_uniform,
            adaptation,
            partials,
            partial_tiles: 1,
            device,
        }
    }

    fn draw_pipeline(&mut self, format: wgpu::TextureFormat) -> &wgpu::RenderPipeline {
        let (device, module, layout) = (&self.device, &self.module, &self.draw_pipeline_layout);
        self.draw_pipelines.entry(format).or_insert_with(|| {
            fullscreen_pipeline(device, layout, module, "tonemap", "fs_tonemap", format)
        })
    }

    /// The buffer `cs_final` writes the adaptation level into (for read-back).
    pub fn adaptation_buffer(&self) -> &wgpu::Buffer {
        &self.adaptation
    }

    /// Records the pass: the auto-exposure reductions (when the settings ask for
    /// them), then the full-screen draw of `radiance` (of `size`) into `target`, which
    /// must be the same size.
    pub fn record(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        radiance: &wgpu::TextureView,
        size: (u32, u32),
        settings: &ToneMapSettings,
        target: &wgpu::TextureView,
        target_format: wgpu::TextureFormat,
    ) {
        let (width, height) = size;
        let tiles_x = width.div_ceil(TILE).max(1);
        let tiles_y = height.div_ceil(TILE).max(1);
        let tiles = u64::from(tiles_x) * u64::from(tiles_y);
        if tiles > self.partial_tiles {
            self.partials = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("tonemap partials"),
                size: tiles * 8,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            });
            self.partial_tiles = tiles;
        }
        // Of `Frame`, only the background and `params.z` (1 for an sRGB target) are
        // read here.
        let frame = FrameUniform {
            clip_from_view: Mat4::IDENTITY,
            background: Vec4::new(
                self.background[0],
                self.background[1],
                self.background[2],
                1.0,
            ),
            params: Vec4::new(
                0.0,
                0.0,
                if target_format.is_srgb() { 1.0 } else { 0.0 },
                0.0,
            ),
            counts: UVec4::ZERO,
        };
        let auto = settings.adaptation.is_none();
        let tone = ToneUniform {
            params: Vec4::new(
                settings.operator.code() as f32,
                settings.key,
                settings.exposure_ev.exp2(),
                1.0 / settings.gamma,
            ),
            adapt: Vec4::new(
                if auto { 1.0 } else { 0.0 },
                settings.adaptation.unwrap_or(1.0),
                LOG_AVERAGE_EPSILON,
                0.0,
            ),
            size: UVec4::new(width, height, tiles as u32, 0),
        };
        self.queue
            .write_buffer(&self.frame_uniform, 0, bytemuck::bytes_of(&frame));
        self.queue
            .write_buffer(&self.tone_uniform, 0, bytemuck::bytes_of(&tone));
        if auto {
            let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("tonemap reduce"),
                layout: &self.compute_layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: self.tone_uniform.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: wgpu::BindingResource::TextureView(radiance),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: self.partials.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: self.adaptation.as_entire_binding(),
                    },
                ],
            });
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tonemap reduce"),
                timestamp_writes: None,
            });
            pass.set_bind_group(0, &bind_group, &[]);
            pass.set_pipeline(&self.partial_pipeline);
            pass.dispatch_workgroups(tiles_x, tiles_y, 1);
            pass.set_pipeline(&self.final_pipeline);
            pass.dispatch_workgroups(1, 1, 1);
        }
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tonemap draw"),
            layout: &self.draw_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: self.frame_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: self.tone_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::TextureView(radiance),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: self.adaptation.as_entire_binding(),
                },
            ],
        });
        let pipeline = self.draw_pipeline(target_format).clone();
        let mut pass = colour_pass(encoder, "tonemap", target, wgpu::Color::BLACK);
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.draw(0..3, 0..1);
    }
}

/// A radiance value as the half float a `RADIANCE_FORMAT` texel holds: non-finite and
/// negative values as 0, values beyond [`RADIANCE_MAX`] as it.
pub(crate) fn half_radiance(v: f32) -> u16 {
    let v = if v.is_finite() {
        v.clamp(0.0, RADIANCE_MAX)
    } else {
        0.0
    };
    half::f16::from_f32(v).to_bits()
}

/// A sampled `RADIANCE_FORMAT` texture holding `texels` (RGBA half floats, row-major;
/// the caller checked the size against the device and the texel count).
pub(crate) fn radiance_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    label: &str,
    width: u32,
    height: u32,
    texels: &[u16],
) -> wgpu::Texture {
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: RADIANCE_FORMAT,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture: &texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        bytemuck::cast_slice(texels),
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(8 * width),
            rows_per_image: Some(height),
        },
        texture.size(),
    );
    texture
}

/// Uploads linear radiance (row-major `[r, g, b]`, `width × height`) into a new
/// [`RADIANCE_FORMAT`] texture: non-finite and negative values as 0, values beyond
/// [`RADIANCE_MAX`] as it.
pub fn upload_radiance(
    gpu: &GpuContext,
    width: u32,
    height: u32,
    radiance: &[[f32; 3]],
) -> Result<wgpu::Texture, GpuError> {
    let limit = gpu.device.limits().max_texture_dimension_2d;
    if width == 0 || height == 0 || width > limit || height > limit {
        return Err(GpuError::TargetSize {
            width,
            height,
            limit,
        });
    }
    if radiance.len() != width as usize * height as usize {
        return Err(GpuError::BadTexture {
            id: 0,
            width,
            height,
            bytes: radiance.len() * 12,
        });
    }
    let texels: Vec<u16> = radiance
        .iter()
        .flat_map(|c| {
            [
                half_radiance(c[0]),
                half_radiance(c[1]),
                half_radiance(c[2]),
                0x3c00,
            ]
        })
        .collect();
    let texture = radiance_texture(&gpu.device, &gpu.queue, "radiance", width, height, &texels);
    Ok(texture)
}

/// Tone-maps a radiance image headless into an 8-bit RGBA image of the same size;
/// also returns the adaptation level the GPU computed (auto-exposure) or was given.
pub fn tone_map_headless(
    gpu: &GpuContext,
    pass: &mut ToneMapPass,
    width: u32,
    height: u32,
    radiance: &[[f32; 3]],
    settings: &ToneMapSettings,
) -> Result<(image::RgbaImage, f32), GpuError> {
    let source = upload_radiance(gpu, width, height, radiance)?;
    let target = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("tonemap target"),
        size: source.size(),
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: super::IMAGE_FORMAT,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    });
    let readback = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("adaptation read-back"),
        size: 16,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("tonemap"),
        });
    pass.record(
        &mut encoder,
        &source.create_view(&Default::default()),
        (width, height),
        settings,
        &target.create_view(&Default::default()),
        super::IMAGE_FORMAT,
    );
    encoder.copy_buffer_to_buffer(pass.adaptation_buffer(), 0, &readback, 0, 16);
    crate::gpu::submit(&gpu.queue, Some(encoder.finish()));
    let image = super::read_rgba_texture(&gpu.device, &gpu.queue, &target)?;
    let slice = readback.slice(..);
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    gpu.wait_idle()?;
    rx.recv()
        .map_err(|e| GpuError::Readback(e.to_string()))?
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    let l_a = {
        let bytes = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        bytes
            .get(..4)
            .and_then(|b| b.try_into().ok())
            .map(f32::from_le_bytes)
            .unwrap_or(f32::NAN)
    };
    readback.unmap();
    Ok((image, settings.adaptation.unwrap_or(l_a)))
}
