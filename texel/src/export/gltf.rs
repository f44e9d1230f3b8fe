//! glTF 2.0: one textured mesh per scan (its usable triangles, the EO image as an
//! unlit base-colour texture), each under a node carrying the scan's pose. `.glb`
//! paths get the binary container; any other path gets JSON with the buffer and
//! images embedded as data URIs.

use std::path::Path;

use serde_json::{Value, json};

use super::{ExportError, ExportScan, check_frames, io_error, usable_triangles};
use crate::capture::encode_compressed;
use crate::pose::{Pose, pose_to_parts};
use crate::scan::TexelScan;

const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
const LINEAR: u32 = 9729;
const CLAMP_TO_EDGE: u32 = 33071;

/// The binary buffer and the JSON arrays that point into it.
#[derive(Default)]
struct Builder {
    bin: Vec<u8>,
    buffer_views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Builder {
    fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let mut view = json!({
            "buffer": 0,
            "byteOffset": self.bin.len(),
            "byteLength": bytes.len(),
        });
        if let Some(t) = target {
            view["target"] = json!(t);
        }
        self.bin.extend_from_slice(bytes);
        self.buffer_views.push(view);
        self.buffer_views.len() - 1
    }

    fn accessor(
        &mut self,
        view: usize,
        component: u32,
        count: usize,
        kind: &str,
        extra: Value,
    ) -> usize {
        let mut a = json!({
            "bufferView": view,
            "componentType": component,
            "count": count,
            "type": kind,
        });
        if let (Some(a), Some(extra)) = (a.as_object_mut(), extra.as_object()) {
            a.extend(extra.clone());
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }
}

fn base64(bytes: &[u8]) -> String {
    const TABLE: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(char::from(TABLE[((n >> (18 - 6 * i)) & 63) as usize]));
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// A scan's texture as glTF embeds it.
#[derive(Debug, Clone, Copy)]
pub enum GltfTexture<'a> {
    /// The scan's own EO pixels, compressed to PNG here (the costly part of a glTF).
    Png,
    /// An image already compressed in a format glTF takes (`image/jpeg` or
    /// `image/png`), embedded as it is: a texture that travelled compressed (the
    /// viewer stream's JPEG) costs no decoding or encoding.
    Encoded {
        mime_type: &'static str,
        data: &'a [u8],
    },
}

/// The glTF document being built: one mesh, material, texture and image per scan.
#[derive(Default)]
struct Document {
    b: Builder,
    nodes: Vec<Value>,
    meshes: Vec<Value>,
    materials: Vec<Value>,
    textures: Vec<Value>,
    images: Vec<Value>,
}

impl Document {
    /// Adds a scan's usable triangles under a node carrying `node_pose`; false when
    /// it has none (nothing is added).
    fn add_scan(
        &mut self,
        scan: &TexelScan,
        texture: GltfTexture<'_>,
        node_pose: Option<Pose>,
    ) -> Result<bool, ExportError> {
        let b = &mut self.b;
        let indices: Vec<u8> = usable_triangles(scan)
            .flatten()
            .flat_map(u32::to_le_bytes)
            .collect();
        if indices.is_empty() {
            return Ok(false);
        }
        let positions: Vec<u8> = scan
            .vertices
            .iter()
            .flatten()
            .flat_map(|c| c.to_le_bytes())
            .collect();
        let uvs: Vec<u8> = scan
            .tex_coords
            .iter()
            .flatten()
            .flat_map(|c| c.to_le_bytes())
            .collect();
        let (lo, hi) = scan.bounds().unwrap_or(([0.0; 3], [0.0; 3]));
        let pv = b.view(&positions, Some(ARRAY_BUFFER));
        let pa = b.accessor(
            pv,
            FLOAT,
            scan.vertex_count(),
            "VEC3",
            json!({"min": lo, "max": hi}),
        );
        let uv = b.view(&uvs, Some(ARRAY_BUFFER));
        let ua = b.accessor(uv, FLOAT, scan.vertex_count(), "VEC2", json!({}));
        let iv = b.view(&indices, Some(ELEMENT_ARRAY_BUFFER));
        let ia = b.accessor(iv, UNSIGNED_INT, indices.len() / 4, "SCALAR", json!({}));
        let png;
        let (mime_type, image) = match texture {
            GltfTexture::Png => {
                png = encode_compressed(
                    &scan.texture.rgb,
                    scan.texture.width,
                    scan.texture.height,
                    "png",
                    90,
                )
                .map_err(|e| ExportError::Texture {
                    seq: scan.seq,
                    message: e.to_string(),
                })?;
                ("image/png", png.as_slice())
            }
            GltfTexture::Encoded { mime_type, data } => (mime_type, data),
        };
        let image_view = b.view(image, None);
        self.images
            .push(json!({"bufferView": image_view, "mimeType": mime_type}));
        self.textures
            .push(json!({"source": self.images.len() - 1, "sampler": 0}));
        self.materials.push(json!({
            "name": format!("scan {}", scan.seq),
            "pbrMetallicRoughness": {
                "baseColorTexture": {"index": self.textures.len() - 1},
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0
            },
            "doubleSided": true,
            // The texture is what the camera saw: shown as is, not relit.
            "extensions": {"KHR_materials_unlit": {}}
        }));
        self.meshes.push(json!({
            "name": format!("scan {}", scan.seq),
            "primitives": [{
                "attributes": {"POSITION": pa, "TEXCOORD_0": ua},
                "indices": ia,
                "material": self.materials.len() - 1
            }]
        }));
        let mut node = json!({"name": format!("scan {} at {} ns", scan.seq, scan.timestamp_ns), "mesh": self.meshes.len() - 1});
        if let Some(pose) = node_pose {
            let (t, q) = pose_to_parts(&pose);
            node["translation"] = json!(t);
            node["rotation"] = json!(q);
        }
        self.nodes.push(node);
        Ok(true)
    }

