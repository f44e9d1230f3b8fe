//! A tile as compact bytes for the wire: positions quantised to 16 bits over the
//! tile's bounds, 8-bit colours, atlas coordinates in eighths of a texel,
//! the atlas as a PNG, and both vertex and index streams through
//! meshoptimizer's codecs (after reordering for its vertex cache and fetch, which is
//! what makes them small). Decoding is bounded and checked: a corrupt or hostile
//! buffer is an error naming what was wrong, never a panic or an index out of range.
//!
//! Layout (little endian): `TXLT`, version u16 (2), lod u8, x i64, y i64, origin
//! 3 × f64, bounds min 3 × f64, bounds max 3 × f64, geometric error f64, voxel f64,
//! merged triangles u32, vertex count u32, triangle count u32, vertex stream length
//! u32, atlas texel f64, atlas PNG length u32 (0: no atlas), the vertex stream, the
//! PNG, the index stream (to the end).
//!
//! The atlas travels as PNG, not JPEG: on the test street's atlases JPEG at quality
//! 90 came out 40 to 60 % larger than PNG (the many small charts' sharp edges are what
//! DCT blocks code worst), and its 8×8 blocks would bleed colour across the one-texel
//! gutters between charts, which lossless PNG keeps to themselves.

use meshopt::{
    decode_index_buffer, decode_vertex_buffer, encode_index_buffer, encode_vertex_buffer,
    optimize_vertex_cache, optimize_vertex_fetch,
};
use std::io::Cursor;

use image::ImageDecoder;
use image::codecs::png::{CompressionType, FilterType, PngDecoder, PngEncoder};
use texel_surface::SurfaceMesh;
use thiserror::Error;

use crate::atlas::{MAX_ATLAS_PX, TileTexture};
use crate::build::LodNode;
use crate::tree::{MAX_LOD, TileId};

const MAGIC: &[u8; 4] = b"TXLT";
const VERSION: u16 = 2;
const HEADER_BYTES: usize = 4 + 2 + 1 + 8 + 8 + 8 * 3 * 3 + 8 + 8 + 4 * 4 + 8 + 4;

/// Largest tile a decoder accepts: far above any budget, bounded before allocation.
pub const MAX_TILE_VERTICES: u32 = 1 << 20;
pub const MAX_TILE_TRIANGLES: u32 = 1 << 21;

#[derive(Debug, Error, PartialEq)]
pub enum TileCodecError {
    #[error("tile bytes: {0} bytes, shorter than the {HEADER_BYTES}-byte header")]
    Truncated(usize),
    #[error("tile bytes: not a tile (magic {0:?})")]
    BadMagic([u8; 4]),
    #[error("tile bytes: version {0}, this reader knows version {VERSION}")]
    Version(u16),
    #[error("tile bytes: {what} is {value}, over the limit {limit}")]
    TooLarge {
        what: &'static str,
        value: u64,
        limit: u64,
    },
    #[error("tile bytes: {0}")]
    Invalid(String),
}

/// One vertex as it travels: position quantised over the bounds, colour, atlas
/// coordinates quantised over [0, 1] (0 without an atlas).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[repr(C)]
struct PackedVertex {
    q: [u16; 4],
    rgba: [u8; 4],
    uv: [u16; 2],
}

/// The atlas image as PNG (RGB, 8 bits); `None` if its size does not match its bytes.
pub fn atlas_png(texture: &TileTexture) -> Option<Vec<u8>> {
    let expected = texture.width as usize * texture.height as usize * 3;
    if texture.width == 0 || texture.height == 0 || texture.rgb.len() != expected {
        return None;
    }
    let mut out = Vec::new();
    // Adaptive filtering: the charts are smooth gradients, which the row filters
    // turn into runs of small numbers.
    let encoder =
        PngEncoder::new_with_quality(&mut out, CompressionType::Best, FilterType::Adaptive);
    image::ImageEncoder::write_image(
        encoder,
        &texture.rgb,
        texture.width,
        texture.height,
        image::ExtendedColorType::Rgb8,
    )
    .ok()?;
    Some(out)
}

