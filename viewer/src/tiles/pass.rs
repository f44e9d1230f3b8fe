//! The tile pass: a long-lived pipeline (one per target format) that draws resident
//! tiles into a given colour and depth target, as the scan passes do: reverse z
//! (depth cleared to 0, compare Greater), display colours through `to_target`, and
//! positions relative to the camera. Each tile's view-from-tile transform is built in
//! f64 from `origin_m - eye` and only then rounded to f32, so a street 5,000 km from
//! the world origin draws as well as one at it.

use std::collections::HashMap;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec4};
use nalgebra::{Matrix4, Vector3};

use super::cache::{
    ATLAS_LAYOUT_ENTRIES, AtlasBinding, GpuTile, TILE_VERTEX_ATTRIBUTES, TileVertex,
};
use super::fade::MAX_CUTS;
use crate::camera::VirtualCamera;
use crate::gpu::{GpuContext, NEAREST_FORMAT, RenderTarget, shaders, surface_pipeline};

/// The frame uniform (`Frame` in `common.wgsl`) of the surface passes (tiles, VDTM):
/// only the projection, the sRGB flag and the width are used.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct SurfaceFrameUniform {
    pub clip_from_view: Mat4,
    pub background: Vec4,
    pub params: Vec4,
    pub counts: UVec4,
}

impl SurfaceFrameUniform {
    pub(crate) fn new(
        camera: &VirtualCamera,
        target: &RenderTarget<'_>,
        background: [f32; 3],
    ) -> Self {
        let bg = background;
        Self {
            clip_from_view: camera.clip_from_view(),
            background: Vec4::new(bg[0], bg[1], bg[2], 1.0),
            params: Vec4::new(
                0.0,
                1.0,
                if target.format.is_srgb() { 1.0 } else { 0.0 },
                0.0,
            ),
            counts: UVec4::new(0, 0, 0, target.width),
        }
    }
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
    /// x: the share of this tile's pixels where scans on its surface win over it
    /// (0: the tile everywhere, 1: the scans wherever they drew; between while
    /// fading); y: how far in front of or behind the scans, metres, the tile still
    /// counts as the same surface.
    pub scans: Vec4,
}

/// One tile to draw and the cuts it belongs to (bit i: cut i; all bits when no fade
/// is under way).
#[derive(Debug, Clone, Copy)]
pub struct TileDraw<'a> {
    pub tile: &'a GpuTile,
    pub cuts: u32,
    /// Share of the tile's pixels where the scans drawn beneath win on its surface
    /// (see [`PassTarget::scans`]): 0 when its scans are not shown.
    pub scan_share: f32,
    /// Same-surface tolerance against the scans, metres (the tile's geometric error).
    pub surface_tolerance_m: f32,
    /// The scan pass fills the holes its scans enclose
    /// ([`crate::gpu::RenderSettings::fill_enclosed_holes`]): the tile gives way there.
    pub scan_holes_filled: bool,
}

/// Where the tile pass draws: a colour target, its depth buffer (`DEPTH_FORMAT`, the
/// target's size) and whether to clear both first (colour to that display colour,
/// depth to the far plane) or draw over what they hold.
#[derive(Debug, Clone, Copy)]
pub struct PassTarget<'a> {
    pub colour: RenderTarget<'a>,
    pub depth: &'a wgpu::TextureView,
    pub clear: Option<[f32; 3]>,
    /// Scans already drawn into `colour` (the hybrid of Liu's tree, whose leaves are
    /// the scans): their nearest distance and sigma per pixel (the scan renderer's
    /// pre-pass target, `NEAREST_FORMAT`, the target's size). A tile fragment behind
    /// the scans is dropped; one on the same surface gives way to them in the share of
    /// pixels its draw says; one in front covers them.
    pub scans: Option<&'a wgpu::TextureView>,
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
pub(crate) fn clear_colour(background: [f32; 3], format: wgpu::TextureFormat) -> wgpu::Color {
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

fn frame_bind_group(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    frame_uniform: &wgpu::Buffer,
    fade_uniform: &wgpu::Buffer,
    scans: &wgpu::TextureView,
) -> wgpu::BindGroup {
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("tile frame"),
        layout,
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: frame_uniform.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: fade_uniform.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: wgpu::BindingResource::TextureView(scans),
            },
        ],
    })
}

/// A 1 x 1 scan pre-pass target holding "no scan" (+infinity, as the pre-pass clears).
fn no_scans_texture(device: &wgpu::Device, queue: &wgpu::Queue) -> wgpu::TextureView {
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("no scans"),
        size: wgpu::Extent3d {
            width: 1,
            height: 1,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: NEAREST_FORMAT,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    let texel = [f32::INFINITY.to_bits(), 0u32];
    queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture: &texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        bytemuck::cast_slice(&texel),
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(8),
            rows_per_image: Some(1),
        },
        wgpu::Extent3d {
            width: 1,
            height: 1,
            depth_or_array_layers: 1,
        },
    );
    texture.create_view(&wgpu::TextureViewDescriptor::default())
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
    frame_layout: wgpu::BindGroupLayout,
    /// The frame bind group with a 1 x 1 "no scans" texture, for passes without scans.
    frame_bind_group: wgpu::BindGroup,
    tile_uniforms: wgpu::Buffer,
    /// Group 1 with the blank atlas, for tiles coloured per vertex.
    tile_bind_group: wgpu::BindGroup,
    atlas: AtlasBinding,
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

