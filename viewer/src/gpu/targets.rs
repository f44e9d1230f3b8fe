//! Size-dependent GPU targets, rebuilt only when the size, k, batch size or layer
//! count changes. Two strategies share the scan pass:
//!
//! - **k-buffer** (bounded memory): a pre-pass target with the nearest valid distance
//!   and its sigma, `batch` per-scan layers that scans are rendered into a batch at a
//!   time, and a storage buffer with the k best fragments of every pixel:
//!   `8 + batch·20 + 4 + k·12` bytes per pixel whatever the number of scans.
//! - **naive layers** (the baseline): one layer per visible scan, `4 + n·20` bytes per
//!   pixel.

use super::{DEPTH_FORMAT, LAYER_COLOUR_FORMAT, LAYER_DATA_FORMAT, NEAREST_FORMAT};

/// Bytes per pixel of one per-scan layer (colour Rgba8 + data Rgba32Uint).
pub const LAYER_BYTES_PER_PIXEL: u64 = 4 + 16;
/// Bytes of one k-buffer entry (packed colour, reliability, scan id).
pub const KBUFFER_ENTRY_BYTES: u64 = 12;
/// Dynamic-offset stride of the per-batch uniform.
const BATCH_UNIFORM_STRIDE: u64 = 256;

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

fn pixels(width: u32, height: u32) -> u64 {
    u64::from(width) * u64::from(height)
}

pub(crate) struct Texture {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
}

#[allow(clippy::too_many_arguments)]
fn texture(
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
    fn new(device: &wgpu::Device, width: u32, height: u32, count: u32) -> Self {
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

    fn bytes(&self) -> u64 {
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
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        Self {
            depth: texture(
                device,
                "depth",
                width,
                height,
                1,
                DEPTH_FORMAT,
                wgpu::TextureUsages::RENDER_ATTACHMENT,
                false,
            ),
            width,
            height,
        }
    }

    pub fn bytes(&self) -> u64 {
        pixels(self.width, self.height) * 4
    }
}

pub(crate) struct KBufferTargets {
    pub width: u32,
    pub height: u32,
    pub k: u32,
    pub batch: u32,
    pub nearest: Texture,
    pub layers: Layers,
    pub kbuffer: wgpu::Buffer,
    pub batch_uniform: wgpu::Buffer,
    pub batch_slots: u32,
    pub merge_bind_group: wgpu::BindGroup,
    pub composite_bind_group: wgpu::BindGroup,
}

impl KBufferTargets {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        device: &wgpu::Device,
        merge_layout: &wgpu::BindGroupLayout,
        composite_layout: &wgpu::BindGroupLayout,
        frame_uniform: &wgpu::Buffer,
        width: u32,
        height: u32,
        k: u32,
        batch: u32,
        batch_slots: u32,
    ) -> Self {
        let nearest = texture(
            device,
            "nearest",
            width,
            height,
            1,
            NEAREST_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            false,
        );
        let layers = Layers::new(device, width, height, batch);
        let kbuffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("k-buffer"),
            size: pixels(width, height) * u64::from(k) * KBUFFER_ENTRY_BYTES,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let batch_slots = batch_slots.max(1);
        let batch_uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("batch sizes"),
            size: u64::from(batch_slots) * BATCH_UNIFORM_STRIDE,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let merge_bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("merge"),
            layout: merge_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: frame_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&nearest.view),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::TextureView(&layers.colour.view),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: wgpu::BindingResource::TextureView(&layers.data.view),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: kbuffer.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &batch_uniform,
                        offset: 0,
                        size: wgpu::BufferSize::new(16),
                    }),
                },
            ],
        });
        let composite_bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("composite k-buffer"),
            layout: composite_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: frame_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: kbuffer.as_entire_binding(),
                },
            ],
        });
        Self {
            width,
            height,
            k,
            batch,
            nearest,
            layers,
            kbuffer,
            batch_uniform,
            batch_slots,
            merge_bind_group,
            composite_bind_group,
        }
    }

    /// Byte offset of batch `i`'s uniform slot.
    pub fn slot_offset(i: u32) -> u32 {
        i * BATCH_UNIFORM_STRIDE as u32
    }

    pub fn memory(&self, depth: u64) -> TargetMemory {
        TargetMemory {
            depth,
            nearest: pixels(self.width, self.height) * 8,
            layers: self.layers.bytes(),
            kbuffer: self.kbuffer.size(),
        }
    }

    /// The k-buffer's size in bytes for a target, k: checked against the device.
    pub fn kbuffer_bytes(width: u32, height: u32, k: u32) -> u64 {
        pixels(width, height) * u64::from(k) * KBUFFER_ENTRY_BYTES
    }
}

pub(crate) struct NaiveTargets {
    pub width: u32,
    pub height: u32,
    pub layers: Layers,
    pub composite_bind_group: wgpu::BindGroup,
}

impl NaiveTargets {
    pub fn new(
        device: &wgpu::Device,
        composite_layout: &wgpu::BindGroupLayout,
        frame_uniform: &wgpu::Buffer,
        width: u32,
        height: u32,
        count: u32,
    ) -> Self {
        let layers = Layers::new(device, width, height, count.max(1));
        let composite_bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("composite naive"),
            layout: composite_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: frame_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&layers.colour.view),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::TextureView(&layers.data.view),
                },
            ],
        });
        Self {
            width,
            height,
            layers,
            composite_bind_group,
        }
    }

    pub fn memory(&self, depth: u64) -> TargetMemory {
        TargetMemory {
            depth,
            nearest: 0,
            layers: self.layers.bytes(),
            kbuffer: 0,
        }
    }
}
