//! The tile pass: a long-lived pipeline (one per target format) that draws resident
//! tiles into a given colour and depth target, as the scan passes do: reverse z
//! (depth cleared to 0, compare Greater), display colours through `to_target`, and
//! positions relative to the camera. Each tile's view-from-tile transform is built in
//! f64 from `origin_m - eye` and only then rounded to f32, so a street 5,000 km from
//! the world origin draws as well as one at it. Also a headless target (colour in
//! `IMAGE_FORMAT` plus depth) read back as an image.

use std::collections::HashMap;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec4};
use nalgebra::{Matrix4, Vector3};

use super::cache::{GpuTile, TILE_VERTEX_ATTRIBUTES, TileVertex};
use super::fade::MAX_CUTS;
use crate::camera::VirtualCamera;
use crate::gpu::{DEPTH_FORMAT, GpuContext, GpuError, IMAGE_FORMAT, RenderTarget, shaders};

/// The frame uniform (`Frame` in `common.wgsl`); only the projection, the sRGB flag
/// and the width are used by the tile pass.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct TileFrameUniform {
    pub clip_from_view: Mat4,
    pub background: Vec4,
    pub params: Vec4,
    pub counts: UVec4,
}

/// `Fade` in `tile.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct FadeUniform {
    pub ends: [Vec4; 2],
}

/// `Tile` in `tile.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct TileUniform {
    pub view_from_tile: Mat4,
    pub cuts: UVec4,
}

/// One tile to draw and the cuts it belongs to (bit i: cut i; all bits when no fade
/// is under way).
#[derive(Debug, Clone, Copy)]
pub struct TileDraw<'a> {
    pub tile: &'a GpuTile,
    pub cuts: u32,
}

/// Where the tile pass draws: a colour target, its depth buffer (`DEPTH_FORMAT`, the
/// target's size) and whether to clear both first (colour to that display colour,
/// depth to the far plane) or draw over what they hold.
#[derive(Debug, Clone, Copy)]
pub struct PassTarget<'a> {
    pub colour: RenderTarget<'a>,
    pub depth: &'a wgpu::TextureView,
    pub clear: Option<[f32; 3]>,
}

/// What a pass drew.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PassCounts {
    pub tiles: usize,
    pub triangles: u64,
}

/// `view_from_tile` for the GPU: the camera's rotation applied to `origin_m - eye` in
/// f64, then rounded.
pub fn view_from_tile(camera: &VirtualCamera, origin_m: [f64; 3]) -> Mat4 {
    let eye = camera.world_from_eo.translation.vector;
    let view_from_world = camera.world_from_eo.rotation.inverse();
    let offset = view_from_world * (Vector3::from(origin_m) - eye);
    let mut m: Matrix4<f64> = view_from_world.to_homogeneous();
    m[(0, 3)] = offset.x;
    m[(1, 3)] = offset.y;
    m[(2, 3)] = offset.z;
    let cols: [[f64; 4]; 4] = m.into();
    glam::DMat4::from_cols_array_2d(&cols).as_mat4()
}

/// A display colour as a target of `format` stores it.
fn clear_colour(background: [f32; 3], format: wgpu::TextureFormat) -> wgpu::Color {
    let c = background.map(|c| {
        let c = f64::from(c.clamp(0.0, 1.0));
        if !format.is_srgb() {
            c
        } else if c <= 0.04045 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        }
    });
    wgpu::Color {
        r: c[0],
        g: c[1],
        b: c[2],
        a: 1.0,
    }
}

/// The tile pipelines, uniforms and bind groups.
pub struct TilePass {
    device: wgpu::Device,
    queue: wgpu::Queue,
    module: wgpu::ShaderModule,
    tile_layout: wgpu::BindGroupLayout,
    pipeline_layout: wgpu::PipelineLayout,
    pipelines: HashMap<wgpu::TextureFormat, wgpu::RenderPipeline>,
    frame_uniform: wgpu::Buffer,
    fade_uniform: wgpu::Buffer,
    frame_bind_group: wgpu::BindGroup,
    tile_uniforms: wgpu::Buffer,
    tile_bind_group: wgpu::BindGroup,
    /// Bytes between tiles' uniforms (the device's dynamic offset alignment).
    stride: u64,
    capacity: u64,
}

