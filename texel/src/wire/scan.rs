//! `ScanAdded`: a texel scan on the wire (mesh, texture coordinates, per-triangle
//! accuracy and flags, the compressed texture, pose, centre of projection, range
//! noise), with every index and value checked on decoding so a client can trust it.
//!
//! Two ways in: the owned [`WireScan`] (what the decoder yields; encoding one checks
//! everything, as decoding does), and [`WireScanRef`], which borrows a [`TexelScan`]'s
//! arrays and an encoded texture so a server writes the frame straight from the scan,
//! after [`check_sendable`] checked the scan's arrays once where it was made. Both
//! write their bytes with the same code.

use std::sync::Arc;

use super::bytes_in::{BodyReader, PutLe};
use super::{LENGTH_PREFIX, WireError, finish_frame, kind, put_pose, read_pose};
use crate::camera::MAX_IMAGE_SIDE;
use crate::capture::{decode_compressed, encode_compressed};
use crate::frames::EoFrame;
use crate::model::ScanId;
use crate::pose::{Pose, pose_to_parts};
use crate::scan::{NO_VERTEX, TexelScan, TriangleFlags};
use crate::sensor::RangeNoise;

/// The largest lidar grid side (as TXL1 allows).
pub const MAX_GRID_SIDE: u32 = 1024;
/// The largest texture payload (a 4096 x 4096 RGB8 image is 48 MiB).
pub const MAX_TEXTURE_BYTES: usize = 96 * 1024 * 1024;
const MAX_VERTICES: usize = (MAX_GRID_SIDE * MAX_GRID_SIDE) as usize;
/// Two triangles per cell of the largest grid.
const MAX_TRIANGLES: usize = 2 * ((MAX_GRID_SIDE - 1) * (MAX_GRID_SIDE - 1)) as usize;
/// Bytes of a `ScanAdded` body besides its arrays and texture bytes: id 8, two poses
/// 2 x 56, timestamp 8, seq, grid width and height 3 x 4, centre of projection 24,
/// range noise 16, vertex and triangle counts 2 x 4, texture format 1, width and
/// height 2 x 4, timestamp 8, data length 4.
const FIXED_FIELDS_LEN: usize = 8 + 2 * 56 + 8 + 3 * 4 + 24 + 16 + 2 * 4 + 1 + 2 * 4 + 8 + 4;
/// Wire bytes per vertex: position 12, texture coordinates 8, textured 1, pixel 4.
const VERTEX_LEN: usize = 12 + 8 + 1 + 4;
/// Wire bytes per triangle: indices 12, accuracy 4, flags 1.
const TRIANGLE_LEN: usize = 12 + 4 + 1;

/// How the texture travels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TextureFormat {
    /// Uncompressed RGB8, `3 * width * height` bytes: exact, for local viewers.
    Rgb8,
    /// Lossless PNG.
    Png,
    /// JPEG (lossy): the default; a fifth of PNG's size on a camera-like image.
    Jpeg,
}

impl TextureFormat {
    fn code(self) -> u8 {
        match self {
            Self::Rgb8 => 0,
            Self::Png => 1,
            Self::Jpeg => 2,
        }
    }

    fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Self::Rgb8),
            1 => Some(Self::Png),
            2 => Some(Self::Jpeg),
            _ => None,
        }
    }
}

/// A scan's texture as it travels: the declared size and the (compressed) bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Texture {
    pub format: TextureFormat,
    pub width: u32,
    pub height: u32,
    pub timestamp_ns: u64,
    pub data: Vec<u8>,
}

impl Texture {
    /// Compresses an EO frame (`jpeg_quality` 1-100, used for JPEG only).
    pub fn encode(
        frame: &EoFrame,
        format: TextureFormat,
        jpeg_quality: u8,
    ) -> Result<Self, WireError> {
        if !frame.is_consistent() {
            return Err(WireError::encode(
                "Texture",
                "RGB buffer does not match its size",
            ));
        }
        let data = match format {
            TextureFormat::Rgb8 => frame.rgb.clone(),
            TextureFormat::Png | TextureFormat::Jpeg => {
                let name = if format == TextureFormat::Png {
                    "png"
                } else {
                    "jpeg"
                };
                encode_compressed(
                    &frame.rgb,
                    frame.width,
                    frame.height,
                    name,
                    jpeg_quality.clamp(1, 100),
                )
                .map_err(|e| WireError::encode("Texture", e.to_string()))?
            }
        };
        if data.len() > MAX_TEXTURE_BYTES {
            return Err(WireError::encode(
                "Texture",
                format!("{} bytes exceed {MAX_TEXTURE_BYTES}", data.len()),
            ));
        }
        Ok(Self {
            format,
            width: frame.width,
            height: frame.height,
            timestamp_ns: frame.timestamp_ns,
            data,
        })
    }

