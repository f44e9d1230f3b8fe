//! One frame's view of the renderer's long-lived state, lent to the strategy that
//! records the frame, and the passes the strategies share: drawing scans, one scan
//! into one per-scan layer, and a full-screen composite into the target.

use std::collections::BTreeMap;

use texel::model::ScanId;

use super::{PlacedScan, RenderSettings, RenderTarget};
use crate::gpu::pipelines::{OutputPipelines, Pipelines};
use crate::gpu::targets::DepthTarget;

/// What a strategy may use while it records a frame; the uniforms are written.
pub(super) struct Frame<'a> {
    pub device: &'a wgpu::Device,
    pub queue: &'a wgpu::Queue,
    pub pipelines: &'a Pipelines,
    /// The pipelines writing into this frame's target format.
    pub outputs: &'a OutputPipelines,
    pub frame_bind_group: &'a wgpu::BindGroup,
    /// Sized for the target.
    pub depth: &'a DepthTarget,
    pub scans: &'a BTreeMap<ScanId, PlacedScan>,
    pub settings: &'a RenderSettings,
    pub target: RenderTarget<'a>,
}

impl<'a> Frame<'a> {
    /// The depth buffer, cleared (reverse z: to 0, the far plane) at the start of the
    /// pass and not kept after it.
    pub fn depth_attachment(&self) -> Option<wgpu::RenderPassDepthStencilAttachment<'a>> {
        Some(wgpu::RenderPassDepthStencilAttachment {
            view: &self.depth.depth.view,
            depth_ops: Some(wgpu::Operations {
                load: wgpu::LoadOp::Clear(0.0),
                store: wgpu::StoreOp::Discard,
            }),
            stencil_ops: None,
        })
    }

    /// The depth buffer kept after the pass, starting from `load`: the k-buffer's
    /// layer passes clear it only where their scan draws.
    pub fn depth_kept(
        &self,
        load: wgpu::LoadOp<f32>,
    ) -> Option<wgpu::RenderPassDepthStencilAttachment<'a>> {
        Some(wgpu::RenderPassDepthStencilAttachment {
            view: &self.depth.depth.view,
            depth_ops: Some(wgpu::Operations {
                load,
                store: wgpu::StoreOp::Store,
            }),
            stencil_ops: None,
        })
    }

    /// The depth buffer and its stencil kept after the pass, starting from `load` and
    /// `stencil_load`: the k-buffer's layer passes mark the pixels their scans draw.
    /// Without a stencil (`gpu::marks_supported`), the depth buffer alone.
    pub fn depth_stencil_kept(
        &self,
        load: wgpu::LoadOp<f32>,
        stencil_load: wgpu::LoadOp<u32>,
    ) -> Option<wgpu::RenderPassDepthStencilAttachment<'a>> {
        Some(wgpu::RenderPassDepthStencilAttachment {
            view: &self.depth.depth.view,
            depth_ops: Some(wgpu::Operations {
                load,
                store: wgpu::StoreOp::Store,
            }),
            stencil_ops: self.depth.has_stencil().then_some(wgpu::Operations {
                load: stencil_load,
                store: wgpu::StoreOp::Store,
            }),
        })
    }

    /// Draws `ids` with the pass's pipeline, in the order given.
    pub fn draw_scans(&self, pass: &mut wgpu::RenderPass<'_>, ids: &[ScanId]) {
        pass.set_bind_group(0, self.frame_bind_group, &[]);
        for id in ids {
            let Some(placed) = self.scans.get(id) else {
                continue;
            };
            let (indices, count) = placed
                .gpu
                .indices(self.settings.keep_stretched, self.settings.coarse);
            if count == 0 {
                continue;
            }
            pass.set_bind_group(1, &placed.gpu.bind_group, &[]);
            pass.set_vertex_buffer(0, placed.gpu.vertices.slice(..));
            pass.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
            pass.draw_indexed(0..count, 0, 0..1);
        }
    }

    /// The background as the target stores it.
    pub fn clear_colour(&self) -> wgpu::Color {
        let format = self.target.format;
        let bg = self.settings.composite.background.map(|c| {
            let c = f64::from(c.clamp(0.0, 1.0));
            if format.is_srgb() {
                // Display values: the target encodes linear ones.
                if c <= 0.04045 {
                    c / 12.92
                } else {
                    ((c + 0.055) / 1.055).powf(2.4)
                }
            } else {
                c
            }
        });
        wgpu::Color {
            r: bg[0],
            g: bg[1],
            b: bg[2],
            a: 1.0,
        }
    }

    /// One scan into one layer (colour + data), with its own depth test.
    pub fn encode_layer(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        colour: &wgpu::TextureView,
        data: &wgpu::TextureView,
        id: ScanId,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("scan layer"),
            color_attachments: &[cleared(colour), cleared(data)],
            depth_stencil_attachment: self.depth_attachment(),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipelines.layer);
        self.draw_scans(&mut pass, &[id]);
    }

    /// A full-screen composite into the target, cleared to the background first.
    pub fn encode_composite(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::RenderPipeline,
        bind_group: &wgpu::BindGroup,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("composite"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: self.target.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(self.clear_colour()),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        pass.draw(0..3, 0..1);
    }
}

/// A layer attachment kept as it is (the k-buffer clears only the part a scan wrote).
pub(super) fn kept(view: &wgpu::TextureView) -> Option<wgpu::RenderPassColorAttachment<'_>> {
    Some(wgpu::RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations {
            load: wgpu::LoadOp::Load,
            store: wgpu::StoreOp::Store,
        },
    })
}

/// A layer attachment cleared to "no fragment" (transparent, all zero).
pub(super) fn cleared(view: &wgpu::TextureView) -> Option<wgpu::RenderPassColorAttachment<'_>> {
    Some(wgpu::RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations {
            load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
            store: wgpu::StoreOp::Store,
        },
    })
}
