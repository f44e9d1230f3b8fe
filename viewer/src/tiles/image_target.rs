//! The headless tile target: an `IMAGE_FORMAT` colour texture and its depth buffer,
//! read back as an image, and a one-call render of given tiles into one.

use super::cache::GpuTile;
use super::fade::MAX_CUTS;
use super::pass::{PassCounts, PassTarget, TileDraw, TilePass};
use crate::camera::VirtualCamera;
use crate::gpu::{DEPTH_FORMAT, GpuContext, GpuError, IMAGE_FORMAT, RenderTarget};

/// A headless target: an `IMAGE_FORMAT` colour texture and its depth buffer.
pub struct ImageTarget {
    pub width: u32,
    pub height: u32,
    colour: wgpu::Texture,
    colour_view: wgpu::TextureView,
    depth: wgpu::Texture,
    depth_view: wgpu::TextureView,
}

impl ImageTarget {
    pub fn new(gpu: &GpuContext, width: u32, height: u32) -> Result<Self, GpuError> {
        let limit = gpu.device.limits().max_texture_dimension_2d;
        if width == 0 || height == 0 || width > limit || height > limit {
            return Err(GpuError::TargetSize {
                width,
                height,
                limit,
            });
        }
        let texture = |label: &str, format, usage| {
            gpu.device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            })
        };
        let colour = texture(
            "tile image",
            IMAGE_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        // Read back for the coverage feedback (`coverage.rs`).
        let depth = texture(
            "tile depth",
            DEPTH_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        Ok(Self {
            width,
            height,
            colour_view: colour.create_view(&Default::default()),
            depth_view: depth.create_view(&Default::default()),
            depth,
            colour,
        })
    }

    pub fn target(&self) -> RenderTarget<'_> {
        RenderTarget {
            view: &self.colour_view,
            format: IMAGE_FORMAT,
            width: self.width,
            height: self.height,
        }
    }

    pub fn depth_view(&self) -> &wgpu::TextureView {
        &self.depth_view
    }

    pub fn depth_texture(&self) -> &wgpu::Texture {
        &self.depth
    }

    /// The colour texture as an image (waits for the GPU).
    pub fn read(&self, gpu: &GpuContext) -> Result<image::RgbaImage, GpuError> {
        crate::gpu::read_rgba_texture(&gpu.device, &gpu.queue, &self.colour)
    }
}

/// Draws `tiles` (all of them whole, no fade) into a new image: the reference render
/// (e.g. every finest tile) and the pass on its own.
pub fn render_tiles_to_image(
    gpu: &GpuContext,
    pass: &mut TilePass,
    tiles: &[&GpuTile],
    camera: &VirtualCamera,
    background: [f32; 3],
) -> Result<(image::RgbaImage, PassCounts), GpuError> {
    let target = ImageTarget::new(gpu, camera.width, camera.height)?;
    let draws: Vec<TileDraw<'_>> = tiles
        .iter()
        .map(|t| TileDraw {
            tile: t,
            cuts: u32::MAX,
            scan_share: 0.0,
            surface_tolerance_m: 0.0,
            scan_holes_filled: false,
        })
        .collect();
    let mut encoder = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("tiles"),
        });
    let counts = pass.encode(
        &mut encoder,
        &PassTarget {
            colour: target.target(),
            depth: target.depth_view(),
            clear: Some(background),
            scans: None,
        },
        camera,
        &[1.0; MAX_CUTS],
        &draws,
    );
    crate::gpu::submit(&gpu.queue, Some(encoder.finish()));
    Ok((target.read(gpu)?, counts))
}
