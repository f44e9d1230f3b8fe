//! One scan's point proxy on the GPU, built once when the `points` mode first needs
//! the scan: its points (`points::cloud`), the EO camera fitted to its texture
//! coordinates, a uniform each frame rewrites, and its acquisition view's depth map.
//! The depth map is splatted from the scan's own points at their texture coordinates:
//! lidar and EO camera share their optics, so what the photograph saw at a pixel is
//! what the scan's own range found there, and nothing another scan adds can occlude
//! it (§4's per-photograph depth maps, made from one scan instead of the whole cloud).

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec4};
use texel::radiance::{EoResponse, merge_exposures};
use texel::{PinholeCamera, Pose, RangeNoise, TexelScan};

use super::depth_map::{DepthMapTargets, DepthMapView, depth_map_texture};
use super::pipelines::PointsPipelines;
use crate::gpu::targets::Texture;
use crate::gpu::tonemap::{half_radiance, radiance_texture};
use crate::points::cloud::{ScanPoint, lidar_pitch_rad, scan_points};
use crate::vdtm::gpu::{EoViewUniform, eo_view_uniform_of};

/// Acquisition depth maps are at most this many pixels on their longer side (the EO
/// image divided by a whole factor): the map is splatted from the scan's own returns,
/// so a few pixels per lidar pixel hold all it knows (a 640x480 EO image over a
/// 128x128 lidar gets 320x240, a quarter of the bytes of the full size).
pub const MAX_ACQUISITION_MAP_PX: u32 = 320;

/// `PointsScan` in `points.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct PointsScanUniform {
    pub view_from_scan: Mat4,
    pub eo: EoViewUniform,
    pub noise: Vec4,
}

pub(crate) struct GpuPoints {
    pub points: wgpu::Buffer,
    pub count: u32,
    pub uniform: wgpu::Buffer,
    pub bind_group: wgpu::BindGroup,
    /// The same with the scan's radiance instead of its EO image, once built.
    pub radiance_bind_group: Option<wgpu::BindGroup>,
    /// The EO camera fitted to the scan; `None`: the scan gives depth but no colour.
    pub camera: Option<PinholeCamera>,
    pub noise: RangeNoise,
    pub acquisition_depth: Texture,
    pub bytes: u64,
}

/// The size of an acquisition depth map for an EO image of this size.
pub fn acquisition_map_size(width: u32, height: u32) -> (u32, u32) {
    let factor = width.max(height).div_ceil(MAX_ACQUISITION_MAP_PX).max(1);
    (
        width.div_ceil(factor).max(1),
        height.div_ceil(factor).max(1),
    )
}

/// Group 2 of the points passes: the scan's uniform, the texture its colours come
/// from (the EO image, or its radiance) and its acquisition depth map.
fn scan_bind_group(
    device: &wgpu::Device,
    pipelines: &PointsPipelines,
    uniform: &wgpu::Buffer,
    texture: &wgpu::TextureView,
    acquisition_depth: &wgpu::TextureView,
) -> wgpu::BindGroup {
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("points scan"),
        layout: &pipelines.scan_layout,
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: uniform.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: wgpu::BindingResource::TextureView(texture),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: wgpu::BindingResource::Sampler(&pipelines.sampler),
            },
            wgpu::BindGroupEntry {
                binding: 3,
                resource: wgpu::BindingResource::TextureView(acquisition_depth),
            },
        ],
    })
}

/// The scan's EO frame as radiance (`texel::radiance::merge_exposures`, a bracket of
/// one: `exp(g(z)) / (exposure_time_s · gain)` per channel) in a `RADIANCE_FORMAT`
/// texture whose alpha is the least of the channels' hat weights (0 to 1): a pixel
/// black or saturated in any channel measured nothing there and colours nothing.
/// `None` when the frame does not record its exposure.
fn scan_radiance_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    scan: &TexelScan,
    response: &EoResponse,
) -> Option<wgpu::Texture> {
    let frame: &texel::EoFrame = &scan.texture;
    frame.exposure?;
    let radiance = merge_exposures(&[frame], response).ok()?;
    // The hat weight of one exposure is at most 127.
    let texels: Vec<u16> = radiance
        .rgb
        .iter()
        .zip(&radiance.weight)
        .flat_map(|(c, w)| {
            let alpha = (w[0].min(w[1]).min(w[2]) / 127.0).clamp(0.0, 1.0);
            [c[0], c[1], c[2], alpha].map(half_radiance)
        })
        .collect();
    let texture = radiance_texture(
        device,
        queue,
        "scan radiance",
        frame.width,
        frame.height,
        &texels,
    );
    Some(texture)
}

