//! A per-view depth map of the point proxy (Lechelek et al. 2019 §4) on the GPU: the
//! size-dependent targets (pass 1's splat depth and normal, pass 2's front and back
//! images, the depth buffer, the pull-push pyramid) and the passes that fill a given
//! depth map from a list of scans' points. The virtual view renders one per frame;
//! every acquisition view gets one once, from its own points.

use bytemuck::{Pod, Zeroable};
use glam::{UVec4, Vec4};

use super::pipelines::{POINT_DEPTH_FORMAT, POINT_NORMAL_FORMAT, PointsPipelines};
use super::scan::GpuPoints;
use crate::gpu::DEPTH_FORMAT;
use crate::gpu::targets::{Texture, pixels, texture};

/// `PointsView` in `points.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct PointsViewUniform {
    pub intrinsics: Vec4,
    pub shape: Vec4,
}

/// `LevelPair` in `points_fill.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct LevelPairUniform {
    pub fine: UVec4,
    pub coarse: UVec4,
}

/// The pinhole a depth map is drawn through.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthMapView {
    /// fx, fy, cx, cy (pixel centres at integers).
    pub intrinsics: [f32; 4],
    /// Points sit at their texture coordinates (an acquisition view of its own scan).
    pub at_texture_coordinates: bool,
}

/// The pull-push pyramid's levels: (offset in pixels, width, height), finest first,
/// down to 1 x 1.
pub fn pyramid(width: u32, height: u32) -> Vec<(u32, u32, u32)> {
    let mut levels = vec![(0, width.max(1), height.max(1))];
    while let Some(&(offset, w, h)) = levels.last() {
        if w <= 1 && h <= 1 {
            break;
        }
        levels.push((offset + w * h, w.div_ceil(2), h.div_ceil(2)));
    }
    levels
}

pub(crate) struct DepthMapTargets {
    pub width: u32,
    pub height: u32,
    splat_z: Texture,
    /// Only the virtual view's colour pass needs normals.
    splat_normal: Texture,
    front: Texture,
    back: Texture,
    depth: Texture,
    levels: wgpu::Buffer,
    level_pairs: wgpu::Buffer,
    level_stride: u64,
    pyramid: Vec<(u32, u32, u32)>,
    view_uniforms: [wgpu::Buffer; 2],
    /// group 1 with the class scatter keeps: front, then back.
    view_bind_groups: [wgpu::BindGroup; 2],
    pub bytes: u64,
}