    /// The RGB8 frame. A compressed image's own header must declare the texture's
    /// size before any pixel is decoded, so decoding allocates no more than the
    /// declared (and bounded) size.
    pub fn decode(&self) -> Result<EoFrame, WireError> {
        if let Some(format) = match self.format {
            TextureFormat::Rgb8 => None,
            TextureFormat::Png => Some(image::ImageFormat::Png),
            TextureFormat::Jpeg => Some(image::ImageFormat::Jpeg),
        } {
            let dims = image::ImageReader::with_format(std::io::Cursor::new(&self.data), format)
                .into_dimensions()
                .map_err(|e| WireError::invalid("Texture", e.to_string()))?;
            if dims != (self.width, self.height) {
                return Err(WireError::invalid(
                    "Texture",
                    format!(
                        "the image header says {}x{}, the message {}x{}",
                        dims.0, dims.1, self.width, self.height
                    ),
                ));
            }
        }
        let (w, h, rgb) = match self.format {
            TextureFormat::Rgb8 => (self.width, self.height, self.data.clone()),
            TextureFormat::Png => decode_compressed("png", &self.data)
                .map_err(|e| WireError::invalid("Texture", e.to_string()))?,
            TextureFormat::Jpeg => decode_compressed("jpeg", &self.data)
                .map_err(|e| WireError::invalid("Texture", e.to_string()))?,
        };
        if (w, h) != (self.width, self.height) || rgb.len() != 3 * w as usize * h as usize {
            return Err(WireError::invalid(
                "Texture",
                format!(
                    "decoded {w}x{h} ({} bytes), declared {}x{}",
                    rgb.len(),
                    self.width,
                    self.height
                ),
            ));
        }
        Ok(EoFrame {
            width: w,
            height: h,
            rgb,
            timestamp_ns: self.timestamp_ns,
            exposure: None,
        })
    }

    /// The texture borrowed, as a [`WireScanRef`] carries it.
    pub fn view(&self) -> TextureRef<'_> {
        TextureRef {
            format: self.format,
            width: self.width,
            height: self.height,
            timestamp_ns: self.timestamp_ns,
            data: &self.data,
        }
    }
}

/// A texture as it travels, its bytes borrowed (from a [`Texture`], or from an EO
/// frame's own pixels for a raw RGB8 texture, which then need no copy of their own).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TextureRef<'a> {
    pub format: TextureFormat,
    pub width: u32,
    pub height: u32,
    pub timestamp_ns: u64,
    pub data: &'a [u8],
}

impl<'a> TextureRef<'a> {
    /// An EO frame's pixels as a raw RGB8 texture, without copying them.
    pub fn rgb8(frame: &'a EoFrame) -> Result<Self, WireError> {
        if !frame.is_consistent() {
            return Err(WireError::encode(
                "Texture",
                "RGB buffer does not match its size",
            ));
        }
        if frame.rgb.len() > MAX_TEXTURE_BYTES {
            return Err(WireError::encode(
                "Texture",
                format!("{} bytes exceed {MAX_TEXTURE_BYTES}", frame.rgb.len()),
            ));
        }
        Ok(Self {
            format: TextureFormat::Rgb8,
            width: frame.width,
            height: frame.height,
            timestamp_ns: frame.timestamp_ns,
            data: &frame.rgb,
        })
    }

    /// The rules the decoder enforces on a texture's header: a size within
    /// [`MAX_IMAGE_SIDE`], raw RGB8 of exactly that size, at most
    /// [`MAX_TEXTURE_BYTES`].
    fn check(&self) -> Result<(), WireError> {
        check_texture_size(self.width, self.height)?;
        if self.format == TextureFormat::Rgb8
            && self.data.len() != 3 * self.width as usize * self.height as usize
        {
            return Err(WireError::invalid(
                "ScanAdded",
                format!(
                    "rgb8 texture of {} bytes for {}x{}",
                    self.data.len(),
                    self.width,
                    self.height
                ),
            ));
        }
        if self.data.len() > MAX_TEXTURE_BYTES {
            return Err(WireError::invalid(
                "ScanAdded",
                format!(
                    "texture of {} bytes exceeds {MAX_TEXTURE_BYTES}",
                    self.data.len()
                ),
            ));
        }
        Ok(())
    }
}

