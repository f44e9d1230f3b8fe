//! Size-dependent GPU targets shared by the strategies: the depth buffer, stacks of
//! per-scan layers, and the accounting of what targets hold. Each strategy's own
//! targets (`renderer/kbuffer.rs`, `renderer/naive_layers.rs`) are built from these
//! and rebuilt only when the size, k, batch size or layer count changes:
//!
//! - **k-buffer** (bounded memory): `8 + batch·20 + 4 + k·12` bytes per pixel
//!   whatever the number of scans.
//! - **naive layers** (the baseline): one layer per visible scan, `4 + n·20` bytes per
//!   pixel.

use super::{LAYER_COLOUR_FORMAT, LAYER_DATA_FORMAT};

/// Bytes per pixel of one per-scan layer (colour Rgba8 + data Rgba32Uint).
pub const LAYER_BYTES_PER_PIXEL: u64 = 4 + 16;

/// GPU memory held by the targets of one strategy, bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TargetMemory {
    pub depth: u64,
    pub nearest: u64,
    pub layers: u64,
    pub kbuffer: u64,
}

impl TargetMemory {
    pub fn total(&self) -> u64 {
        self.depth + self.nearest + self.layers + self.kbuffer
    }
}

pub(crate) fn pixels(width: u32, height: u32) -> u64 {
    u64::from(width) * u64::from(height)
}

pub(crate) struct Texture {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
}

#[allow(clippy::too_many_arguments)]
pub(crate) fn texture(
    device: &wgpu::Device,
    label: &str,
    width: u32,
    height: u32,
    layers: u32,
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
    array: bool,
) -> Texture {
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: layers,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage,
        view_formats: &[],
    });
    let view = texture.create_view(&wgpu::TextureViewDescriptor {
        dimension: Some(if array {
            wgpu::TextureViewDimension::D2Array
        } else {
            wgpu::TextureViewDimension::D2
        }),
        ..Default::default()
    });
    Texture { texture, view }
}

/// A stack of per-scan layers (colour + data) with one attachment view per layer.
pub(crate) struct Layers {
    pub colour: Texture,
    pub data: Texture,
    pub colour_layers: Vec<wgpu::TextureView>,
    pub data_layers: Vec<wgpu::TextureView>,
    pub count: u32,
}

impl Layers {
    pub fn new(device: &wgpu::Device, width: u32, height: u32, count: u32) -> Self {
        let usage = wgpu::TextureUsages::RENDER_ATTACHMENT
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC;
        let colour = texture(
            device,
            "layer colour",
            width,
            height,
            count,
            LAYER_COLOUR_FORMAT,
            usage,
            true,
        );
        let data = texture(
            device,
            "layer data",
            width,
            height,
            count,
            LAYER_DATA_FORMAT,
            usage,
            true,
        );
        let per_layer = |t: &wgpu::Texture| -> Vec<wgpu::TextureView> {
            (0..count)
                .map(|l| {
                    t.create_view(&wgpu::TextureViewDescriptor {
                        dimension: Some(wgpu::TextureViewDimension::D2),
                        base_array_layer: l,
                        array_layer_count: Some(1),
                        ..Default::default()
                    })
                })
                .collect()
        };
        Self {
            colour_layers: per_layer(&colour.texture),
            data_layers: per_layer(&data.texture),
            colour,
            data,
            count,
        }
    }

    pub fn bytes(&self) -> u64 {
        let s = self.colour.texture.size();
        pixels(s.width, s.height) * u64::from(self.count) * LAYER_BYTES_PER_PIXEL
    }
}

pub(crate) struct DepthTarget {
    pub depth: Texture,
    pub width: u32,
    pub height: u32,
}

impl DepthTarget {
    /// A `format` depth buffer (`gpu::scan_depth_format`).
    pub fn new(
        device: &wgpu::Device,
        width: u32,
        height: u32,
        format: wgpu::TextureFormat,
    ) -> Self {
        Self {
            depth: texture(
                device,
                "depth",
                width,
                height,
                1,
                format,
                wgpu::TextureUsages::RENDER_ATTACHMENT,
                false,
            ),
            width,
            height,
        }
    }

    pub fn bytes(&self) -> u64 {
        let stencil = if self.depth.texture.format().has_stencil_aspect() {
            1
        } else {
            0
        };
        pixels(self.width, self.height) * (4 + stencil)
    }

    /// Whether it has a stencil (the k-buffer's marks).
    pub fn has_stencil(&self) -> bool {
        self.depth.texture.format().has_stencil_aspect()
    }
}

/// A render pass into one colour target, cleared to `clear` first, no depth: the
/// full-screen passes' shape.
pub(crate) fn colour_pass<'e>(
    encoder: &'e mut wgpu::CommandEncoder,
    label: &str,
    view: &wgpu::TextureView,
    clear: wgpu::Color,
) -> wgpu::RenderPass<'e> {
    encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some(label),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view,
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
    })
}
