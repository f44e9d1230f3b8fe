//! One scan's GPU data, uploaded once when the view needs the scan and held until it
//! is evicted: vertices (scan frame, f32, small), three index buffers (usable
//! triangles; with stretched ones; the coarse list of interactive frames), the EO texture and a uniform that a pose or camera
//! change rewrites; and its exact size in bytes, known before uploading.

use bytemuck::{Pod, Zeroable};
use glam::{DVec3, Mat4, UVec4, Vec2, Vec3, Vec4};
use texel::{RangeNoise, TexelScan};
use wgpu::util::DeviceExt;

use super::{EO_FORMAT, GpuError};
use crate::cull::ScanBounds;
use crate::footprint::Footprint;
use crate::reliability::{triangle_drawn, vertex_accuracy, vertex_acquisition_range};

/// Vertex layout: position (scan frame), texture coordinate, interpolated normal
/// accuracy, acquisition range.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct Vertex {
    pub position: Vec3,
    pub uv: Vec2,
    pub accuracy: f32,
    pub acquisition_range: f32,
}

pub(crate) const VERTEX_ATTRIBUTES: [wgpu::VertexAttribute; 4] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x2, 2 => Float32, 3 => Float32];

/// The per-scan uniform (`Scan` in `scan.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct ScanUniform {
    pub view_from_scan: Mat4,
    /// xyz: the acquisition centre of projection in the view frame; w: 1.
    pub cop_view: Vec4,
    /// x: range noise sigma (m), y: its growth per metre of range.
    pub noise: Vec4,
    /// x: the scan id.
    pub ids: UVec4,
}

pub(crate) struct GpuScan {
    pub vertices: wgpu::Buffer,
    pub usable: wgpu::Buffer,
    pub usable_count: u32,
    pub with_stretched: wgpu::Buffer,
    pub with_stretched_count: u32,
    /// The interactive frame's triangles (`super::coarse`).
    pub coarse: wgpu::Buffer,
    pub coarse_count: u32,
    pub uniform: wgpu::Buffer,
    pub bind_group: wgpu::BindGroup,
    pub bounds: Option<ScanBounds>,
    /// Where on screen the scan can draw (`crate::footprint`).
    pub footprint: Footprint,
    /// The acquisition centre of projection, scan frame.
    pub cop_scan: DVec3,
    pub noise: RangeNoise,
    /// GPU bytes held by this scan.
    pub bytes: u64,
    /// The EO texture, for the modes that bind it their own way (`points`).
    pub eo_view: wgpu::TextureView,
}

impl GpuScan {
    pub fn upload(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        layout: &wgpu::BindGroupLayout,
        sampler: &wgpu::Sampler,
        id: u64,
        scan: &TexelScan,
    ) -> Result<Self, GpuError> {
        let tex = &scan.texture;
        let limit = device.limits().max_texture_dimension_2d;
        if tex.width == 0 || tex.height == 0 || tex.width > limit || tex.height > limit {
            return Err(GpuError::TextureTooLarge {
                id,
                width: tex.width,
                height: tex.height,
                limit,
            });
        }
        if !tex.is_consistent() {
            return Err(GpuError::BadTexture {
                id,
                width: tex.width,
                height: tex.height,
                bytes: tex.rgb.len(),
            });
        }
        let vertices = vertex_data(scan);
        let usable = drawn_indices(scan, false);
        let with_stretched = drawn_indices(scan, true);
        let coarse = super::coarse::coarse_indices(scan);
        let vertex_buffer = buffer(
            device,
            queue,
            "scan vertices",
            bytemuck::cast_slice(&vertices),
            wgpu::BufferUsages::VERTEX,
        );
        let usable_buffer = buffer(
            device,
            queue,
            "scan triangles",
            bytemuck::cast_slice(&usable),
            wgpu::BufferUsages::INDEX,
        );
        let stretched_buffer = buffer(
            device,
            queue,
            "scan triangles with stretched",
            bytemuck::cast_slice(&with_stretched),
            wgpu::BufferUsages::INDEX,
        );
        let coarse_buffer = buffer(
            device,
            queue,
            "scan coarse triangles",
            bytemuck::cast_slice(&coarse),
            wgpu::BufferUsages::INDEX,
        );
        let uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("scan uniform"),
            size: std::mem::size_of::<ScanUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let size = wgpu::Extent3d {
            width: tex.width,
            height: tex.height,
            depth_or_array_layers: 1,
        };
        let rgba = rgba_of_rgb(&tex.rgb);
        let texture = device.create_texture_with_data(
            queue,
            &wgpu::TextureDescriptor {
                label: Some("scan EO texture"),
                size,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: EO_FORMAT,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            },
            wgpu::util::TextureDataOrder::LayerMajor,
            &rgba,
        );
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("scan bind group"),
            layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&view),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::Sampler(sampler),
                },
            ],
        });
        let bytes = vertex_buffer.size()
            + usable_buffer.size()
            + stretched_buffer.size()
            + coarse_buffer.size()
            + uniform.size()
            + texture_bytes(tex.width, tex.height);
        Ok(Self {
            vertices: vertex_buffer,
            usable: usable_buffer,
            usable_count: usable.len() as u32,
            with_stretched: stretched_buffer,
            with_stretched_count: with_stretched.len() as u32,
            coarse: coarse_buffer,
            coarse_count: coarse.len() as u32,
            uniform,
            bind_group,
            bounds: ScanBounds::of(scan),
            footprint: Footprint::of(scan),
            cop_scan: DVec3::from_array(scan.cop_m),
            noise: scan.range_noise,
            bytes,
            eo_view: view,
        })
    }

    /// The index buffer and its length for the stretched-triangle toggle and the
    /// interactive frame's coarse triangles (not with stretched ones: those are shown
    /// to be seen).
    pub fn indices(&self, keep_stretched: bool, coarse: bool) -> (&wgpu::Buffer, u32) {
        if keep_stretched {
            (&self.with_stretched, self.with_stretched_count)
        } else if coarse {
            (&self.coarse, self.coarse_count)
        } else {
            (&self.usable, self.usable_count)
        }
    }
}

