//! Reading GPU images back: a rendered frame as an RGBA image, and the naive
//! per-scan layers as fragments for the CPU reference composite.

use texel::model::ScanId;

use super::renderer::{RenderSettings, RenderTarget, Renderer, Strategy};
use super::{GpuError, IMAGE_FORMAT};
use crate::camera::VirtualCamera;
use crate::composite::Fragment;

/// The per-scan layers of one frame as read back.
#[derive(Debug, Clone)]
pub struct LayerReadback {
    pub width: u32,
    pub height: u32,
    /// The scans in layer order (ascending id).
    pub scans: Vec<ScanId>,
    /// Per layer: RGBA8 colour, row-major.
    pub colour: Vec<Vec<u8>>,
    /// Per layer: (reliability, distance, sigma, scan id) bits, row-major.
    pub data: Vec<Vec<[u32; 4]>>,
}

impl LayerReadback {
    /// The fragments at a pixel, one per layer that has one.
    pub fn fragments_at(&self, x: u32, y: u32) -> Vec<Fragment> {
        let i = (y * self.width + x) as usize;
        self.colour
            .iter()
            .zip(&self.data)
            .filter_map(|(colour, data)| {
                let d = data.get(i)?;
                let reliability = f32::from_bits(d[0]);
                if reliability <= 0.0 {
                    return None;
                }
                let c = colour.get(4 * i..4 * i + 3)?;
                Some(Fragment {
                    colour: [c[0], c[1], c[2]].map(|v| f32::from(v) / 255.0),
                    reliability,
                    distance_m: f32::from_bits(d[1]),
                    sigma_m: f32::from_bits(d[2]),
                    scan: d[3],
                })
            })
            .collect()
    }
}

/// Copies `layers` layers of a texture into one buffer (rows padded to 256 bytes).
fn copy_texture(
    device: &wgpu::Device,
    encoder: &mut wgpu::CommandEncoder,
    texture: &wgpu::Texture,
    layers: u32,
    bytes_per_pixel: u32,
) -> (wgpu::Buffer, u32) {
    let size = texture.size();
    let row = (size.width * bytes_per_pixel).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
        * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read-back"),
        size: u64::from(row) * u64::from(size.height) * u64::from(layers),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(size.height),
            },
        },
        wgpu::Extent3d {
            width: size.width,
            height: size.height,
            depth_or_array_layers: layers,
        },
    );
    (buffer, row)
}

/// Maps a buffer and returns its rows without padding, per layer.
fn map_rows(
    device: &wgpu::Device,
    buffer: &wgpu::Buffer,
    row: u32,
    width_bytes: u32,
    height: u32,
    layers: u32,
) -> Result<Vec<Vec<u8>>, GpuError> {
    let slice = buffer.slice(..);
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    rx.recv()
        .map_err(|e| GpuError::Readback(e.to_string()))?
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    let mapped = slice
        .get_mapped_range()
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    let per_layer = row as usize * height as usize;
    let out = (0..layers as usize)
        .map(|l| {
            let layer = &mapped[l * per_layer..(l + 1) * per_layer];
            layer
                .chunks_exact(row as usize)
                .flat_map(|r| &r[..width_bytes as usize])
                .copied()
                .collect()
        })
        .collect();
    drop(mapped);
    buffer.unmap();
    Ok(out)
}

/// Reads a 2-D colour texture of four bytes a pixel (RGBA8 or BGRA8, either colour
/// space) back as an RGBA image, BGRA swizzled: the one read-back of rendered frames,
/// for headless images and the window's screenshot alike.
pub fn read_rgba_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
) -> Result<image::RgbaImage, GpuError> {
    let size = texture.size();
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
        label: Some("read-back"),
    });
    let (buffer, row) = copy_texture(device, &mut encoder, texture, 1, 4);
    crate::gpu::submit(queue, Some(encoder.finish()));
    let mut rows = map_rows(device, &buffer, row, size.width * 4, size.height, 1)?;
    let mut pixels = rows.pop().unwrap_or_default();
    if matches!(
        texture.format(),
        wgpu::TextureFormat::Bgra8Unorm | wgpu::TextureFormat::Bgra8UnormSrgb
    ) {
        for p in pixels.chunks_exact_mut(4) {
            p.swap(0, 2);
        }
    }
    image::RgbaImage::from_raw(size.width, size.height, pixels)
        .ok_or_else(|| GpuError::Readback("image size mismatch".into()))
}

