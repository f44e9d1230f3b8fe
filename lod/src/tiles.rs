//! The hierarchy as an OGC 3D Tiles 1.1 tileset: `tileset.json` (bounding boxes,
//! geometric errors, REPLACE refinement, one tile per node) and one binary glTF 2.0
//! per tile, coloured by its atlas (an embedded PNG) or, without one, per vertex
//! (linear, from the sRGB pixels), and unlit (the colours are the scene's own light).
//!
//! Frames: tile coordinates are the model's world frame (right-handed, +z up,
//! metres), read as a local east-north-up frame. glTF is +y up and 3D Tiles turns
//! content +y up to +z up, so content is written as (x, z, -y). Without a
//! geo-reference the tileset stays in that local frame; with one, the root's
//! `transform` places the given world point at the given WGS84 latitude, longitude
//! and height with world x east, y north, z up there.

use serde_json::{Value, json};
use texel::export::glb_container;
use texel_surface::SurfaceMesh;
use thiserror::Error;

use crate::build::{Hierarchy, LodNode};
use crate::codec::atlas_png;
use crate::tiles_meshopt::{View, compress};
use crate::tree::TileId;

/// Where the model's world frame lies on the globe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoReference {
    pub latitude_deg: f64,
    pub longitude_deg: f64,
    /// Height above the WGS84 ellipsoid, metres.
    pub height_m: f64,
    /// The world point that lies there (often the origin).
    pub world_point_m: [f64; 3],
}

#[derive(Debug, Error, PartialEq)]
pub enum TilesError {
    #[error("geo-reference {field} must be {expected}, got {value}")]
    BadGeoReference {
        field: &'static str,
        expected: &'static str,
        value: f64,
    },
    #[error("tile {tile} holds {vertices} vertices, more than a glTF index of 32 bits reaches")]
    TooLarge { tile: String, vertices: usize },
    #[error("tile {tile}: its geometry could not be compressed: {what}")]
    Compression { tile: String, what: String },
}

/// How a tile's glTF carries its geometry.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum TileCompression {
    /// Plain accessors: every glTF reader opens it.
    #[default]
    None,
    /// `EXT_meshopt_compression` (meshoptimizer's vertex and index codecs): smaller,
    /// for readers that know the extension (CesiumJS, loaders.gl, three.js).
    Meshopt,
}

impl GeoReference {
    pub fn validate(&self) -> Result<(), TilesError> {
        let bad = |field, expected, value| TilesError::BadGeoReference {
            field,
            expected,
            value,
        };
        if !(self.latitude_deg.is_finite() && self.latitude_deg.abs() <= 90.0) {
            return Err(bad("latitude_deg", "in [-90, 90]", self.latitude_deg));
        }
        if !(self.longitude_deg.is_finite() && self.longitude_deg.abs() <= 180.0) {
            return Err(bad("longitude_deg", "in [-180, 180]", self.longitude_deg));
        }
        if !(self.height_m.is_finite() && self.height_m.abs() <= 1.0e5) {
            return Err(bad(
                "height_m",
                "within 100 km of the ellipsoid",
                self.height_m,
            ));
        }
        if let Some(&v) = self.world_point_m.iter().find(|v| !v.is_finite()) {
            return Err(bad("world_point_m", "finite", v));
        }
        Ok(())
    }