fn check_texture_size(width: u32, height: u32) -> Result<(), WireError> {
    if width == 0 || height == 0 || width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(WireError::invalid(
            "ScanAdded",
            format!("texture size {width}x{height}"),
        ));
    }
    Ok(())
}

/// A scan's fields as `ScanAdded` carries them, its arrays borrowed: from a
/// [`TexelScan`] where the scan was made, or from a [`WireScan`].
#[derive(Debug, Clone, Copy)]
struct ScanFields<'a> {
    timestamp_ns: u64,
    seq: u32,
    grid_width: u32,
    grid_height: u32,
    scan_from_lidar: Pose,
    cop_m: [f64; 3],
    range_noise: RangeNoise,
    vertices: &'a [[f32; 3]],
    tex_coords: &'a [[f32; 2]],
    vertex_textured: &'a [bool],
    vertex_pixel: &'a [u32],
    triangles: &'a [[u32; 3]],
    triangle_accuracy: &'a [f32],
    triangle_flags: &'a [TriangleFlags],
}

impl<'a> ScanFields<'a> {
    fn of_scan(scan: &'a TexelScan) -> Self {
        Self {
            timestamp_ns: scan.timestamp_ns,
            seq: scan.seq,
            grid_width: scan.grid_width,
            grid_height: scan.grid_height,
            scan_from_lidar: scan.scan_from_lidar,
            cop_m: scan.cop_m,
            range_noise: scan.range_noise,
            vertices: &scan.vertices,
            tex_coords: &scan.tex_coords,
            vertex_textured: &scan.vertex_textured,
            vertex_pixel: &scan.vertex_pixel,
            triangles: &scan.triangles,
            triangle_accuracy: &scan.triangle_accuracy,
            triangle_flags: &scan.triangle_flags,
        }
    }

    /// The decoder's rules that cost nothing per element: the grid, the counts, the
    /// arrays' lengths, the centre of projection, range noise and lidar pose. The
    /// frame's layout depends on them, so they are checked whenever a frame is written.
    fn check_layout(&self) -> Result<(), WireError> {
        let bad = |m: String| Err(WireError::invalid("ScanAdded", m));
        if self.grid_width > MAX_GRID_SIDE || self.grid_height > MAX_GRID_SIDE {
            return bad(format!(
                "grid {}x{} exceeds {MAX_GRID_SIDE} per side",
                self.grid_width, self.grid_height
            ));
        }
        let pixels = self.grid_width as usize * self.grid_height as usize;
        let n = self.vertices.len();
        if n > pixels {
            return bad(format!("{n} vertices for a grid of {pixels} pixels"));
        }
        if self.tex_coords.len() != n
            || self.vertex_textured.len() != n
            || self.vertex_pixel.len() != n
        {
            return bad("per-vertex arrays differ in length".into());
        }
        let m = self.triangles.len();
        if m > MAX_TRIANGLES || self.triangle_accuracy.len() != m || self.triangle_flags.len() != m
        {
            return bad("per-triangle arrays differ in length or exceed the limit".into());
        }
        let noise = [self.range_noise.sigma_m, self.range_noise.sigma_per_m];
        if self
            .cop_m
            .iter()
            .chain(noise.iter())
            .any(|v| !v.is_finite())
            || noise.iter().any(|&v| v < 0.0)
        {
            return bad("non-finite centre of projection or invalid range noise".into());
        }
        // The decoder refuses a non-finite pose as it reads it; checked here too so a
        // scan `check_sendable` lets through cannot fail to encode on its own pose.
        let (t, q) = pose_to_parts(&self.scan_from_lidar);
        if t.iter().chain(q.iter()).any(|v| !v.is_finite()) {
            return bad("non-finite scan_from_lidar pose".into());
        }
        Ok(())
    }