pub(crate) fn uniform_buffer(device: &wgpu::Device, label: &str, size: u64) -> wgpu::Buffer {
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
            entries: &[
                uniform_entry(0, false),
                uniform_entry(1, false),
                wgpu::BindGroupLayoutEntry {
                    binding: 2,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Uint,
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
            ],
        });
        let tile_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tile"),
            entries: &[
                uniform_entry(0, true),
                ATLAS_LAYOUT_ENTRIES[0],
                ATLAS_LAYOUT_ENTRIES[1],
            ],
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
            std::mem::size_of::<SurfaceFrameUniform>() as u64,
        );
        let fade_uniform = uniform_buffer(
            &device,
            "tile fade uniform",
            std::mem::size_of::<FadeUniform>() as u64,
        );
        let no_scans = no_scans_texture(&device, &gpu.queue);
        let frame_bind_group = frame_bind_group(
            &device,
            &frame_layout,
            &frame_uniform,
            &fade_uniform,
            &no_scans,
        );
        let align = u64::from(device.limits().min_uniform_buffer_offset_alignment).max(1);
        let stride = TILE_UNIFORM_BYTES.div_ceil(align) * align;
        let capacity = 64;
        let atlas = AtlasBinding::new(&device, &gpu.queue);
        let (tile_uniforms, tile_bind_group) =
            Self::tile_buffer(&device, &tile_layout, &atlas, stride * capacity);
        Self {
            device,
            queue: gpu.queue.clone(),
            module,
            tile_layout,
            pipeline_layout,
            pipelines: HashMap::new(),
            frame_uniform,
            fade_uniform,
            frame_layout,
            frame_bind_group,
            tile_uniforms,
            tile_bind_group,
            atlas,
            stride,
            capacity,
        }
    }

    fn tile_buffer(
        device: &wgpu::Device,
        layout: &wgpu::BindGroupLayout,
        atlas: &AtlasBinding,
        bytes: u64,
    ) -> (wgpu::Buffer, wgpu::BindGroup) {
        let buffer = uniform_buffer(device, "tile uniforms", bytes);
        let bind_group = atlas.bind_group(device, layout, &buffer, TILE_UNIFORM_BYTES, None);
        (buffer, bind_group)
    }

    fn pipeline(&mut self, format: wgpu::TextureFormat) -> &wgpu::RenderPipeline {
        let (device, layout, module) = (&self.device, &self.pipeline_layout, &self.module);
        self.pipelines.entry(format).or_insert_with(|| {
            // Tiles are closed surfaces only where the scans saw all round; a facade
            // seen from behind still shows (no face culling).
            surface_pipeline(
                device,
                "tile",
                layout,
                module,
                ("vs_tile", "fs_tile"),
                wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<TileVertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &TILE_VERTEX_ATTRIBUTES,
                },
                format,
            )
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
        let (clear, depth, scans) = (target.clear, target.depth, target.scans);
        let target = &target.colour;
        let bg = clear.unwrap_or([0.0; 3]);
        let frame = SurfaceFrameUniform::new(camera, target, bg);
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
            let (buffer, bind_group) = Self::tile_buffer(
                &self.device,
                &self.tile_layout,
                &self.atlas,
                self.stride * self.capacity,
            );
            self.tile_uniforms = buffer;
            self.tile_bind_group = bind_group;
        }
        if count > 0 {
            let mut bytes = vec![0u8; (self.stride * count) as usize];
            for (i, d) in drawable.iter().enumerate() {
                let uniform = TileUniform {
                    view_from_tile: view_from_tile(camera, d.tile.origin_m),
                    cuts: UVec4::new(d.cuts, 0, 0, 0),
                    scans: Vec4::new(
                        d.scan_share.clamp(0.0, 1.0),
                        d.surface_tolerance_m.max(0.0),
                        if d.scan_holes_filled { 1.0 } else { 0.0 },
                        0.0,
                    ),
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
            // Over the scans: their colour stays, the tiles' depth starts afresh (the
            // scans' own is the pre-pass target the shader reads).
            None if scans.is_some() => (wgpu::LoadOp::Load, wgpu::LoadOp::Clear(0.0)),
            None => (wgpu::LoadOp::Load, wgpu::LoadOp::Load),
        };
        let stride = self.stride;
        let frame_bind_group = match scans {
            Some(nearest) => frame_bind_group(
                &self.device,
                &self.frame_layout,
                &self.frame_uniform,
                &self.fade_uniform,
                nearest,
            ),
            None => self.frame_bind_group.clone(),
        };
        let tile_bind_group = self.tile_bind_group.clone();
        // Textured tiles bind their atlas beside the uniforms: made per pass, as the
        // uniform buffer may have grown since the last.
        let atlas_bind_groups: Vec<Option<wgpu::BindGroup>> = drawable
            .iter()
            .map(|d| {
                d.tile.atlas.as_ref().map(|view| {
                    self.atlas.bind_group(
                        &self.device,
                        &self.tile_layout,
                        &self.tile_uniforms,
                        TILE_UNIFORM_BYTES,
                        Some(view),
                    )
                })
            })
            .collect();
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
            let group = atlas_bind_groups.get(i).and_then(Option::as_ref);
            pass.set_bind_group(1, group.unwrap_or(&tile_bind_group), &[offset]);
            pass.set_vertex_buffer(0, vertices.slice(..));
            pass.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
            pass.draw_indexed(0..d.tile.triangles * 3, 0, 0..1);
            counts.tiles += 1;
            counts.triangles += u64::from(d.tile.triangles);
        }
        counts
    }
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
            size(std::mem::size_of::<SurfaceFrameUniform>()),
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
