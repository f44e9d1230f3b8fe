//! The k-buffer strategy (bounded memory): its size-dependent targets (a pre-pass
//! target with the nearest valid distance and its sigma, `batch` per-scan layers, and
//! a storage buffer with the k best fragments of every pixel) and a frame's passes:
//! the pre-pass, scans a batch at a time into the layers with each batch merged into
//! the k-buffer, then the composite. Optionally timed phase by phase.

// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::Instant;

use texel::model::ScanId;

use super::frame::Frame;
use crate::gpu::pipelines::{KBufferPipelines, Pipelines};
use crate::gpu::targets::{Layers, TargetMemory, Texture, pixels, texture};
use crate::gpu::{GpuError, NEAREST_FORMAT};

/// Bytes of one k-buffer entry (packed colour, reliability, scan id).
const KBUFFER_ENTRY_BYTES: u64 = 12;
/// Dynamic-offset stride of the per-batch uniform.
const BATCH_UNIFORM_STRIDE: u64 = 256;

/// What the k-buffer's targets are sized for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct KBufferShape {
    pub width: u32,
    pub height: u32,
    /// Fragments kept per pixel.
    pub k: u32,
    /// Scans rendered into layers before each merge.
    pub batch: u32,
}

impl KBufferShape {
    /// The k-buffer's size in bytes: checked against the device.
    fn kbuffer_bytes(&self) -> u64 {
        pixels(self.width, self.height) * u64::from(self.k) * KBUFFER_ENTRY_BYTES
    }
}

pub(crate) struct KBufferTargets {
    shape: KBufferShape,
    nearest: Texture,
    layers: Layers,
    kbuffer: wgpu::Buffer,
    batch_uniform: wgpu::Buffer,
    /// Batches the per-batch uniform has room for.
    batch_slots: u32,
    merge_bind_group: wgpu::BindGroup,
    composite_bind_group: wgpu::BindGroup,
}

impl KBufferTargets {
    /// The pre-pass target: nearest valid distance and its sigma per pixel.
    pub fn nearest_view(&self) -> &wgpu::TextureView {
        &self.nearest.view
    }

    fn new(
        device: &wgpu::Device,
        pipelines: &KBufferPipelines,
        frame_uniform: &wgpu::Buffer,
        shape: KBufferShape,
        batch_slots: u32,
    ) -> Self {
        let KBufferShape {
            width,
            height,
            batch,
            ..
        } = shape;
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
            size: shape.kbuffer_bytes(),
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
            layout: &pipelines.merge_layout,
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
            layout: &pipelines.composite_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: frame_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: kbuffer.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::TextureView(&nearest.view),
                },
            ],
        });
        Self {
            shape,
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
    fn slot_offset(i: u32) -> u32 {
        i * BATCH_UNIFORM_STRIDE as u32
    }

    pub fn memory(&self, depth: u64) -> TargetMemory {
        TargetMemory {
            depth,
            nearest: pixels(self.shape.width, self.shape.height) * 8,
            layers: self.layers.bytes(),
            kbuffer: self.kbuffer.size(),
        }
    }
}

/// The targets for a frame of `shape` with `batches` batches, checked against the
/// device's limits; those in `slot` are kept while they fit (the uniform slots only
/// grow, so a frame with fewer scans reuses them).
pub(super) fn prepare<'a>(
    slot: &'a mut Option<KBufferTargets>,
    device: &wgpu::Device,
    pipelines: &Pipelines,
    frame_uniform: &wgpu::Buffer,
    shape: KBufferShape,
    batches: u32,
) -> Result<&'a KBufferTargets, GpuError> {
    let bytes = shape.kbuffer_bytes();
    let limits = device.limits();
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
    if shape.batch > limits.max_texture_array_layers {
        return Err(GpuError::TooManyLayers {
            visible: shape.batch as usize,
            limit: limits.max_texture_array_layers,
        });
    }
    let targets = match slot.take() {
        Some(t) if t.shape == shape && t.batch_slots >= batches => t,
        old => {
            let slots = batches.max(old.map_or(1, |t| t.batch_slots));
            let pipelines = pipelines
                .kbuffer
                .as_ref()
                .ok_or(GpuError::NoStorageBuffers)?;
            KBufferTargets::new(device, pipelines, frame_uniform, shape, slots)
        }
    };
    Ok(slot.insert(targets))
}