    /// The 4×4 column-major matrix from world coordinates to Earth-centred,
    /// Earth-fixed ones (WGS84): east-north-up at the reference point.
    pub fn ecef_from_world(&self) -> [f64; 16] {
        const A: f64 = 6_378_137.0;
        const E2: f64 = 6.694_379_990_141_316e-3;
        let (lat, lon) = (
            self.latitude_deg.to_radians(),
            self.longitude_deg.to_radians(),
        );
        let (sl, cl) = lat.sin_cos();
        let (so, co) = lon.sin_cos();
        // 1 - e² sin²φ ≥ 1 - e² > 0: the square root is of a positive number.
        let n = A / (1.0 - E2 * sl * sl).sqrt();
        let origin = [
            (n + self.height_m) * cl * co,
            (n + self.height_m) * cl * so,
            (n * (1.0 - E2) + self.height_m) * sl,
        ];
        let east = [-so, co, 0.0];
        let north = [-sl * co, -sl * so, cl];
        let up = [cl * co, cl * so, sl];
        // translation = origin - R · world_point
        let w = self.world_point_m;
        let t = [0, 1, 2].map(|k| origin[k] - (east[k] * w[0] + north[k] * w[1] + up[k] * w[2]));
        [
            east[0], east[1], east[2], 0.0, north[0], north[1], north[2], 0.0, up[0], up[1], up[2],
            0.0, t[0], t[1], t[2], 1.0,
        ]
    }
}

/// One file of the tileset: its path relative to the tileset's folder and its bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct TileFile {
    pub path: String,
    pub bytes: Vec<u8>,
}

/// The tileset's files: `tileset.json` first, then one `.glb` per tile with surface.
pub fn tileset_files(
    hierarchy: &Hierarchy,
    geo: Option<&GeoReference>,
    compression: TileCompression,
) -> Result<Vec<TileFile>, TilesError> {
    if let Some(g) = geo {
        g.validate()?;
    }
    let mut files = vec![TileFile {
        path: "tileset.json".into(),
        bytes: Vec::new(),
    }];
    for node in hierarchy.nodes.values().filter(|n| !n.mesh.is_empty()) {
        files.push(TileFile {
            path: content_path(node.id),
            bytes: tile_glb(node, compression)?,
        });
    }
    // The top level's tiles (at most four) under one root without content, whose
    // box holds theirs and whose error is that of drawing nothing: its extent.
    let roots = hierarchy.roots();
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    let mut worst: f64 = 0.0;
    for node in roots.iter().filter_map(|id| hierarchy.nodes.get(id)) {
        for a in 0..3 {
            lo[a] = lo[a].min(node.bounds_min_m[a]);
            hi[a] = hi[a].max(node.bounds_max_m[a]);
        }
        worst = worst.max(node.geometric_error_m);
    }
    if roots.is_empty() {
        lo = [0.0; 3];
        hi = [0.0; 3];
    }
    let extent = (0..3).map(|a| (hi[a] - lo[a]).powi(2)).sum::<f64>().sqrt();
    let mut root = json!({
        "boundingVolume": { "box": box_of(lo, hi) },
        "geometricError": extent.max(worst),
        "refine": "REPLACE",
        "children": roots.iter().map(|id| tile_json(hierarchy, *id)).collect::<Vec<_>>(),
    });
    if let (Some(g), Some(obj)) = (geo, root.as_object_mut()) {
        obj.insert("transform".into(), json!(g.ecef_from_world().to_vec()));
    }
    let tileset = json!({
        "asset": { "version": "1.1", "generator": "texel" },
        "geometricError": extent.max(worst),
        "root": root,
    });
    files[0].bytes = serde_json::to_vec_pretty(&tileset).unwrap_or_default();
    Ok(files)
}

/// A tile's content path.
pub fn content_path(id: TileId) -> String {
    format!("tiles/{}.glb", id.path())
}

fn tile_json(hierarchy: &Hierarchy, id: TileId) -> Value {
    let Some(node) = hierarchy.nodes.get(&id) else {
        return Value::Null;
    };
    let mut tile = json!({
        "boundingVolume": { "box": bounding_box(node) },
        "geometricError": node.geometric_error_m,
    });
    if !node.mesh.is_empty() {
        tile["content"] = json!({ "uri": content_path(id) });
    }
    let children: Vec<Value> = hierarchy
        .children(id)
        .map(|c| tile_json(hierarchy, c.id))
        .collect();
    if !children.is_empty() {
        tile["children"] = Value::Array(children);
    }
    tile
}