fn uniform_entry(binding: u32, dynamic: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: dynamic,
            min_binding_size: None,
        },
        count: None,
    }
}

fn uniform_buffer(device: &wgpu::Device, label: &str, size: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

const TILE_UNIFORM_BYTES: u64 = std::mem::size_of::<TileUniform>() as u64;

impl TilePass {
    pub fn new(gpu: &GpuContext) -> Self {
        let device = gpu.device.clone();
        let frame_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tile frame"),
            entries: &[uniform_entry(0, false), uniform_entry(1, false)],
        });
        let tile_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tile"),
            entries: &[uniform_entry(0, true)],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("tile"),
            bind_group_layouts: &[Some(&frame_layout), Some(&tile_layout)],
            immediate_size: 0,
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("tile.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::source(shaders::TILE).into()),
        });
        let frame_uniform = uniform_buffer(
            &device,
            "tile frame uniform",
            std::mem::size_of::<TileFrameUniform>() as u64,
        );
        let fade_uniform = uniform_buffer(
            &device,
            "tile fade uniform",
            std::mem::size_of::<FadeUniform>() as u64,
        );
        let frame_bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tile frame"),
            layout: &frame_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: frame_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: fade_uniform.as_entire_binding(),
                },
            ],
        });
        let align = u64::from(device.limits().min_uniform_buffer_offset_alignment).max(1);
        let stride = TILE_UNIFORM_BYTES.div_ceil(align) * align;
        let capacity = 64;
        let (tile_uniforms, tile_bind_group) =
            Self::tile_buffer(&device, &tile_layout, stride * capacity);
        Self {
            device,
            queue: gpu.queue.clone(),
            module,
            tile_layout,
            pipeline_layout,
            pipelines: HashMap::new(),
            frame_uniform,
            fade_uniform,
            frame_bind_group,
            tile_uniforms,
            tile_bind_group,
            stride,
            capacity,
        }
    }

    fn tile_buffer(
        device: &wgpu::Device,
        layout: &wgpu::BindGroupLayout,
        bytes: u64,
    ) -> (wgpu::Buffer, wgpu::BindGroup) {
        let buffer = uniform_buffer(device, "tile uniforms", bytes);
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tile"),
            layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &buffer,
                    offset: 0,
                    size: wgpu::BufferSize::new(TILE_UNIFORM_BYTES),
                }),
            }],
        });
        (buffer, bind_group)
    }

    fn pipeline(&mut self, format: wgpu::TextureFormat) -> &wgpu::RenderPipeline {
        let (device, layout, module) = (&self.device, &self.pipeline_layout, &self.module);
        self.pipelines.entry(format).or_insert_with(|| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("tile"),
                layout: Some(layout),
                vertex: wgpu::VertexState {
                    module,
                    entry_point: Some("vs_tile"),
                    compilation_options: Default::default(),
                    buffers: &[Some(wgpu::VertexBufferLayout {
                        array_stride: std::mem::size_of::<TileVertex>() as u64,
                        step_mode: wgpu::VertexStepMode::Vertex,
                        attributes: &TILE_VERTEX_ATTRIBUTES,
                    })],
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    // Tiles are closed surfaces only where the scans saw all round;
                    // a facade seen from behind still shows (no face culling).
                    cull_mode: None,
                    ..Default::default()
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    depth_write_enabled: Some(true),
                    depth_compare: Some(wgpu::CompareFunction::Greater),
                    stencil: wgpu::StencilState::default(),
                    bias: wgpu::DepthBiasState::default(),
                }),
                multisample: wgpu::MultisampleState::default(),
                fragment: Some(wgpu::FragmentState {
                    module,
                    entry_point: Some("fs_tile"),
                    compilation_options: Default::default(),
                    targets: &[Some(wgpu::ColorTargetState {
                        format,
                        blend: None,
                        write_mask: wgpu::ColorWrites::ALL,
                    })],
                }),
                multiview_mask: None,
                cache: None,
            })
        })
    }

    /// Records the tile pass into `encoder`: `draws` into `target`. `ends` are the
    /// cuts' shares (see `fade.rs`). The uniforms are written now: one pass per
    /// submission.
    pub fn encode(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        target: &PassTarget<'_>,
        camera: &VirtualCamera,
        ends: &[f32; MAX_CUTS],
        draws: &[TileDraw<'_>],
    ) -> PassCounts {
        let (clear, depth) = (target.clear, target.depth);
        let target = &target.colour;
        let bg = clear.unwrap_or([0.0; 3]);
        let frame = TileFrameUniform {
            clip_from_view: camera.clip_from_view(),
            background: Vec4::new(bg[0], bg[1], bg[2], 1.0),
            params: Vec4::new(
                0.0,
                1.0,
                if target.format.is_srgb() { 1.0 } else { 0.0 },
                0.0,
            ),
            counts: UVec4::new(0, 0, 0, target.width),
        };
        self.queue
            .write_buffer(&self.frame_uniform, 0, bytemuck::bytes_of(&frame));
        let fade = FadeUniform {
            ends: [
                Vec4::new(ends[0], ends[1], ends[2], ends[3]),
                Vec4::new(ends[4], ends[5], ends[6], ends[7]),
            ],
        };
        self.queue
            .write_buffer(&self.fade_uniform, 0, bytemuck::bytes_of(&fade));
        let drawable: Vec<&TileDraw<'_>> = draws
            .iter()
            .filter(|d| d.tile.buffers.is_some() && d.cuts != 0)
            .collect();
        let count = drawable.len() as u64;
        if count > self.capacity {
            self.capacity = count.next_power_of_two();
            let (buffer, bind_group) =
                Self::tile_buffer(&self.device, &self.tile_layout, self.stride * self.capacity);
            self.tile_uniforms = buffer;
            self.tile_bind_group = bind_group;
        }
        if count > 0 {
            let mut bytes = vec![0u8; (self.stride * count) as usize];
            for (i, d) in drawable.iter().enumerate() {
                let uniform = TileUniform {
                    view_from_tile: view_from_tile(camera, d.tile.origin_m),
                    cuts: UVec4::new(d.cuts, 0, 0, 0),
                };
                let at = i * self.stride as usize;
                bytes[at..at + TILE_UNIFORM_BYTES as usize]
                    .copy_from_slice(bytemuck::bytes_of(&uniform));
            }
            self.queue.write_buffer(&self.tile_uniforms, 0, &bytes);
        }
        let (colour_load, depth_load) = match clear {
            Some(c) => (
                wgpu::LoadOp::Clear(clear_colour(c, target.format)),
                wgpu::LoadOp::Clear(0.0),
            ),
            None => (wgpu::LoadOp::Load, wgpu::LoadOp::Load),
        };
        let stride = self.stride;
        let frame_bind_group = self.frame_bind_group.clone();
        let tile_bind_group = self.tile_bind_group.clone();
        let pipeline = self.pipeline(target.format).clone();
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("tiles"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: colour_load,
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: depth,
                depth_ops: Some(wgpu::Operations {
                    load: depth_load,
                    store: wgpu::StoreOp::Store,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &frame_bind_group, &[]);
        let mut counts = PassCounts::default();
        for (i, d) in drawable.iter().enumerate() {
            let Some((vertices, indices)) = &d.tile.buffers else {
                continue;
            };
            let offset = u32::try_from(i as u64 * stride).unwrap_or(u32::MAX);
            pass.set_bind_group(1, &tile_bind_group, &[offset]);
            pass.set_vertex_buffer(0, vertices.slice(..));
            pass.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
            pass.draw_indexed(0..d.tile.triangles * 3, 0, 0..1);
            counts.tiles += 1;
            counts.triangles += u64::from(d.tile.triangles);
        }
        counts
    }
}

/// A headless target: an `IMAGE_FORMAT` colour texture and its depth buffer.
pub struct ImageTarget {
    pub width: u32,
    pub height: u32,
    colour: wgpu::Texture,
    colour_view: wgpu::TextureView,
    depth_view: wgpu::TextureView,
}

impl ImageTarget {
    pub fn new(gpu: &GpuContext, width: u32, height: u32) -> Result<Self, GpuError> {
        let limit = gpu.device.limits().max_texture_dimension_2d;
        if width == 0 || height == 0 || width > limit || height > limit {
            return Err(GpuError::TargetSize {
                width,
                height,
                limit,
            });
        }
        let texture = |label: &str, format, usage| {
            gpu.device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            })
        };
        let colour = texture(
            "tile image",
            IMAGE_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        let depth = texture(
            "tile depth",
            DEPTH_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
        );
        Ok(Self {
            width,
            height,
            colour_view: colour.create_view(&Default::default()),
            depth_view: depth.create_view(&Default::default()),
            colour,
        })
    }

    pub fn target(&self) -> RenderTarget<'_> {
        RenderTarget {
            view: &self.colour_view,
            format: IMAGE_FORMAT,
            width: self.width,
            height: self.height,
        }
    }

    pub fn depth_view(&self) -> &wgpu::TextureView {
        &self.depth_view
    }

    /// The colour texture as an image (waits for the GPU).
    pub fn read(&self, gpu: &GpuContext) -> Result<image::RgbaImage, GpuError> {
        crate::gpu::read_rgba_texture(&gpu.device, &gpu.queue, &self.colour)
    }
}