    /// The decoder's rules on the arrays' values: pixels within the grid, indices
    /// within the vertices, finite coordinates, accuracies in [0, 1], known flags.
    /// One pass over each array, allocating nothing unless it fails.
    fn check_values(&self) -> Result<(), WireError> {
        let bad = |m: String| Err(WireError::invalid("ScanAdded", m));
        let pixels = self.grid_width as usize * self.grid_height as usize;
        let n = self.vertices.len();
        if let Some(p) = self.vertex_pixel.iter().find(|&&p| p as usize >= pixels) {
            return bad(format!("vertex pixel {p} outside the {pixels}-pixel grid"));
        }
        if let Some(t) = self
            .triangles
            .iter()
            .find(|t| t.iter().any(|&i| i as usize >= n))
        {
            return bad(format!("triangle {t:?} indexes past {n} vertices"));
        }
        if self.vertices.iter().flatten().any(|v| !v.is_finite())
            || self.tex_coords.iter().flatten().any(|v| !v.is_finite())
        {
            return bad("non-finite vertex or texture coordinate".into());
        }
        if let Some(a) = self
            .triangle_accuracy
            .iter()
            .find(|a| !(0.0..=1.0).contains(*a))
        {
            return bad(format!("triangle accuracy {a} outside [0, 1]"));
        }
        let known = TriangleFlags::STRETCHED | TriangleFlags::DEGENERATE;
        if self.triangle_flags.iter().any(|f| f.0 & !known != 0) {
            return bad("unknown triangle flag bits".into());
        }
        Ok(())
    }
}

/// A `ScanAdded` message that borrows its scan's arrays and its texture's bytes:
/// what a server encodes a scan from, without copying the mesh.
///
/// It checks what costs nothing per element (sizes, counts, array lengths, the
/// texture's header, finite values of the header); the arrays' values are checked
/// once, where the scan is made, by [`check_sendable`]. A scan that skipped that
/// check still encodes safely, but possibly into a frame the decoder refuses.
#[derive(Debug, Clone, Copy)]
pub struct WireScanRef<'a> {
    id: ScanId,
    world_from_scan: Pose,
    fields: ScanFields<'a>,
    texture: TextureRef<'a>,
}

impl<'a> WireScanRef<'a> {
    /// Scan `id` at `world_from_scan` with `texture` (compressed elsewhere, or the
    /// scan's own pixels through [`TextureRef::rgb8`]), which should declare the scan
    /// texture's size. `scan` must have passed [`check_sendable`].
    pub fn new(
        id: ScanId,
        scan: &'a TexelScan,
        world_from_scan: Pose,
        texture: TextureRef<'a>,
    ) -> Result<Self, WireError> {
        let view = Self {
            id,
            world_from_scan,
            fields: ScanFields::of_scan(scan),
            texture,
        };
        view.check_layout()
            .map_err(|e| WireError::encode("ScanAdded", e.to_string()))?;
        Ok(view)
    }

    fn check_layout(&self) -> Result<(), WireError> {
        self.fields.check_layout()?;
        self.texture.check()
    }

    /// The exact length of the whole frame (length prefix included).
    pub fn frame_len(&self) -> usize {
        LENGTH_PREFIX + 1 + self.body_fields_len()
    }

    /// Bytes after the kind byte.
    fn body_fields_len(&self) -> usize {
        FIXED_FIELDS_LEN
            + self.fields.vertices.len() * VERTEX_LEN
            + self.fields.triangles.len() * TRIANGLE_LEN
            + self.texture.data.len()
    }

    /// The whole `ScanAdded` frame, in one allocation of exactly its length; refused
    /// beyond [`super::MAX_SERVER_FRAME_LEN`] or at a non-finite pose.
    pub fn encode(&self) -> Result<Vec<u8>, WireError> {
        let mut out = Vec::with_capacity(self.frame_len());
        out.extend_from_slice(&[0u8; LENGTH_PREFIX]);
        out.put_u8(kind::SCAN_ADDED);
        self.write_fields(&mut out)?;
        finish_frame(out, "ScanAdded")
    }

