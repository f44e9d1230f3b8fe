//! The k-buffer strategy (bounded memory): its size-dependent targets (a pre-pass
//! target with the nearest valid distance and its sigma, `batch` per-scan layers of
//! 16 bytes a pixel (reliability, distance, sigma, packed colour), and
//! a storage buffer with the k best fragments of every pixel) and a frame's passes:
//! the pre-pass, scans a batch at a time into the layers with each batch merged into
//! the k-buffer, then the composite. Optionally timed phase by phase.
//!
//! A scan covers part of the screen, so each layer is cleared and drawn, and each batch
//! merged, only inside the scans' conservative pixel rectangles (`crate::footprint`):
//! on a software rasteriser the full-screen clears and merges were most of a frame.
//! Within its rectangle, a batch is merged only at the pixels where one of its scans
//! kept a fragment: the layer passes write the batch's mark into the stencil there,
//! and the merge's stencil test, forced before its shader, skips the rest (the sky,
//! the ground beyond a scan's view). Where the device lacks the features for it
//! (`gpu::MARK_FEATURES`), the whole rectangle is merged, with the same result.

// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::Instant;

use texel::model::ScanId;

use super::frame::{Frame, cleared, kept};
use crate::footprint::PixelRect;
use crate::gpu::pipelines::{KBufferPipelines, Pipelines};
use crate::gpu::targets::{TargetMemory, Texture, pixels, texture};
use crate::gpu::{GpuError, LAYER_DATA_FORMAT, NEAREST_FORMAT};

/// Bytes of one k-buffer entry (packed colour, reliability, scan id).
const KBUFFER_ENTRY_BYTES: u64 = 12;
/// Bytes of one packed layer texel.
const LAYER_BYTES: u64 = 16;
/// Layers a batch may hold: the per-batch uniform has a scan id for each.
pub(super) const MAX_BATCH: u32 = 64;
/// The per-batch uniform (`merge.wgsl`'s `Batch`): the layer count, then the scan id of
/// each layer.
const BATCH_UNIFORM_BYTES: u64 = 16 + 4 * MAX_BATCH as u64;
/// Dynamic-offset stride of the per-batch uniform (a multiple of the 256-byte offset
/// alignment).
const BATCH_UNIFORM_STRIDE: u64 = BATCH_UNIFORM_BYTES.next_multiple_of(256);

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
    /// One attachment view per layer (the views keep the layers' texture alive).
    layer_views: Vec<wgpu::TextureView>,
    kbuffer: wgpu::Buffer,
    batch_uniform: wgpu::Buffer,
    /// Batches the per-batch uniform has room for.
    batch_slots: u32,
    merge_bind_group: wgpu::BindGroup,
    composite_bind_group: wgpu::BindGroup,
    /// Merge only where a layer of the batch marked the stencil (`Renderer::merge_marks`).
    pub marked: bool,
    /// Per layer: the rectangle outside which it holds no fragment (`None`: all of it
    /// is clear), so the next scan drawn into it clears only that and its own.
    dirty: Vec<Option<PixelRect>>,
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
        let layers = texture(
            device,
            "k-buffer layers",
            width,
            height,
            batch,
            LAYER_DATA_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            true,
        );
        let layer_views = (0..batch)
            .map(|l| {
                layers.texture.create_view(&wgpu::TextureViewDescriptor {
                    dimension: Some(wgpu::TextureViewDimension::D2),
                    base_array_layer: l,
                    array_layer_count: Some(1),
                    ..Default::default()
                })
            })
            .collect();
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
                    resource: wgpu::BindingResource::TextureView(&layers.view),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: kbuffer.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &batch_uniform,
                        offset: 0,
                        size: wgpu::BufferSize::new(BATCH_UNIFORM_BYTES),
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
            layer_views,
            kbuffer,
            batch_uniform,
            batch_slots,
            merge_bind_group,
            composite_bind_group,
            dirty: vec![None; batch as usize],
            marked: true,
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
            layers: pixels(self.shape.width, self.shape.height)
                * u64::from(self.shape.batch)
                * LAYER_BYTES,
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
) -> Result<&'a mut KBufferTargets, GpuError> {
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

/// A scan drawn into a layer and the pixels it can draw there.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Layered {
    pub id: ScanId,
    /// `None`: the whole target, cleared and merged as a whole (no footprints).
    pub rect: Option<PixelRect>,
}

/// Orders the layered scans along a Morton curve of their rectangles' centres, so a
/// batch's scans lie near each other on screen and its merge covers little more than
/// they do. Changes no pixel: fragments are ranked by a total order (reliability, then
/// scan id), whatever the batches.
pub(super) fn order_on_screen(layered: &mut [Layered]) {
    layered.sort_by_key(|l| {
        let (x, y) = l.rect.map_or((0, 0), |r| r.centre());
        (morton(x / 16, y / 16), l.id)
    });
}

