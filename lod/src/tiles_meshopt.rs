//! A tile's glTF geometry compressed with `EXT_meshopt_compression`: each vertex
//! attribute's view and the index view carried as meshoptimizer's vertex codec
//! (bitstream version 0, as the extension asks) and triangle index codec, the same
//! codecs the wire uses (`codec.rs`), in a form CesiumJS, loaders.gl and three.js
//! decode. The uncompressed layout stays described by a fallback buffer with no data,
//! so the extension is required.

use serde_json::{Value, json};

use crate::tiles::TilesError;

const EXTENSION: &str = "EXT_meshopt_compression";

/// One view to compress: its index in `bufferViews`, the bytes of one element, and
/// whether it holds triangle indices (else vertex attributes).
pub(crate) struct View {
    pub index: usize,
    pub stride: usize,
    pub triangles: bool,
}

/// Rewrites an uncompressed tile (`json` describing `bin`, buffer 0) so that `views`
/// are meshopt-compressed into a new binary chunk; every other view is copied there
/// as it was. Returns the new JSON and binary chunk.
pub(crate) fn compress(
    mut json: Value,
    bin: &[u8],
    views: &[View],
    tile: &str,
) -> Result<(Value, Vec<u8>), TilesError> {
    let failed = |what: String| TilesError::Compression {
        tile: tile.to_string(),
        what,
    };
    let Some(buffer_views) = json["bufferViews"].as_array().cloned() else {
        return Err(failed("no buffer views".into()));
    };
    let mut out = Vec::with_capacity(bin.len() / 2);
    let mut fallback_len = 0usize;
    let mut rewritten = Vec::with_capacity(buffer_views.len());
    for (i, view) in buffer_views.into_iter().enumerate() {
        let offset = view["byteOffset"].as_u64().unwrap_or(0) as usize;
        let len = view["byteLength"].as_u64().unwrap_or(0) as usize;
        let bytes = bin
            .get(offset..offset + len)
            .ok_or_else(|| failed(format!("view {i} lies beyond the buffer")))?;
        // Every stream starts 4-byte aligned, as accessors and the decoders want.
        while !out.len().is_multiple_of(4) {
            out.push(0);
        }
        let at = out.len();
        let Some(spec) = views.iter().find(|v| v.index == i) else {
            out.extend_from_slice(bytes);
            let mut copied = view;
            copied["buffer"] = json!(0);
            copied["byteOffset"] = json!(at);
            rewritten.push(copied);
            continue;
        };
        if spec.stride == 0 || !len.is_multiple_of(spec.stride) {
            return Err(failed(format!(
                "view {i}: {len} bytes is not a whole number of {}-byte elements",
                spec.stride
            )));
        }
        let count = len / spec.stride;
        let encoded = if spec.triangles {
            encode_triangles(bytes, count).map_err(|e| failed(format!("view {i}: {e}")))?
        } else {
            encode_attributes(bytes, spec.stride).map_err(|e| failed(format!("view {i}: {e}")))?
        };
        out.extend_from_slice(&encoded);
        let mut compressed = view;
        // The view itself describes the decoded bytes, in the fallback buffer.
        compressed["buffer"] = json!(1);
        compressed["byteOffset"] = json!(fallback_len);
        if !spec.triangles {
            compressed["byteStride"] = json!(spec.stride);
        }
        compressed["extensions"] = json!({ EXTENSION: {
            "buffer": 0,
            "byteOffset": at,
            "byteLength": encoded.len(),
            "byteStride": spec.stride,
            "count": count,
            "mode": if spec.triangles { "TRIANGLES" } else { "ATTRIBUTES" },
        }});
        fallback_len += len;
        // Views in the fallback buffer stay 4-byte aligned too.
        fallback_len = fallback_len.div_ceil(4) * 4;
        rewritten.push(compressed);
    }
    while !out.len().is_multiple_of(4) {
        out.push(0);
    }
    json["bufferViews"] = Value::Array(rewritten);
    json["buffers"] = json!([
        { "byteLength": out.len() },
        { "byteLength": fallback_len, "extensions": { EXTENSION: { "fallback": true } } }
    ]);
    for key in ["extensionsUsed", "extensionsRequired"] {
        let mut list = json[key].as_array().cloned().unwrap_or_default();
        list.push(json!(EXTENSION));
        json[key] = Value::Array(list);
    }
    Ok((json, out))
}

/// A view of vertex attributes through the vertex codec, version 0 (the version
/// `EXT_meshopt_compression` specifies).
fn encode_attributes(bytes: &[u8], stride: usize) -> Result<Vec<u8>, String> {
    fn typed<const S: usize>(bytes: &[u8]) -> Result<Vec<u8>, String> {
        let elements: Vec<[u8; S]> = bytes
            .chunks_exact(S)
            .map(|c| {
                let mut e = [0u8; S];
                e.copy_from_slice(c);
                e
            })
            .collect();
        meshopt::encode_vertex_buffer_level(&elements, 2, Some(0)).map_err(|e| e.to_string())
    }
    match stride {
        8 => typed::<8>(bytes),
        12 => typed::<12>(bytes),
        16 => typed::<16>(bytes),
        other => Err(format!("no vertex codec for {other}-byte elements")),
    }
}

/// A view of u32 triangle indices through the index codec.
fn encode_triangles(bytes: &[u8], count: usize) -> Result<Vec<u8>, String> {
    if !count.is_multiple_of(3) {
        return Err(format!("{count} indices are not whole triangles"));
    }
    let indices: Vec<u32> = bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let vertices = indices.iter().max().map_or(0, |&m| m as usize + 1);
    meshopt::encode_index_buffer(&indices, vertices).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests panic on failure by design
    use super::*;

    #[test]
    fn the_streams_decode_to_the_bytes_they_replace() {
        let positions: Vec<[f32; 3]> = (0..300)
            .map(|i| {
                let t = i as f32 * 0.1;
                [t.cos(), t.sin(), 0.01 * t]
            })
            .collect();
        let bytes: Vec<u8> = positions
            .iter()
            .flatten()
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let encoded = encode_attributes(&bytes, 12).unwrap();
        // Bitstream version 0: the header byte is 0xa0.
        assert_eq!(encoded[0], 0xa0);
        let decoded: Vec<[u8; 12]> = meshopt::decode_vertex_buffer(&encoded, 300).unwrap();
        assert_eq!(decoded.concat(), bytes);

        let triangles: Vec<u32> = (0..298).flat_map(|i| [i, i + 1, i + 2]).collect();
        let bytes: Vec<u8> = triangles.iter().flat_map(|i| i.to_le_bytes()).collect();
        let encoded = encode_triangles(&bytes, triangles.len()).unwrap();
        let decoded: Vec<u32> = meshopt::decode_index_buffer(&encoded, triangles.len()).unwrap();
        // The codec may rotate a triangle's corners, never change the triangle.
        for (a, b) in decoded.chunks(3).zip(triangles.chunks(3)) {
            let mut a = a.to_vec();
            let mut b = b.to_vec();
            a.sort_unstable();
            b.sort_unstable();
            assert_eq!(a, b);
        }
        assert!(encode_triangles(&bytes[..8], 2).is_err());
        assert!(encode_attributes(&[0; 20], 20).is_err());
    }
}