    /// Writes the fields after the kind byte; the one writer of a `ScanAdded` body.
    fn write_fields(&self, out: &mut Vec<u8>) -> Result<(), WireError> {
        let f = &self.fields;
        out.reserve(self.body_fields_len());
        out.put_u64(self.id);
        put_pose(out, "ScanAdded.world_from_scan", &self.world_from_scan)?;
        out.put_u64(f.timestamp_ns);
        out.put_u32(f.seq);
        out.put_u32(f.grid_width);
        out.put_u32(f.grid_height);
        put_pose(out, "ScanAdded.scan_from_lidar", &f.scan_from_lidar)?;
        for v in f.cop_m {
            out.put_f64(v);
        }
        out.put_f64(f.range_noise.sigma_m);
        out.put_f64(f.range_noise.sigma_per_m);
        // Counts fit: checked against the grid (at most 1024 x 1024) and the limits.
        out.put_u32(f.vertices.len() as u32);
        for v in f.vertices.iter().flatten() {
            out.put_f32(*v);
        }
        for v in f.tex_coords.iter().flatten() {
            out.put_f32(*v);
        }
        for &t in f.vertex_textured {
            out.put_u8(u8::from(t));
        }
        for &p in f.vertex_pixel {
            out.put_u32(p);
        }
        out.put_u32(f.triangles.len() as u32);
        for i in f.triangles.iter().flatten() {
            out.put_u32(*i);
        }
        for a in f.triangle_accuracy {
            out.put_f32(*a);
        }
        for flags in f.triangle_flags {
            out.put_u8(flags.0);
        }
        let t = &self.texture;
        out.put_u8(t.format.code());
        out.put_u32(t.width);
        out.put_u32(t.height);
        out.put_u64(t.timestamp_ns);
        out.put_bytes(t.data);
        Ok(())
    }
}

/// A scan as it travels in a `ScanAdded` message.
#[derive(Debug, Clone, PartialEq)]
pub struct WireScan {
    pub id: ScanId,
    pub world_from_scan: Pose,
    pub timestamp_ns: u64,
    pub seq: u32,
    pub grid_width: u32,
    pub grid_height: u32,
    pub scan_from_lidar: Pose,
    pub cop_m: [f64; 3],
    pub range_noise: RangeNoise,
    pub vertices: Vec<[f32; 3]>,
    pub tex_coords: Vec<[f32; 2]>,
    pub vertex_textured: Vec<bool>,
    pub vertex_pixel: Vec<u32>,
    pub triangles: Vec<[u32; 3]>,
    pub triangle_accuracy: Vec<f32>,
    pub triangle_flags: Vec<TriangleFlags>,
    pub texture: Texture,
}

impl WireScan {
    /// The wire form of scan `id` at `world_from_scan`, its texture compressed.
    pub fn from_scan(
        id: ScanId,
        scan: &TexelScan,
        world_from_scan: Pose,
        format: TextureFormat,
        jpeg_quality: u8,
    ) -> Result<Self, WireError> {
        let texture = Texture::encode(&scan.texture, format, jpeg_quality)?;
        Self::with_texture(id, scan, world_from_scan, texture)
    }

    /// The wire form of scan `id` with a texture compressed elsewhere (a faster
    /// encoder); it must declare the scan texture's size.
    pub fn with_texture(
        id: ScanId,
        scan: &TexelScan,
        world_from_scan: Pose,
        texture: Texture,
    ) -> Result<Self, WireError> {
        let wire = Self {
            id,
            world_from_scan,
            timestamp_ns: scan.timestamp_ns,
            seq: scan.seq,
            grid_width: scan.grid_width,
            grid_height: scan.grid_height,
            scan_from_lidar: scan.scan_from_lidar,
            cop_m: scan.cop_m,
            range_noise: scan.range_noise,
            vertices: scan.vertices.clone(),
            tex_coords: scan.tex_coords.clone(),
            vertex_textured: scan.vertex_textured.clone(),
            vertex_pixel: scan.vertex_pixel.clone(),
            triangles: scan.triangles.clone(),
            triangle_accuracy: scan.triangle_accuracy.clone(),
            triangle_flags: scan.triangle_flags.clone(),
            texture,
        };
        wire.validate()
            .map_err(|e| WireError::encode("ScanAdded", e.to_string()))?;
        Ok(wire)
    }

    /// The bytes a `ScanAdded` frame of this scan takes at most, its texture as raw
    /// RGB (a compressed texture is smaller in practice, but never counted on).
    pub fn rgb8_frame_bound(scan: &TexelScan) -> usize {
        256 + scan.vertices.len() * 25 + scan.triangles.len() * 17 + scan.texture.rgb.len()
    }