/// The k-buffer's phases, for profiling.
#[derive(Debug, Clone, Copy)]
enum Phase {
    Prepass = 0,
    Layers = 1,
    Merge = 2,
    Composite = 3,
}

/// With `Renderer::profile_phases`: milliseconds per phase, the work of each
/// submitted and waited for on its own (slower than one submission per frame).
pub(super) struct PhaseClock {
    since: Instant,
    phase_ms: [f64; 4],
}

impl PhaseClock {
    /// Submits and waits for what `encoder` holds so far, then starts timing.
    pub fn start(frame: &Frame<'_>, encoder: &mut wgpu::CommandEncoder) -> Self {
        submit_and_wait(frame, encoder);
        Self {
            since: Instant::now(),
            phase_ms: [0.0; 4],
        }
    }

    /// Ends `phase`: submits what is encoded, waits for the GPU and books the time
    /// since the previous checkpoint to `phase`.
    fn checkpoint(&mut self, frame: &Frame<'_>, encoder: &mut wgpu::CommandEncoder, phase: Phase) {
        submit_and_wait(frame, encoder);
        let now = Instant::now();
        self.phase_ms[phase as usize] += now.duration_since(self.since).as_secs_f64() * 1e3;
        self.since = now;
    }

    /// Pre-pass, scan layers, merges, composite.
    pub fn phase_ms(&self) -> [f64; 4] {
        self.phase_ms
    }
}

fn submit_and_wait(frame: &Frame<'_>, encoder: &mut wgpu::CommandEncoder) {
    let done = std::mem::replace(
        encoder,
        frame
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("profiled frame"),
            }),
    );
    crate::gpu::submit(frame.queue, Some(done.finish()));
    // A failed wait only spoils the timing, not the frame.
    let _ = frame.device.poll(wgpu::PollType::wait_indefinitely());
}

/// Records the k-buffer's passes for `visible` into the frame's target.
pub(super) fn encode(
    frame: &Frame<'_>,
    encoder: &mut wgpu::CommandEncoder,
    t: &KBufferTargets,
    visible: &[ScanId],
    mut clock: Option<&mut PhaseClock>,
) {
    // `prepare` made the targets, so the device has the k-buffer's pipelines.
    let (Some(KBufferPipelines { merge, .. }), Some(composite)) = (
        frame.pipelines.kbuffer.as_ref(),
        frame.outputs.composite_kbuffer.as_ref(),
    ) else {
        return;
    };
    let mut checkpoint = |encoder: &mut wgpu::CommandEncoder, phase| {
        if let Some(clock) = clock.as_deref_mut() {
            clock.checkpoint(frame, encoder, phase);
        }
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
            depth_stencil_attachment: frame.depth_attachment(),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&frame.pipelines.prepass);
        frame.draw_scans(&mut pass, visible);
    }
    checkpoint(encoder, Phase::Prepass);
    // 2. Scans a batch at a time into the layers, each batch merged into the k-buffer.
    encoder.clear_buffer(&t.kbuffer, 0, None);
    for (b, chunk) in visible.chunks(t.shape.batch as usize).enumerate() {
        let offset = KBufferTargets::slot_offset(b as u32);
        frame.queue.write_buffer(
            &t.batch_uniform,
            u64::from(offset),
            bytemuck::bytes_of(&[chunk.len() as u32, 0, 0, 0]),
        );
        for (l, &id) in chunk.iter().enumerate() {
            frame.encode_layer(
                encoder,
                &t.layers.colour_layers[l],
                &t.layers.data_layers[l],
                id,
            );
        }
        checkpoint(encoder, Phase::Layers);
        // The pass needs an attachment: the depth buffer, neither tested nor written.
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("merge"),
            color_attachments: &[],
            depth_stencil_attachment: frame.depth_attachment(),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(merge);
        pass.set_bind_group(0, &t.merge_bind_group, &[offset]);
        pass.draw(0..3, 0..1);
        drop(pass);
        checkpoint(encoder, Phase::Merge);
    }
    // 3. Composite into the target.
    frame.encode_composite(encoder, composite, &t.composite_bind_group);
    checkpoint(encoder, Phase::Composite);
}