/// Interleaves the low 16 bits of `x` and `y` (x in the even bits).
fn morton(x: u32, y: u32) -> u32 {
    let spread = |v: u32| {
        let mut v = v & 0xFFFF;
        v = (v | (v << 8)) & 0x00FF_00FF;
        v = (v | (v << 4)) & 0x0F0F_0F0F;
        v = (v | (v << 2)) & 0x3333_3333;
        (v | (v << 1)) & 0x5555_5555
    };
    spread(x) | (spread(y) << 1)
}

/// Records the k-buffer's passes for `visible` into the frame's target: every visible
/// scan into the pre-pass, those in `layered` (in that order) into the layers.
pub(super) fn encode(
    frame: &Frame<'_>,
    encoder: &mut wgpu::CommandEncoder,
    t: &mut KBufferTargets,
    visible: &[ScanId],
    layered: &[Layered],
    mut clock: Option<&mut PhaseClock>,
) {
    let mut checkpoint = |encoder: &mut wgpu::CommandEncoder, phase| {
        if let Some(clock) = clock.as_deref_mut() {
            clock.checkpoint(frame, encoder, phase);
        }
    };
    // 1. Pre-pass: the nearest valid fragment's distance and sigma per pixel.
    encode_prepass(frame, encoder, t, visible, true);
    checkpoint(encoder, Phase::Prepass);
    // 2. Scans a batch at a time into the layers, each batch merged into the k-buffer.
    clear_kbuffer(encoder, t);
    for (b, chunk) in layered.chunks(t.shape.batch as usize).enumerate() {
        encode_layers(frame, encoder, t, b, chunk);
        checkpoint(encoder, Phase::Layers);
        encode_merge(frame, encoder, t, b, chunk);
        checkpoint(encoder, Phase::Merge);
    }
    // 3. Composite into the target.
    encode_composite(frame, encoder, t);
    checkpoint(encoder, Phase::Composite);
}

/// The scans a progressive frame's pre-pass step draws (a frame drawn over several
/// submissions, `super::progressive`): on a software rasteriser about as long as one
/// batch of layers and its merge.
pub(super) const PREPASS_SCANS_PER_STEP: usize = 16;

/// The pre-pass for `scans`: the nearest valid fragment's distance and sigma per pixel
/// (Killpack & Budge 2016, Algorithm 2, steps 1-2). `first`: the frame's first
/// pre-pass, which clears the nearest target and the depth buffer; later ones (a
/// progressive frame's) add their scans to what is there, with the same result as
/// one pass over all (the depth test keeps the first drawn of equal depths).
pub(super) fn encode_prepass(
    frame: &Frame<'_>,
    encoder: &mut wgpu::CommandEncoder,
    t: &KBufferTargets,
    scans: &[ScanId],
    first: bool,
) {
    let infinity = f64::from(f32::INFINITY.to_bits());
    let (load, depth_load) = if first {
        (
            wgpu::LoadOp::Clear(wgpu::Color {
                r: infinity,
                g: 0.0,
                b: 0.0,
                a: 0.0,
            }),
            wgpu::LoadOp::Clear(0.0),
        )
    } else {
        (wgpu::LoadOp::Load, wgpu::LoadOp::Load)
    };
    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("pre-pass"),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view: &t.nearest.view,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations {
                load,
                store: wgpu::StoreOp::Store,
            },
        })],
        // Kept: the layer passes clear it only inside their rectangles. The stencil
        // starts at 0, which no batch's mark is.
        depth_stencil_attachment: if first {
            frame.depth_stencil_kept(depth_load, wgpu::LoadOp::Clear(0))
        } else {
            frame.depth_kept(depth_load)
        },
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    pass.set_pipeline(&frame.pipelines.prepass);
    frame.draw_scans(&mut pass, scans);
}

/// Empties every pixel's list of best fragments (before the first batch).
pub(super) fn clear_kbuffer(encoder: &mut wgpu::CommandEncoder, t: &KBufferTargets) {
    encoder.clear_buffer(&t.kbuffer, 0, None);
}

/// Batch `b`'s scans into the layers.
pub(super) fn encode_layers(
    frame: &Frame<'_>,
    encoder: &mut wgpu::CommandEncoder,
    t: &mut KBufferTargets,
    b: usize,
    chunk: &[Layered],
) {
    // `prepare` made the targets, so the device has the k-buffer's pipelines.
    let Some(pipelines) = frame.pipelines.kbuffer.as_ref() else {
        return;
    };
    let offset = KBufferTargets::slot_offset(b as u32);
    let mut uniform = [0u32; BATCH_UNIFORM_BYTES as usize / 4];
    uniform[0] = chunk.len() as u32;
    for (slot, scan) in uniform[4..].iter_mut().zip(chunk) {
        // As the scan's own uniform gives it to the shaders.
        *slot = u32::try_from(scan.id).unwrap_or(u32::MAX);
    }
    frame.queue.write_buffer(
        &t.batch_uniform,
        u64::from(offset),
        bytemuck::bytes_of(&uniform),
    );
    if b > 0 && b.is_multiple_of(MARKS) && frame.depth.has_stencil() {
        // The marks wrap around: start the stencil from 0 again.
        drop(encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("stencil clear"),
            color_attachments: &[],
            depth_stencil_attachment:
                frame.depth_stencil_kept(wgpu::LoadOp::Load, wgpu::LoadOp::Clear(0)),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        }));
    }
    for (l, scan) in chunk.iter().enumerate() {
        encode_layer(frame, encoder, t, pipelines, l, scan, mark(b));
    }
}