    /// The document's bytes: a GLB container, or JSON with the buffer embedded as a
    /// data URI.
    fn finish(self, glb: bool) -> Vec<u8> {
        let mut buffer = json!({"byteLength": self.b.bin.len()});
        if !glb {
            buffer["uri"] = json!(format!(
                "data:application/octet-stream;base64,{}",
                base64(&self.b.bin)
            ));
        }
        let document = json!({
            "asset": {"version": "2.0", "generator": concat!("texel ", env!("CARGO_PKG_VERSION"))},
            "extensionsUsed": ["KHR_materials_unlit"],
            "scene": 0,
            "scenes": [{"nodes": (0..self.nodes.len()).collect::<Vec<_>>()}],
            "nodes": self.nodes,
            "meshes": self.meshes,
            "materials": self.materials,
            "textures": self.textures,
            "samplers": [{"magFilter": LINEAR, "minFilter": LINEAR, "wrapS": CLAMP_TO_EDGE, "wrapT": CLAMP_TO_EDGE}],
            "images": self.images,
            "accessors": self.b.accessors,
            "bufferViews": self.b.buffer_views,
            "buffers": [buffer],
        });
        let text = document.to_string();
        if glb {
            glb_container(text.into_bytes(), self.b.bin)
        } else {
            text.into_bytes()
        }
    }
}

/// Writes the scans to a glTF 2.0 file (`.glb` binary, otherwise embedded JSON).
pub fn write_gltf(scans: &[ExportScan<'_>], path: &Path) -> Result<(), ExportError> {
    check_frames(scans)?;
    let mut doc = Document::default();
    for s in scans {
        doc.add_scan(s.scan, GltfTexture::Png, s.world_from_scan)?;
    }
    if doc.meshes.is_empty() {
        return Err(ExportError::Empty("no scan has a usable triangle".into()));
    }
    let glb = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("glb"));
    std::fs::write(path, doc.finish(glb)).map_err(io_error(path))
}

/// One scan as a binary glTF (GLB) in memory: its usable triangles in the scan's own
/// frame (f32, relative to its origin), its texture as `texture` says, under one
/// node carrying `root` (none: the identity). For a model placed by someone else, as
/// a Foxglove model primitive is by its pose. A scan without a usable triangle is
/// [`ExportError::Empty`].
pub fn scan_glb(
    scan: &TexelScan,
    texture: GltfTexture<'_>,
    root: Option<Pose>,
) -> Result<Vec<u8>, ExportError> {
    let mut doc = Document::default();
    if !doc.add_scan(scan, texture, root)? {
        return Err(ExportError::Empty(format!(
            "scan {} has no usable triangle",
            scan.seq
        )));
    }
    Ok(doc.finish(true))
}

/// The GLB container: a 12-byte header, a JSON chunk padded with spaces and a BIN
/// chunk padded with zeros.
pub fn glb_container(mut json: Vec<u8>, mut bin: Vec<u8>) -> Vec<u8> {
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

#[cfg(test)]
mod tests {
    use super::base64;

    #[test]
    fn base64_matches_the_rfc_examples() {
        for (plain, encoded) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(plain.as_bytes()), encoded);
        }
    }
}