/// Bytes of an RGBA8 texture.
fn texture_bytes(width: u32, height: u32) -> u64 {
    u64::from(width) * u64::from(height) * 4
}

/// The GPU bytes an upload of `scan` holds, without uploading it: the buffers as
/// [`GpuScan::upload`] sizes them (one word for an empty one) and the texture.
pub fn scan_gpu_bytes(scan: &TexelScan) -> u64 {
    let padded = |bytes: u64| bytes.max(4).next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT);
    let n = scan.vertices.len() as u32;
    let indices = |keep_stretched: bool| {
        let triangles = scan
            .triangles
            .iter()
            .enumerate()
            .filter(|(t, tri)| {
                triangle_drawn(scan, *t, keep_stretched) && tri.iter().all(|&v| v < n)
            })
            .count() as u64;
        padded(triangles * 3 * 4)
    };
    padded(scan.vertices.len() as u64 * std::mem::size_of::<Vertex>() as u64)
        + indices(false)
        + indices(true)
        + padded(super::coarse::coarse_indices(scan).len() as u64 * 4)
        + std::mem::size_of::<ScanUniform>() as u64
        + texture_bytes(scan.texture.width, scan.texture.height)
}

fn buffer(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    label: &str,
    data: &[u8],
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    // Written through the queue, not mapped at creation: Chromium's WebGPU refuses
    // buffers mapped at creation beyond a small size when its GPU process cannot share
    // memory with the page (headless, software rendering), and both cost the same
    // copy. Sizes are whole words (the queue writes words); wgpu refuses zero-sized
    // vertex/index buffers in some paths, so one word at least.
    let size = (data.len() as u64).div_ceil(4).max(1) * 4;
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: usage | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let whole = data.len() / 4 * 4;
    if whole > 0 {
        queue.write_buffer(&buffer, 0, &data[..whole]);
    }
    if whole < data.len() {
        let mut tail = [0u8; 4];
        tail[..data.len() - whole].copy_from_slice(&data[whole..]);
        queue.write_buffer(&buffer, whole as u64, &tail);
    }
    buffer
}

fn vertex_data(scan: &TexelScan) -> Vec<Vertex> {
    let accuracy = vertex_accuracy(scan);
    let range = vertex_acquisition_range(scan);
    scan.vertices
        .iter()
        .enumerate()
        .map(|(i, &position)| Vertex {
            position: Vec3::from_array(position),
            uv: scan
                .tex_coords
                .get(i)
                .copied()
                .map_or(Vec2::ZERO, Vec2::from_array),
            accuracy: accuracy.get(i).copied().unwrap_or(0.0),
            acquisition_range: range.get(i).copied().unwrap_or(0.0),
        })
        .collect()
}

/// Indices of the drawn triangles; triangles naming a vertex that does not exist are
/// skipped (a malformed scan must not make the GPU read out of bounds).
fn drawn_indices(scan: &TexelScan, keep_stretched: bool) -> Vec<u32> {
    let n = scan.vertices.len() as u32;
    scan.triangles
        .iter()
        .enumerate()
        .filter(|(t, tri)| triangle_drawn(scan, *t, keep_stretched) && tri.iter().all(|&v| v < n))
        .flat_map(|(_, tri)| *tri)
        .collect()
}

/// RGB8 pixels as opaque RGBA8 (GPU textures have no three-channel 8-bit format).
pub(crate) fn rgba_of_rgb(rgb: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3)
        .flat_map(|p| [p[0], p[1], p[2], 255])
        .collect()
}
