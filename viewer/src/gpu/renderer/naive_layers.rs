//! The naive-layers strategy (the baseline of the k-buffer): one per-scan layer for
//! each visible scan, `4 + n·20` bytes per pixel, composited in one full-screen pass.
//! Its layers are also what `read_layers` reads back for the CPU reference.

use texel::model::ScanId;

use super::frame::{Frame, cleared};
use crate::gpu::GpuError;
use crate::gpu::pipelines::Pipelines;
use crate::gpu::targets::{Layers, TargetMemory};

pub(crate) struct NaiveTargets {
    pub width: u32,
    pub height: u32,
    pub layers: Layers,
    pub composite_bind_group: wgpu::BindGroup,
}

impl NaiveTargets {
    fn new(
        device: &wgpu::Device,
        pipelines: &Pipelines,
        frame_uniform: &wgpu::Buffer,
        (width, height): (u32, u32),
        count: u32,
    ) -> Self {
        let layers = Layers::new(device, width, height, count.max(1));
        let composite_bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("composite naive"),
            layout: &pipelines.naive_layout,
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

/// Layers for `layers` visible scans at `size`, checked against the device's limit;
/// those in `slot` are kept when they match exactly.
pub(super) fn prepare<'a>(
    slot: &'a mut Option<NaiveTargets>,
    device: &wgpu::Device,
    pipelines: &Pipelines,
    frame_uniform: &wgpu::Buffer,
    size: (u32, u32),
    layers: u32,
) -> Result<&'a NaiveTargets, GpuError> {
    let limit = device.limits().max_texture_array_layers;
    if layers > limit {
        return Err(GpuError::TooManyLayers {
            visible: layers as usize,
            limit,
        });
    }
    let targets = match slot.take() {
        Some(t) if (t.width, t.height) == size && t.layers.count == layers.max(1) => t,
        _ => NaiveTargets::new(device, pipelines, frame_uniform, size, layers),
    };
    Ok(slot.insert(targets))
}

/// Records one layer per visible scan, then the composite into the frame's target.
pub(super) fn encode(
    frame: &Frame<'_>,
    encoder: &mut wgpu::CommandEncoder,
    t: &NaiveTargets,
    visible: &[ScanId],
) {
    if visible.is_empty() {
        // Layer 0 must not hold stale fragments: the composite reads 0 layers
        // anyway, but keep the stack clean for read-back.
        encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("clear layer"),
            color_attachments: &[
                cleared(&t.layers.colour_layers[0]),
                cleared(&t.layers.data_layers[0]),
            ],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
    }
    for (l, &id) in visible.iter().enumerate() {
        frame.encode_layer(
            encoder,
            &t.layers.colour_layers[l],
            &t.layers.data_layers[l],
            id,
        );
    }
    frame.encode_composite(
        encoder,
        &frame.outputs.composite_naive,
        &t.composite_bind_group,
    );
}