/// Reads a `Depth32Float` texture (made with `COPY_SRC`) back, row-major.
pub fn read_depth_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
) -> Result<Vec<f32>, GpuError> {
    // One f32 per pixel: the depth buffer, or a depth map (`POINT_DEPTH_FORMAT`).
    let one_float = [
        wgpu::TextureFormat::Depth32Float,
        crate::gpu::points::POINT_DEPTH_FORMAT,
    ];
    if !one_float.contains(&texture.format()) {
        return Err(GpuError::Readback(format!(
            "depth read-back of a {:?} texture",
            texture.format()
        )));
    }
    let size = texture.size();
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
        label: Some("depth read-back"),
    });
    let (buffer, row) = copy_texture(device, &mut encoder, texture, 1, 4);
    crate::gpu::submit(queue, Some(encoder.finish()));
    let rows = map_rows(device, &buffer, row, size.width * 4, size.height, 1)?;
    let bytes = rows.into_iter().next().unwrap_or_default();
    Ok(bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

/// Reads a `RADIANCE_FORMAT` (Rgba16Float) texture back as f32 RGBA, row-major.
pub fn read_radiance_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
) -> Result<Vec<[f32; 4]>, GpuError> {
    if texture.format() != super::RADIANCE_FORMAT {
        return Err(GpuError::Readback(format!(
            "radiance read-back of a {:?} texture",
            texture.format()
        )));
    }
    let size = texture.size();
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
        label: Some("radiance read-back"),
    });
    let (buffer, row) = copy_texture(device, &mut encoder, texture, 1, 8);
    crate::gpu::submit(queue, Some(encoder.finish()));
    let rows = map_rows(device, &buffer, row, size.width * 8, size.height, 1)?;
    let bytes = rows.into_iter().next().unwrap_or_default();
    Ok(bytes
        .chunks_exact(8)
        .map(|p| {
            std::array::from_fn(|c| {
                half::f16::from_bits(u16::from_le_bytes([p[2 * c], p[2 * c + 1]])).to_f32()
            })
        })
        .collect())
}

impl Renderer {
    /// Renders a frame into an offscreen RGBA8 image (the headless path: the same
    /// passes as the window, into a texture instead of a swapchain image).
    pub fn render_to_image(
        &mut self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
    ) -> Result<(image::RgbaImage, super::FrameStats), GpuError> {
        let (width, height) = (camera.width, camera.height);
        let texture = super::image_texture(
            &self.device,
            "headless target",
            width,
            height,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let stats = self.render(
            camera,
            settings,
            &RenderTarget {
                view: &view,
                format: IMAGE_FORMAT,
                width,
                height,
            },
        )?;
        let image = read_rgba_texture(&self.device, &self.queue, &texture)?;
        Ok((image, stats))
    }

    /// Renders the naive per-scan layers for `camera` and reads them back, with the
    /// composite image of the same frame (for the CPU reference comparison).
    pub fn read_layers(
        &mut self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
    ) -> Result<(LayerReadback, image::RgbaImage), GpuError> {
        let mut naive = settings.clone();
        naive.strategy = Strategy::NaiveLayers;
        let (image, _) = self.render_to_image(camera, &naive)?;
        let (scans, _) = self.cull(camera, &naive);
        let Some(t) = self.naive.as_ref() else {
            return Err(GpuError::Readback("no layers were rendered".into()));
        };
        let layers = (scans.len() as u32).max(1);
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("layers"),
            });
        let (colour_buf, colour_row) = copy_texture(
            &self.device,
            &mut encoder,
            &t.layers.colour.texture,
            layers,
            4,
        );
        let (data_buf, data_row) = copy_texture(
            &self.device,
            &mut encoder,
            &t.layers.data.texture,
            layers,
            16,
        );
        crate::gpu::submit(&self.queue, Some(encoder.finish()));
        let (w, h) = (camera.width, camera.height);
        let colour = map_rows(&self.device, &colour_buf, colour_row, w * 4, h, layers)?;
        let data = map_rows(&self.device, &data_buf, data_row, w * 16, h, layers)?
            .into_iter()
            .map(|bytes| {
                bytes
                    .chunks_exact(16)
                    .map(|c| {
                        let word =
                            |k: usize| u32::from_le_bytes([c[k], c[k + 1], c[k + 2], c[k + 3]]);
                        [word(0), word(4), word(8), word(12)]
                    })
                    .collect()
            })
            .collect();
        let n = scans.len();
        Ok((
            LayerReadback {
                width: w,
                height: h,
                scans,
                colour: colour.into_iter().take(n).collect(),
                data: Vec::<Vec<[u32; 4]>>::into_iter(data).take(n).collect(),
            },
            image,
        ))
    }
}