impl DepthMapTargets {
    pub fn new(
        device: &wgpu::Device,
        pipelines: &PointsPipelines,
        width: u32,
        height: u32,
        with_normals: bool,
    ) -> Self {
        let rw = wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING;
        let map = |label| {
            texture(
                device,
                label,
                width,
                height,
                1,
                POINT_DEPTH_FORMAT,
                rw,
                false,
            )
        };
        let (nw, nh) = if with_normals {
            (width, height)
        } else {
            (1, 1)
        };
        let splat_normal = texture(
            device,
            "points normal",
            nw,
            nh,
            1,
            POINT_NORMAL_FORMAT,
            rw,
            false,
        );
        let depth = texture(
            device,
            "points depth",
            width,
            height,
            1,
            DEPTH_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
            false,
        );
        let pyramid = pyramid(width, height);
        let texels: u64 = pyramid.iter().map(|&(_, w, h)| pixels(w, h)).sum();
        let levels = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("points pull-push levels"),
            size: texels * 16,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        let align = u64::from(device.limits().min_uniform_buffer_offset_alignment).max(1);
        let level_stride = (std::mem::size_of::<LevelPairUniform>() as u64).next_multiple_of(align);
        let mut pairs = vec![0u8; (level_stride * pyramid.len() as u64) as usize];
        for (i, &(offset, w, h)) in pyramid.iter().enumerate() {
            let (co, cw, ch) = pyramid.get(i + 1).copied().unwrap_or((offset, w, h));
            let pair = LevelPairUniform {
                fine: UVec4::new(offset, w, h, 0),
                coarse: UVec4::new(co, cw, ch, 0),
            };
            let at = i * level_stride as usize;
            pairs[at..at + std::mem::size_of::<LevelPairUniform>()]
                .copy_from_slice(bytemuck::bytes_of(&pair));
        }
        let level_pairs = wgpu::util::DeviceExt::create_buffer_init(
            device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("points pull-push level pairs"),
                contents: &pairs,
                usage: wgpu::BufferUsages::UNIFORM,
            },
        );
        let view_uniform = || {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("points view"),
                size: std::mem::size_of::<PointsViewUniform>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let view_uniforms = [view_uniform(), view_uniform()];
        let view_bind_group = |buffer: &wgpu::Buffer| {
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("points view"),
                layout: &pipelines.view_layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: buffer.as_entire_binding(),
                }],
            })
        };
        let view_bind_groups = [
            view_bind_group(&view_uniforms[0]),
            view_bind_group(&view_uniforms[1]),
        ];
        let bytes = pixels(width, height) * (3 * 4 + 4)
            + pixels(nw, nh) * 8
            + texels * 16
            + level_pairs.size();
        Self {
            width,
            height,
            splat_z: map("points splat depth"),
            splat_normal,
            front: map("points front"),
            back: map("points back"),
            depth,
            levels,
            level_pairs,
            level_stride,
            pyramid,
            view_uniforms,
            view_bind_groups,
            bytes,
        }
    }

    /// Sets the pinhole the next encoded depth map is drawn through (takes effect at
    /// the next submit: one view per submit).
    pub fn write_view(&self, queue: &wgpu::Queue, view: &DepthMapView) {
        for (buffer, class) in self.view_uniforms.iter().zip([1.0, 0.0]) {
            let uniform = PointsViewUniform {
                intrinsics: Vec4::from_array(view.intrinsics),
                shape: Vec4::new(
                    self.width as f32,
                    self.height as f32,
                    if view.at_texture_coordinates {
                        1.0
                    } else {
                        0.0
                    },
                    class,
                ),
            };
            queue.write_buffer(buffer, 0, bytemuck::bytes_of(&uniform));
        }
    }

    /// The view bind group whose class is front (the splat and colour passes ignore
    /// the class).
    pub fn view_bind_group(&self) -> &wgpu::BindGroup {
        &self.view_bind_groups[0]
    }

    /// Group 3 of the scatter and colour passes, with `resolved` as the filled map.
    pub fn targets_bind_group(
        &self,
        device: &wgpu::Device,
        pipelines: &PointsPipelines,
        resolved: &wgpu::TextureView,
    ) -> wgpu::BindGroup {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("points targets"),
            layout: &pipelines.targets_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&self.splat_z.view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&self.splat_normal.view),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::TextureView(resolved),
                },
            ],
        })
    }

    fn attachment<'a>(view: &'a wgpu::TextureView) -> Option<wgpu::RenderPassColorAttachment<'a>> {
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

    fn depth_attachment(&self) -> Option<wgpu::RenderPassDepthStencilAttachment<'_>> {
        Some(wgpu::RenderPassDepthStencilAttachment {
            view: &self.depth.view,
            depth_ops: Some(wgpu::Operations {
                load: wgpu::LoadOp::Clear(0.0),
                store: wgpu::StoreOp::Discard,
            }),
            stencil_ops: None,
        })
    }

    /// Passes 1 to 5 into `resolved` (`POINT_DEPTH_FORMAT`, this size, storage):
    /// splat, scatter front and back, pull-push both, keep where pass 1 drew. Returns
    /// group 3 for a colour pass that reads the result.
    #[allow(clippy::too_many_arguments)]
    pub fn encode(
        &self,
        device: &wgpu::Device,
        pipelines: &PointsPipelines,
        encoder: &mut wgpu::CommandEncoder,
        frame_bind_group: &wgpu::BindGroup,
        scans: &[&GpuPoints],
        with_normals: bool,
        resolved: &wgpu::TextureView,
    ) -> wgpu::BindGroup {
        let targets = self.targets_bind_group(device, pipelines, resolved);
        // Pass 1: the splats, nearest kept.
        {
            let colour = if with_normals {
                vec![
                    Self::attachment(&self.splat_z.view),
                    Self::attachment(&self.splat_normal.view),
                ]
            } else {
                vec![Self::attachment(&self.splat_z.view)]
            };
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("points splat"),
                color_attachments: &colour,
                depth_stencil_attachment: self.depth_attachment(),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(if with_normals {
                &pipelines.splat_depth_normal
            } else {
                &pipelines.splat_depth
            });
            pass.set_bind_group(0, frame_bind_group, &[]);
            pass.set_bind_group(1, &self.view_bind_groups[0], &[]);
            for scan in scans {
                pass.set_bind_group(2, &scan.bind_group, &[]);
                pass.set_vertex_buffer(0, scan.points.slice(..));
                pass.draw(0..6, 0..scan.count);
            }
        }
        // Pass 2: every centre into the front or the back image, nearest kept.
        for (class, image) in [&self.front, &self.back].into_iter().enumerate() {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("points scatter"),
                color_attachments: &[Self::attachment(&image.view)],
                depth_stencil_attachment: self.depth_attachment(),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&pipelines.scatter);
            pass.set_bind_group(0, frame_bind_group, &[]);
            pass.set_bind_group(1, &self.view_bind_groups[class], &[]);
            pass.set_bind_group(3, &targets, &[]);
            for scan in scans {
                pass.set_bind_group(2, &scan.bind_group, &[]);
                pass.set_vertex_buffer(0, scan.points.slice(..));
                pass.draw(0..scan.count, 0..1);
            }
        }
        // Passes 3 to 5: pull-push both classes, keep where pass 1 drew.
        let fill = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("points fill"),
            layout: &pipelines.fill_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: self.levels.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &self.level_pairs,
                        offset: 0,
                        size: wgpu::BufferSize::new(std::mem::size_of::<LevelPairUniform>() as u64),
                    }),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::TextureView(&self.front.view),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: wgpu::BindingResource::TextureView(&self.back.view),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: wgpu::BindingResource::TextureView(&self.splat_z.view),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: wgpu::BindingResource::TextureView(resolved),
                },
            ],
        });
        let groups = |w: u32, h: u32| (w.div_ceil(8), h.div_ceil(8));
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("points pull-push"),
            timestamp_writes: None,
        });
        let offset = |level: usize| (level as u64 * self.level_stride) as u32;
        let (_, w0, h0) = self.pyramid[0];
        pass.set_pipeline(&pipelines.fill_load);
        pass.set_bind_group(0, &fill, &[offset(0)]);
        let (gx, gy) = groups(w0, h0);
        pass.dispatch_workgroups(gx, gy, 1);
        let last = self.pyramid.len().saturating_sub(1);
        pass.set_pipeline(&pipelines.fill_pull);
        for level in 0..last {
            let (_, w, h) = self.pyramid[level + 1];
            pass.set_bind_group(0, &fill, &[offset(level)]);
            let (gx, gy) = groups(w, h);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        pass.set_pipeline(&pipelines.fill_push);
        for level in (0..last).rev() {
            let (_, w, h) = self.pyramid[level];
            pass.set_bind_group(0, &fill, &[offset(level)]);
            let (gx, gy) = groups(w, h);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        pass.set_pipeline(&pipelines.fill_resolve);
        pass.set_bind_group(0, &fill, &[offset(0)]);
        pass.dispatch_workgroups(gx, gy, 1);
        drop(pass);
        targets
    }
}

/// A filled depth map texture of this size (the virtual view's, or an acquisition
/// view's kept with its scan).
pub(crate) fn depth_map_texture(
    device: &wgpu::Device,
    label: &str,
    width: u32,
    height: u32,
) -> Texture {
    texture(
        device,
        label,
        width,
        height,
        1,
        POINT_DEPTH_FORMAT,
        wgpu::TextureUsages::STORAGE_BINDING
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC,
        false,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pyramid_halves_down_to_one_pixel() {
        assert_eq!(
            pyramid(5, 3),
            vec![(0, 5, 3), (15, 3, 2), (21, 2, 1), (23, 1, 1)]
        );
        assert_eq!(pyramid(1, 1), vec![(0, 1, 1)]);
        assert_eq!(pyramid(0, 0), vec![(0, 1, 1)]);
    }
}