/// An atlas image back from PNG bytes: RGB, 8 bits, each side in [1, MAX_ATLAS_PX]
/// (checked before the pixels are allocated).
fn decode_png(bytes: &[u8]) -> Result<(u32, u32, Vec<u8>), TileCodecError> {
    let bad = |e: image::ImageError| TileCodecError::Invalid(format!("atlas image: {e}"));
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_ATLAS_PX);
    limits.max_image_height = Some(MAX_ATLAS_PX);
    limits.max_alloc = Some(u64::from(MAX_ATLAS_PX) * u64::from(MAX_ATLAS_PX) * 4 * 2);
    let decoder = PngDecoder::with_limits(Cursor::new(bytes), limits).map_err(bad)?;
    let (width, height) = decoder.dimensions();
    for (what, side) in [("the atlas width", width), ("the atlas height", height)] {
        if side > MAX_ATLAS_PX {
            return Err(TileCodecError::TooLarge {
                what,
                value: u64::from(side),
                limit: u64::from(MAX_ATLAS_PX),
            });
        }
        if side == 0 {
            return Err(TileCodecError::Invalid(format!("{what} is 0")));
        }
    }
    if decoder.color_type() != image::ColorType::Rgb8 {
        return Err(TileCodecError::Invalid(format!(
            "atlas image of {:?}, not 8-bit RGB",
            decoder.color_type()
        )));
    }
    let mut rgb = vec![0u8; width as usize * height as usize * 3];
    if decoder.total_bytes() != rgb.len() as u64 {
        return Err(TileCodecError::Invalid("atlas image size".into()));
    }
    decoder.read_image(&mut rgb).map_err(bad)?;
    Ok((width, height, rgb))
}

