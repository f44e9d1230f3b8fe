//! The painter strategy, the baseline the paper improves on: one depth-tested pass
//! draws every visible scan's textured mesh straight into the target. It owns no
//! targets beyond the shared depth buffer.

use texel::model::ScanId;

use super::frame::Frame;

/// Records the painter's single pass into the frame's target.
pub(super) fn encode(frame: &Frame<'_>, encoder: &mut wgpu::CommandEncoder, visible: &[ScanId]) {
    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("painter"),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view: frame.target.view,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations {
                load: wgpu::LoadOp::Clear(frame.clear_colour()),
                store: wgpu::StoreOp::Store,
            },
        })],
        depth_stencil_attachment: frame.depth_attachment(),
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    pass.set_pipeline(&frame.outputs.painter);
    frame.draw_scans(&mut pass, visible);
}