/// Draws `tiles` (all of them whole, no fade) into a new image: the reference render
/// (e.g. every finest tile) and the pass on its own.
pub fn render_tiles_to_image(
    gpu: &GpuContext,
    pass: &mut TilePass,
    tiles: &[&GpuTile],
    camera: &VirtualCamera,
    background: [f32; 3],
) -> Result<(image::RgbaImage, PassCounts), GpuError> {
    let target = ImageTarget::new(gpu, camera.width, camera.height)?;
    let draws: Vec<TileDraw<'_>> = tiles
        .iter()
        .map(|t| TileDraw {
            tile: t,
            cuts: u32::MAX,
        })
        .collect();
    let mut encoder = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("tiles"),
        });
    let counts = pass.encode(
        &mut encoder,
        &PassTarget {
            colour: target.target(),
            depth: target.depth_view(),
            clear: Some(background),
        },
        camera,
        &[1.0; MAX_CUTS],
        &draws,
    );
    gpu.queue.submit(Some(encoder.finish()));
    Ok((target.read(gpu)?, counts))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    fn wgsl_size(name: &str) -> u32 {
        let module = naga::front::wgsl::parse_str(&shaders::source(shaders::TILE)).unwrap();
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

    #[test]
    fn uniforms_and_vertices_match_the_shader() {
        let size = |b: usize| u32::try_from(b).unwrap();
        assert_eq!(
            size(std::mem::size_of::<TileFrameUniform>()),
            wgsl_size("Frame")
        );
        assert_eq!(size(std::mem::size_of::<FadeUniform>()), wgsl_size("Fade"));
        assert_eq!(size(std::mem::size_of::<TileUniform>()), wgsl_size("Tile"));
        let last = TILE_VERTEX_ATTRIBUTES[TILE_VERTEX_ATTRIBUTES.len() - 1];
        assert_eq!(
            last.offset + last.format.size(),
            std::mem::size_of::<TileVertex>() as u64
        );
    }

    #[test]
    fn tile_transforms_are_relative_to_the_eye_in_f64() {
        use texel::pose::pose_from_parts;
        let far = [5.0e6, -4.0e6, 1234.5];
        let pose = pose_from_parts(far, [0.1, 0.2, -0.05, 0.97]).unwrap();
        let cam = VirtualCamera::new(pose, 60.0, 64, 48).unwrap();
        let origin = [far[0] + 3.25, far[1] - 1.5, far[2] + 0.125];
        let m = view_from_tile(&cam, origin);
        let p = m.transform_point3(glam::Vec3::new(0.1, 0.2, 0.3));
        let world = nalgebra::Point3::new(origin[0] + 0.1, origin[1] + 0.2, origin[2] + 0.3);
        let want = pose.inverse() * world;
        let error = (p.as_dvec3() - glam::DVec3::new(want.x, want.y, want.z)).length();
        assert!(error < 1e-5, "{error}");
    }
}