    /// The texel scan this message carries (texture decoded, the pixel-to-vertex map
    /// rebuilt), with its id and pose.
    pub fn into_scan(self) -> Result<(ScanId, TexelScan, Pose), WireError> {
        let texture = self.texture.decode()?;
        Ok(self.assemble(texture))
    }

    /// The scan's geometry alone: [`Self::into_scan`] with an empty (0 x 0) texture,
    /// the encoded one left undecoded. For what needs the mesh only (coverage
    /// signatures), without the cost of decoding an image.
    pub fn into_geometry(self) -> (ScanId, TexelScan, Pose) {
        let texture = EoFrame {
            width: 0,
            height: 0,
            rgb: Vec::new(),
            timestamp_ns: self.timestamp_ns,
            exposure: None,
        };
        self.assemble(texture)
    }

    fn assemble(self, texture: EoFrame) -> (ScanId, TexelScan, Pose) {
        let pixels = self.grid_width as usize * self.grid_height as usize;
        let mut pixel_vertex = vec![NO_VERTEX; pixels];
        for (v, &p) in self.vertex_pixel.iter().enumerate() {
            // Checked on decoding: p < pixels and v < vertex count <= u32::MAX.
            if let Some(slot) = pixel_vertex.get_mut(p as usize) {
                *slot = v as u32;
            }
        }
        let scan = TexelScan {
            timestamp_ns: self.timestamp_ns,
            seq: self.seq,
            grid_width: self.grid_width,
            grid_height: self.grid_height,
            vertices: self.vertices,
            tex_coords: self.tex_coords,
            vertex_textured: self.vertex_textured,
            vertex_pixel: self.vertex_pixel,
            pixel_vertex,
            triangles: self.triangles,
            triangle_accuracy: self.triangle_accuracy,
            triangle_flags: self.triangle_flags,
            texture: Arc::new(texture),
            cop_m: self.cop_m,
            scan_from_lidar: self.scan_from_lidar,
            range_noise: self.range_noise,
        };
        (self.id, scan, self.world_from_scan)
    }