/// Distinct stencil marks before they wrap around.
const MARKS: usize = 255;

/// Batch `b`'s stencil mark: the value its layer passes write where a scan keeps a
/// fragment, so its merge runs only there (1 to 255; 0 is the cleared stencil).
fn mark(b: usize) -> u32 {
    (b % MARKS) as u32 + 1
}

/// Folds batch `b`'s layers into the k-buffer (Algorithm 2, step 3, a batch at a time).
pub(super) fn encode_merge(
    frame: &Frame<'_>,
    encoder: &mut wgpu::CommandEncoder,
    t: &KBufferTargets,
    b: usize,
    chunk: &[Layered],
) {
    let Some(pipelines) = frame.pipelines.kbuffer.as_ref() else {
        return;
    };
    let offset = KBufferTargets::slot_offset(b as u32);
    // The pass needs an attachment: the depth buffer, neither tested nor written.
    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("merge"),
        color_attachments: &[],
        depth_stencil_attachment: frame.depth_kept(wgpu::LoadOp::Load),
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    if t.marked && frame.depth.has_stencil() {
        pass.set_pipeline(&pipelines.merge_marked);
        pass.set_stencil_reference(mark(b));
    } else {
        pass.set_pipeline(&pipelines.merge);
    }
    pass.set_bind_group(0, &t.merge_bind_group, &[offset]);
    // Outside the batch's rectangles no layer holds a fragment.
    let rects = chunk.iter().map(|s| s.rect);
    if let Some(Some(r)) = rects.reduce(|a, b| a.zip(b).map(|(a, b)| a.union(&b))) {
        pass.set_scissor_rect(r.x, r.y, r.width, r.height);
    }
    pass.draw(0..3, 0..1);
}

/// Shades every pixel from its k-buffer entries into the frame's target (step 4).
pub(super) fn encode_composite(
    frame: &Frame<'_>,
    encoder: &mut wgpu::CommandEncoder,
    t: &KBufferTargets,
) {
    if let Some(composite) = frame.outputs.composite_kbuffer.as_ref() {
        frame.encode_composite(encoder, composite, &t.composite_bind_group);
    }
}

/// One scan into layer `l`. With a rectangle: clears what the layer's previous scan
/// wrote and the rectangle, then draws the scan there. Without: clears the whole
/// layer and the depth buffer first.
fn encode_layer(
    frame: &Frame<'_>,
    encoder: &mut wgpu::CommandEncoder,
    t: &mut KBufferTargets,
    pipelines: &KBufferPipelines,
    l: usize,
    scan: &Layered,
    mark: u32,
) {
    let view = &t.layer_views[l];
    let Some(rect) = scan.rect else {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("scan layer"),
            color_attachments: &[cleared(view)],
            depth_stencil_attachment: frame
                .depth_stencil_kept(wgpu::LoadOp::Clear(0.0), wgpu::LoadOp::Load),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&pipelines.layer);
        pass.set_stencil_reference(mark);
        frame.draw_scans(&mut pass, &[scan.id]);
        // The scan may have drawn anywhere.
        t.dirty[l] = Some(PixelRect::full(t.shape.width, t.shape.height));
        return;
    };
    let clear = t.dirty[l].map_or(rect, |d| d.union(&rect));
    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("scan layer"),
        color_attachments: &[kept(view)],
        depth_stencil_attachment: frame.depth_stencil_kept(wgpu::LoadOp::Load, wgpu::LoadOp::Load),
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    pass.set_pipeline(&pipelines.clear_layer);
    pass.set_scissor_rect(clear.x, clear.y, clear.width, clear.height);
    pass.draw(0..3, 0..1);
    pass.set_pipeline(&pipelines.layer);
    pass.set_stencil_reference(mark);
    pass.set_scissor_rect(rect.x, rect.y, rect.width, rect.height);
    frame.draw_scans(&mut pass, &[scan.id]);
    t.dirty[l] = Some(rect);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_interleaves_x_and_y() {
        assert_eq!(morton(0, 0), 0);
        assert_eq!(morton(1, 0), 1);
        assert_eq!(morton(0, 1), 2);
        assert_eq!(morton(3, 3), 15);
        assert_eq!(morton(0xFFFF, 0), 0x5555_5555);
    }

    #[test]
    fn nearby_rectangles_share_batches() {
        let at = |id, x, y| Layered {
            id,
            rect: Some(PixelRect {
                x,
                y,
                width: 10,
                height: 10,
            }),
        };
        // Two clusters on screen, interleaved by id.
        let mut l = vec![at(0, 0, 0), at(1, 600, 400), at(2, 20, 10), at(3, 610, 420)];
        order_on_screen(&mut l);
        let ids: Vec<ScanId> = l.iter().map(|s| s.id).collect();
        assert_eq!(ids, vec![0, 2, 1, 3]);
    }
}