/// The 3D Tiles oriented box of a node's world bounds.
fn bounding_box(node: &LodNode) -> Vec<f64> {
    box_of(node.bounds_min_m, node.bounds_max_m)
}

/// An axis-aligned box as 3D Tiles writes it: centre and three half axes. Half axes
/// are at least a centimetre: a flat tile still has a volume.
fn box_of(lo: [f64; 3], hi: [f64; 3]) -> Vec<f64> {
    let c = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]));
    let h = [0, 1, 2].map(|a| (0.5 * (hi[a] - lo[a])).max(0.01));
    vec![
        c[0], c[1], c[2], h[0], 0.0, 0.0, 0.0, h[1], 0.0, 0.0, 0.0, h[2],
    ]
}

/// An 8-bit sRGB value as a 16-bit linear one (IEC 61966-2-1).
pub fn srgb_to_linear_u16(value: u8) -> u16 {
    let v = f64::from(value) / 255.0;
    let linear = if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    };
    (linear * 65535.0).round().clamp(0.0, 65535.0) as u16
}

/// A node's mesh as binary glTF: positions (f32, y-up, offsets from a translated
/// node), u32 indices and one unlit material; coloured by its atlas (TEXCOORD_0 and
/// an embedded PNG as the base colour texture, which glTF reads as sRGB, as the atlas
/// holds) where it has one, else by linear RGBA16 vertex colours. Never both: glTF
/// multiplies COLOR_0 into the base colour. With [`TileCompression::Meshopt`] the
/// positions, colours or texture coordinates and indices are compressed
/// (`tiles_meshopt.rs`).
pub fn tile_glb(node: &LodNode, compression: TileCompression) -> Result<Vec<u8>, TilesError> {
    let mesh: &SurfaceMesh = &node.mesh;
    let n = mesh.vertex_count();
    if n >= u32::MAX as usize {
        return Err(TilesError::TooLarge {
            tile: node.id.path(),
            vertices: n,
        });
    }
    let png = node
        .texture
        .as_ref()
        .filter(|t| t.uvs.len() == n)
        .and_then(|t| Some((t, atlas_png(t)?)));
    let to_gltf = |p: [f32; 3]| [p[0], p[2], -p[1]];
    let mut bin: Vec<u8> = Vec::with_capacity(n * 20 + mesh.triangle_count() * 12);
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in &mesh.positions {
        let q = to_gltf(*p);
        for a in 0..3 {
            lo[a] = lo[a].min(q[a]);
            hi[a] = hi[a].max(q[a]);
            bin.extend_from_slice(&q[a].to_le_bytes());
        }
    }
    let colour_offset = bin.len();
    let colour_accessor = match &png {
        Some((texture, _)) => {
            // glTF's texture coordinates start at the image's first row, as the
            // atlas's do.
            for uv in &texture.uvs {
                for c in uv {
                    bin.extend_from_slice(&c.clamp(0.0, 1.0).to_le_bytes());
                }
            }
            json!({ "bufferView": 1, "componentType": 5126, "count": n, "type": "VEC2" })
        }
        None => {
            // glTF vertex colours are linear; the EO pixels are sRGB. Sixteen bits
            // keep the dark end, where linear values crowd together, as fine as the
            // pixels were.
            for c in &mesh.colours {
                for channel in [c[0], c[1], c[2]] {
                    bin.extend_from_slice(&srgb_to_linear_u16(channel).to_le_bytes());
                }
                bin.extend_from_slice(&u16::MAX.to_le_bytes());
            }
            json!({ "bufferView": 1, "componentType": 5123, "normalized": true, "count": n,
                    "type": "VEC4" })
        }
    };
    let index_offset = bin.len();
    for t in &mesh.triangles {
        for v in t {
            bin.extend_from_slice(&v.to_le_bytes());
        }
    }
    let o = mesh.origin_m;
    let mut material = json!({
        "pbrMetallicRoughness": {
            "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
            "metallicFactor": 0.0,
            "roughnessFactor": 1.0
        },
        "extensions": { "KHR_materials_unlit": {} }
    });
    let mut buffer_views = vec![
        json!({ "buffer": 0, "byteOffset": 0, "byteLength": colour_offset, "target": 34962 }),
        json!({ "buffer": 0, "byteOffset": colour_offset,
                "byteLength": index_offset - colour_offset, "target": 34962 }),
        json!({ "buffer": 0, "byteOffset": index_offset,
                "byteLength": bin.len() - index_offset, "target": 34963 }),
    ];
    let attributes = if png.is_some() {
        json!({ "POSITION": 0, "TEXCOORD_0": 1 })
    } else {
        json!({ "POSITION": 0, "COLOR_0": 1 })
    };
    let mut json = json!({
        "asset": { "version": "2.0", "generator": "texel" },
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "mesh": 0, "translation": [o[0], o[2], -o[1]] }],
        "meshes": [{ "primitives": [{
            "attributes": attributes,
            "indices": 2,
            "material": 0,
            "mode": 4
        }]}],
        "accessors": [
            { "bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3",
              "min": lo, "max": hi },
            colour_accessor,
            { "bufferView": 2, "componentType": 5125, "count": mesh.triangle_count() * 3,
              "type": "SCALAR" }
        ],
    });
    if let Some((_, png)) = &png {
        // The image last: the accessors' views before it stay 4-byte aligned.
        let image_offset = bin.len();
        bin.extend_from_slice(png);
        buffer_views.push(json!({ "buffer": 0, "byteOffset": image_offset,
                                  "byteLength": png.len() }));
        material["pbrMetallicRoughness"]["baseColorTexture"] = json!({ "index": 0 });
        json["images"] = json!([{ "bufferView": 3, "mimeType": "image/png" }]);
        // Linear filtering without mipmaps (the charts' gutters hold one texel, which
        // is all a bilinear tap reaches), clamped at the atlas's edges.
        json["samplers"] =
            json!([{ "magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071 }]);
        json["textures"] = json!([{ "sampler": 0, "source": 0 }]);
    }
    json["materials"] = json!([material]);
    json["bufferViews"] = Value::Array(buffer_views);
    json["buffers"] = json!([{ "byteLength": bin.len() }]);
    if compression == TileCompression::Meshopt {
        let views = [
            View {
                index: 0,
                stride: 12,
                triangles: false,
            },
            // Texture coordinates (2 x f32) or colours (4 x u16): 8 bytes either way.
            View {
                index: 1,
                stride: 8,
                triangles: false,
            },
            View {
                index: 2,
                stride: 4,
                triangles: true,
            },
        ];
        let (json, bin) = compress(json, &bin, &views, &node.id.path())?;
        return Ok(glb_container(
            serde_json::to_vec(&json).unwrap_or_default(),
            bin,
        ));
    }
    Ok(glb_container(
        serde_json::to_vec(&json).unwrap_or_default(),
        bin,
    ))
}

#[cfg(test)]
mod tests {
    use super::srgb_to_linear_u16;

    #[test]
    fn srgb_decodes_to_linear_at_the_standard_points() {
        assert_eq!(srgb_to_linear_u16(0), 0);
        assert_eq!(srgb_to_linear_u16(255), 65535);
        // sRGB 0.5 (128 of 255) is linear 0.2158 (IEC 61966-2-1).
        let mid = f64::from(srgb_to_linear_u16(128)) / 65535.0;
        assert!((mid - 0.2158605).abs() < 1e-4, "{mid}");
        // The linear segment below 0.04045.
        let low = f64::from(srgb_to_linear_u16(10)) / 65535.0;
        assert!((low - 10.0 / 255.0 / 12.92).abs() < 1e-5, "{low}");
        // Monotone.
        assert!((1..=255u8).all(|v| srgb_to_linear_u16(v) > srgb_to_linear_u16(v - 1)));
    }
}