/// The tile as bytes.
pub fn encode_tile(node: &LodNode) -> Vec<u8> {
    let mesh = &node.mesh;
    let n = mesh.vertex_count();
    // Quantise every vertex over the world bounds of its mesh (f64 maths; the scale's
    // degenerate case, a flat extent, keeps its axis at 0).
    let (lo, scale) = quantisation(node);
    // An atlas that cannot be written (or does not match the mesh) is left out: the
    // tile still has its vertex colours.
    let texture = node
        .texture
        .as_ref()
        .filter(|t| t.uvs.len() == n && t.texel_m.is_finite() && t.texel_m > 0.0);
    let png = texture.and_then(atlas_png);
    let texture = texture.filter(|_| png.is_some());
    let png = png.unwrap_or_default();
    let packed: Vec<PackedVertex> = (0..n)
        .map(|v| {
            let w = mesh.world(v).unwrap_or(node.bounds_min_m);
            let c = mesh.colours.get(v).copied().unwrap_or([0; 3]);
            let uv = texture.map_or([0; 2], |t| {
                let uv = t.uvs.get(v).copied().unwrap_or([0.0; 2]);
                [quantise_uv(uv[0], t.width), quantise_uv(uv[1], t.height)]
            });
            PackedVertex {
                q: [
                    quantise(w[0], lo[0], scale[0]),
                    quantise(w[1], lo[1], scale[1]),
                    quantise(w[2], lo[2], scale[2]),
                    0,
                ],
                rgba: [c[0], c[1], c[2], 255],
                uv,
            }
        })
        .collect();
    let flat: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
    let mut indices = optimize_vertex_cache(&flat, n);
    let packed = optimize_vertex_fetch(&mut indices, &packed);
    let vertices = encode_vertex_buffer(&packed).unwrap_or_default();
    let index_bytes = encode_index_buffer(&indices, packed.len()).unwrap_or_default();
    let mut out = Vec::with_capacity(HEADER_BYTES + vertices.len() + png.len() + index_bytes.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.push(node.id.lod);
    out.extend_from_slice(&node.id.x.to_le_bytes());
    out.extend_from_slice(&node.id.y.to_le_bytes());
    for v in mesh
        .origin_m
        .iter()
        .chain(&node.bounds_min_m)
        .chain(&node.bounds_max_m)
        .chain([&node.geometric_error_m, &node.voxel_m])
    {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for v in [
        node.merged_triangles as u32,
        packed.len() as u32,
        mesh.triangle_count() as u32,
        vertices.len() as u32,
    ] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&texture.map_or(0.0, |t| t.texel_m).to_le_bytes());
    out.extend_from_slice(&(png.len() as u32).to_le_bytes());
    out.extend_from_slice(&vertices);
    out.extend_from_slice(&png);
    out.extend_from_slice(&index_bytes);
    out
}

/// The tile back from bytes. Positions come back to within half a quantisation step
/// (the bounds' extent over 65,535) of what was encoded, in the f64 world, relative to
/// the same origin.
pub fn decode_tile(bytes: &[u8]) -> Result<LodNode, TileCodecError> {
    if bytes.len() < HEADER_BYTES {
        return Err(TileCodecError::Truncated(bytes.len()));
    }
    let mut r = Reader { bytes, at: 0 };
    let magic: [u8; 4] = r.array();
    if &magic != MAGIC {
        return Err(TileCodecError::BadMagic(magic));
    }
    let version = u16::from_le_bytes(r.array());
    if version != VERSION {
        return Err(TileCodecError::Version(version));
    }
    let lod = r.array::<1>()[0];
    if lod > MAX_LOD {
        return Err(TileCodecError::Invalid(format!(
            "level {lod} over {MAX_LOD}"
        )));
    }
    let x = i64::from_le_bytes(r.array());
    let y = i64::from_le_bytes(r.array());
    let mut f = [0.0f64; 11];
    for v in &mut f {
        *v = f64::from_le_bytes(r.array());
    }
    if let Some(bad) = f.iter().find(|v| !v.is_finite()) {
        return Err(TileCodecError::Invalid(format!(
            "a non-finite number ({bad}) in the header"
        )));
    }
    let [merged, vertex_count, triangle_count, vertex_len] =
        [0; 4].map(|_: u32| u32::from_le_bytes(r.array()));
    let limit = |what, value: u32, limit: u32| {
        if value > limit {
            Err(TileCodecError::TooLarge {
                what,
                value: u64::from(value),
                limit: u64::from(limit),
            })
        } else {
            Ok(())
        }
    };
    limit("the vertex count", vertex_count, MAX_TILE_VERTICES)?;
    limit("the triangle count", triangle_count, MAX_TILE_TRIANGLES)?;
    let texel_m = f64::from_le_bytes(r.array());
    let png_len = u32::from_le_bytes(r.array()) as usize;
    let rest = &bytes[HEADER_BYTES..];
    let vertex_len = vertex_len as usize;
    if vertex_len > rest.len() {
        return Err(TileCodecError::Invalid(format!(
            "a vertex stream of {vertex_len} bytes in {} remaining",
            rest.len()
        )));
    }
    let (vertex_bytes, rest) = rest.split_at(vertex_len);
    if png_len > rest.len() {
        return Err(TileCodecError::Invalid(format!(
            "an atlas image of {png_len} bytes in {} remaining",
            rest.len()
        )));
    }
    let (png, index_bytes) = rest.split_at(png_len);
    if png_len > 0 && !(texel_m.is_finite() && texel_m > 0.0) {
        return Err(TileCodecError::Invalid(format!(
            "an atlas texel of {texel_m} m"
        )));
    }
    let packed: Vec<PackedVertex> = decode_vertex_buffer(vertex_bytes, vertex_count as usize)
        .map_err(|e| TileCodecError::Invalid(format!("vertex stream: {e}")))?;
    let flat: Vec<u32> = decode_index_buffer(index_bytes, triangle_count as usize * 3)
        .map_err(|e| TileCodecError::Invalid(format!("index stream: {e}")))?;
    // The index codec decodes garbage to garbage: every index must name a vertex.
    if let Some(bad) = flat.iter().find(|&&i| i >= vertex_count) {
        return Err(TileCodecError::Invalid(format!(
            "index {bad} of a tile with {vertex_count} vertices"
        )));
    }
    let origin_m = [f[0], f[1], f[2]];
    let bounds_min_m = [f[3], f[4], f[5]];
    let bounds_max_m = [f[6], f[7], f[8]];
    let mut node = LodNode {
        id: TileId { lod, x, y },
        mesh: SurfaceMesh::empty(origin_m),
        bounds_min_m,
        bounds_max_m,
        geometric_error_m: f[9],
        voxel_m: f[10],
        merged_triangles: merged as usize,
        texture: None,
    };
    let (lo, scale) = quantisation(&node);
    node.mesh.positions = packed
        .iter()
        .map(|p| {
            [0, 1, 2].map(|a| {
                let world = lo[a] + f64::from(p.q[a]) / scale[a].max(f64::MIN_POSITIVE);
                let world = if scale[a] > 0.0 { world } else { lo[a] };
                (world - origin_m[a]) as f32
            })
        })
        .collect();
    node.mesh.colours = packed
        .iter()
        .map(|p| [p.rgba[0], p.rgba[1], p.rgba[2]])
        .collect();
    node.mesh.triangles = flat.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();
    if png_len > 0 {
        let (width, height, rgb) = decode_png(png)?;
        node.texture = Some(TileTexture {
            width,
            height,
            texel_m,
            rgb,
            uvs: packed
                .iter()
                .map(|p| {
                    [
                        dequantise_uv(p.uv[0], width),
                        dequantise_uv(p.uv[1], height),
                    ]
                })
                .collect(),
        });
    }
    Ok(node)
}

/// The low corner and the steps per metre of a tile's quantisation grid (0 steps per
/// metre on a flat axis).
fn quantisation(node: &LodNode) -> ([f64; 3], [f64; 3]) {
    let lo = node.bounds_min_m;
    let scale = [0, 1, 2].map(|a| {
        let extent = node.bounds_max_m[a] - node.bounds_min_m[a];
        if extent > 1e-9 && extent.is_finite() {
            65_535.0 / extent
        } else {
            0.0
        }
    });
    (lo, scale)
}

/// Steps of a texture coordinate per texel. An eighth of a texel (1.25 cm at 0.1 m)
/// is far inside the one-texel gutter, and coarser steps than 16 bits over [0, 1]
/// leave the low bits less noisy for the vertex codec. 4,096 texels · 8 fit 16 bits.
const UV_STEPS_PER_TEXEL: u32 = 8;

/// A texture coordinate in [0, 1] of an atlas `side` texels long, in eighths of a
/// texel; NaN goes to 0.
fn quantise_uv(value: f32, side: u32) -> u16 {
    let steps = f64::from(side.min(MAX_ATLAS_PX) * UV_STEPS_PER_TEXEL);
    let v = f64::from(value);
    if v.is_nan() {
        0
    } else {
        (v.clamp(0.0, 1.0) * steps).round().clamp(0.0, 65_535.0) as u16
    }
}

/// A texture coordinate back in [0, 1] (`side` ≥ 1: a decoded atlas's).
fn dequantise_uv(q: u16, side: u32) -> f32 {
    let steps = f64::from(side.max(1) * UV_STEPS_PER_TEXEL);
    (f64::from(q) / steps).min(1.0) as f32
}

fn quantise(value: f64, lo: f64, scale: f64) -> u16 {
    ((value - lo) * scale).round().clamp(0.0, 65_535.0) as u16
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    /// The next `N` bytes; the caller checked the header's length.
    fn array<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        if let Some(src) = self.bytes.get(self.at..self.at + N) {
            out.copy_from_slice(src);
        }
        self.at += N;
        out
    }
}