impl GpuPoints {
    /// Adds the radiance texture and its bind group if the scan's frame records its
    /// exposure and it has none yet; true when the scan has one afterwards.
    pub fn ensure_radiance(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        pipelines: &PointsPipelines,
        scan: &TexelScan,
        response: &EoResponse,
    ) -> bool {
        if self.radiance_bind_group.is_some() {
            return true;
        }
        let Some(texture) = scan_radiance_texture(device, queue, scan, response) else {
            return false;
        };
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        self.radiance_bind_group = Some(scan_bind_group(
            device,
            pipelines,
            &self.uniform,
            &view,
            &self.acquisition_depth.view,
        ));
        self.bytes += u64::from(scan.texture.width) * u64::from(scan.texture.height) * 8;
        true
    }

    /// Builds the scan's points and uniform; the acquisition depth map is filled by
    /// [`GpuPoints::encode_acquisition_depth`].
    pub fn upload(
        device: &wgpu::Device,
        pipelines: &PointsPipelines,
        scan: &TexelScan,
        eo_view: &wgpu::TextureView,
    ) -> Self {
        let points = scan_points(scan, lidar_pitch_rad(scan));
        let camera = crate::live::eo_fit::eo_camera_of_scan(scan).map(|fit| fit.camera);
        let contents: &[u8] = if points.is_empty() {
            &[0u8; std::mem::size_of::<ScanPoint>()]
        } else {
            bytemuck::cast_slice(&points)
        };
        let buffer = wgpu::util::DeviceExt::create_buffer_init(
            device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("scan points"),
                contents,
                usage: wgpu::BufferUsages::VERTEX,
            },
        );
        let uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("points scan uniform"),
            size: std::mem::size_of::<PointsScanUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let (mw, mh) = acquisition_map_size(scan.texture.width, scan.texture.height);
        let acquisition_depth = depth_map_texture(device, "acquisition depth map", mw, mh);
        let bind_group = scan_bind_group(
            device,
            pipelines,
            &uniform,
            eo_view,
            &acquisition_depth.view,
        );
        let bytes = buffer.size() + uniform.size() + u64::from(mw) * u64::from(mh) * 4;
        Self {
            count: points.len() as u32,
            points: buffer,
            uniform,
            bind_group,
            radiance_bind_group: None,
            camera,
            noise: scan.range_noise,
            acquisition_depth,
            bytes,
        }
    }

    /// The acquisition view of the scan's own points: the depth map's pinhole (the
    /// fitted camera scaled to the map; an approximate one without a fit) and the
    /// uniform placing the scan in its own EO frame.
    pub fn write_acquisition(&self, queue: &wgpu::Queue, scan: &TexelScan) -> DepthMapView {
        let (_, mh) = acquisition_map_size(scan.texture.width, scan.texture.height);
        let scale_y = f64::from(mh) / f64::from(scan.texture.height.max(1));
        let fy = self
            .camera
            .as_ref()
            .map_or(f64::from(mh), |c| c.fy * scale_y);
        // The fitted camera's frame is the scan frame (texture coordinates are the
        // scan's vertices projected through it), so depths are the scan frame's z.
        let uniform = PointsScanUniform {
            view_from_scan: Mat4::IDENTITY,
            eo: EoViewUniform::zeroed(),
            noise: self.noise_vec(),
        };
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
        DepthMapView {
            intrinsics: [fy as f32, fy as f32, 0.0, 0.0],
            at_texture_coordinates: true,
        }
    }

    fn noise_vec(&self) -> Vec4 {
        Vec4::new(
            self.noise.sigma_m.max(0.0) as f32,
            self.noise.sigma_per_m.max(0.0) as f32,
            0.0,
            0.0,
        )
    }

    /// This frame's uniform: the scan placed in the virtual view, and its acquisition
    /// camera with the view's frame as the model frame (poses relative to the eye).
    pub fn write_frame(&self, queue: &wgpu::Queue, world_from_view: &Pose, world_from_scan: &Pose) {
        let view_from_scan =
            crate::gpu::gpu_from_pose_relative(&world_from_view.inverse(), world_from_scan);
        let eo = self
            .camera
            .as_ref()
            .map_or_else(EoViewUniform::zeroed, |c| {
                eo_view_uniform_of(c, world_from_scan, world_from_view)
            });
        let uniform = PointsScanUniform {
            view_from_scan,
            eo,
            noise: self.noise_vec(),
        };
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
    }

    /// Fills the acquisition depth map (one submit of its own: the targets' view
    /// uniform is per submit).
    pub fn fill_acquisition_depth(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        pipelines: &PointsPipelines,
        targets: &DepthMapTargets,
        frame_bind_group: &wgpu::BindGroup,
        scan: &TexelScan,
    ) {
        let view = self.write_acquisition(queue, scan);
        targets.write_view(queue, &view);
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("acquisition depth map"),
        });
        targets.encode(
            device,
            pipelines,
            &mut encoder,
            frame_bind_group,
            &[self],
            false,
            &self.acquisition_depth.view,
        );
        crate::gpu::submit(queue, Some(encoder.finish()));
    }
}