    /// The message borrowed, as the encoder writes it.
    pub fn view(&self) -> WireScanRef<'_> {
        WireScanRef {
            id: self.id,
            world_from_scan: self.world_from_scan,
            fields: ScanFields {
                timestamp_ns: self.timestamp_ns,
                seq: self.seq,
                grid_width: self.grid_width,
                grid_height: self.grid_height,
                scan_from_lidar: self.scan_from_lidar,
                cop_m: self.cop_m,
                range_noise: self.range_noise,
                vertices: &self.vertices,
                tex_coords: &self.tex_coords,
                vertex_textured: &self.vertex_textured,
                vertex_pixel: &self.vertex_pixel,
                triangles: &self.triangles,
                triangle_accuracy: &self.triangle_accuracy,
                triangle_flags: &self.triangle_flags,
            },
            texture: self.texture.view(),
        }
    }

    /// The rules the decoder enforces, also applied before encoding.
    fn validate(&self) -> Result<(), WireError> {
        let view = self.view();
        view.check_layout()?;
        view.fields.check_values()
    }

    /// Writes the fields after the kind byte, everything checked first (a message
    /// built by hand may break any rule).
    pub(super) fn encode_into(&self, out: &mut Vec<u8>) -> Result<(), WireError> {
        self.validate()
            .map_err(|e| WireError::encode("ScanAdded", e.to_string()))?;
        self.view().write_fields(out)
    }

    pub(super) fn decode(body: &[u8]) -> Result<Self, WireError> {
        let mut r = BodyReader::new(body, "ScanAdded");
        let id = r.u64("id")?;
        let world_from_scan = read_pose(&mut r, "world_from_scan")?;
        let timestamp_ns = r.u64("timestamp_ns")?;
        let seq = r.u32("seq")?;
        let grid_width = r.u32("grid_width")?;
        let grid_height = r.u32("grid_height")?;
        if grid_width > MAX_GRID_SIDE || grid_height > MAX_GRID_SIDE {
            return Err(WireError::invalid(
                "ScanAdded",
                format!("grid {grid_width}x{grid_height} exceeds {MAX_GRID_SIDE} per side"),
            ));
        }
        let scan_from_lidar = read_pose(&mut r, "scan_from_lidar")?;
        let cop_m = [r.f64("cop_m")?, r.f64("cop_m")?, r.f64("cop_m")?];
        let range_noise = RangeNoise {
            sigma_m: r.f64("range_noise")?,
            sigma_per_m: r.f64("range_noise")?,
        };
        // 12 + 8 + 1 + 4 bytes per vertex.
        let max_vertices = (grid_width as usize * grid_height as usize).min(MAX_VERTICES);
        let n = r.count("vertex_count", 25, max_vertices)?;
        let vertices = r.vec(n, "vertices", 12, |r| {
            Ok([r.f32("vertices")?, r.f32("vertices")?, r.f32("vertices")?])
        })?;
        let tex_coords = r.vec(n, "tex_coords", 8, |r| {
            Ok([r.f32("tex_coords")?, r.f32("tex_coords")?])
        })?;
        let vertex_textured = r.vec(n, "vertex_textured", 1, |r| {
            match r.u8("vertex_textured")? {
                0 => Ok(false),
                1 => Ok(true),
                b => Err(WireError::invalid(
                    "ScanAdded",
                    format!("vertex_textured byte {b} is not 0 or 1"),
                )),
            }
        })?;
        let vertex_pixel = r.vec(n, "vertex_pixel", 4, |r| r.u32("vertex_pixel"))?;
        // 12 + 4 + 1 bytes per triangle.
        let m = r.count("triangle_count", 17, MAX_TRIANGLES)?;
        let triangles = r.vec(m, "triangles", 12, |r| {
            Ok([
                r.u32("triangles")?,
                r.u32("triangles")?,
                r.u32("triangles")?,
            ])
        })?;
        let triangle_accuracy = r.vec(m, "triangle_accuracy", 4, |r| r.f32("triangle_accuracy"))?;
        let triangle_flags = r.vec(m, "triangle_flags", 1, |r| {
            Ok(TriangleFlags(r.u8("triangle_flags")?))
        })?;
        let format_code = r.u8("texture.format")?;
        let format = TextureFormat::from_code(format_code).ok_or_else(|| {
            WireError::invalid("ScanAdded", format!("unknown texture format {format_code}"))
        })?;
        let width = r.u32("texture.width")?;
        let height = r.u32("texture.height")?;
        let texture_timestamp_ns = r.u64("texture.timestamp_ns")?;
        let len = r.count("texture.data", 1, MAX_TEXTURE_BYTES)?;
        let data = r.take(len, "texture.data")?.to_vec();
        r.finish()?;
        let scan = Self {
            id,
            world_from_scan,
            timestamp_ns,
            seq,
            grid_width,
            grid_height,
            scan_from_lidar,
            cop_m,
            range_noise,
            vertices,
            tex_coords,
            vertex_textured,
            vertex_pixel,
            triangles,
            triangle_accuracy,
            triangle_flags,
            texture: Texture {
                format,
                width,
                height,
                timestamp_ns: texture_timestamp_ns,
                data,
            },
        };
        scan.validate()?;
        Ok(scan)
    }
}

/// Whether `scan` can be streamed at all: everything the decoder checks, with the
/// texture as raw RGB (which needs no compression and so cannot fail to encode), and
/// the frame within [`super::MAX_SERVER_FRAME_LEN`]. A scan that passes always encodes
/// at a finite pose, whatever happens to its compressed texture. Made where the scan
/// is made, once: [`WireScanRef`] relies on it. Allocates nothing unless it fails.
pub fn check_sendable(scan: &TexelScan) -> Result<(), WireError> {
    let bound = WireScan::rgb8_frame_bound(scan);
    if bound > super::MAX_SERVER_FRAME_LEN as usize {
        return Err(WireError::encode(
            "ScanAdded",
            format!(
                "a frame of up to {bound} bytes exceeds the limit {}",
                super::MAX_SERVER_FRAME_LEN
            ),
        ));
    }
    if !scan.texture.is_consistent() {
        return Err(WireError::encode(
            "Texture",
            "RGB buffer does not match its size",
        ));
    }
    // The texture's declared size only: its RGB size was checked just above, and a
    // compressed texture's bytes are checked where it is compressed.
    let fields = ScanFields::of_scan(scan);
    fields
        .check_layout()
        .and_then(|()| check_texture_size(scan.texture.width, scan.texture.height))
        .and_then(|()| fields.check_values())
        .map_err(|e| WireError::encode("ScanAdded", e.to_string()))
}
