//! Tiles through the wire codec: every tile of a street comes back with the same
//! triangles to within its quantisation step and the same colours, in a fraction of
//! its glTF bytes; corrupt, truncated or hostile bytes are errors, never a panic or
//! an index out of range.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![allow(clippy::needless_range_loop)] // x, y and z side by side read clearer indexed

mod support;

use std::sync::OnceLock;

use proptest::prelude::*;
use texel_lod::tiles::tile_glb;
use texel_lod::{
    Hierarchy, LodConfig, LodNode, TileCodecError, TileCompression, atlas_png, decode_tile,
    encode_tile,
};

const FAR: [f64; 3] = [5.0e6, 4.2e6, 120.0];

fn street() -> &'static Hierarchy {
    static STREET: OnceLock<Hierarchy> = OnceLock::new();
    STREET.get_or_init(|| {
        support::street(
            40.0,
            FAR,
            &LodConfig {
                tile_voxels: 64,
                tile_triangle_budget: 3_000,
                ..LodConfig::default()
            },
        )
    })
}

/// For every vertex of `back`, the vertex of `node` within `tolerance_m` of it.
fn match_vertices(node: &LodNode, back: &LodNode, tolerance_m: f64) -> Vec<Option<u32>> {
    let cell = |p: [f64; 3]| p.map(|x| (x / tolerance_m).floor() as i64);
    let mut grid: std::collections::HashMap<[i64; 3], Vec<u32>> = Default::default();
    for v in 0..node.mesh.vertex_count() {
        grid.entry(cell(node.mesh.world(v).unwrap()))
            .or_default()
            .push(v as u32);
    }
    (0..back.mesh.vertex_count())
        .map(|v| {
            let p = back.mesh.world(v).unwrap();
            let c = cell(p);
            let mut best: Option<(f64, u32)> = None;
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        for &o in grid
                            .get(&[c[0] + dx, c[1] + dy, c[2] + dz])
                            .into_iter()
                            .flatten()
                        {
                            let q = node.mesh.world(o as usize).unwrap();
                            let d = (0..3).map(|k| (p[k] - q[k]).abs()).fold(0.0, f64::max);
                            if d <= tolerance_m && best.is_none_or(|(bd, _)| d < bd) {
                                best = Some((d, o));
                            }
                        }
                    }
                }
            }
            best.map(|(_, o)| o)
        })
        .collect()
}

#[test]
fn every_tile_comes_back_within_its_quantisation_step_in_a_fraction_of_its_bytes() {
    let h = street();
    let (mut encoded, mut glb, mut textured) = (0usize, 0usize, 0usize);
    for node in h.nodes.values().filter(|n| !n.mesh.is_empty()) {
        let bytes = encode_tile(node);
        let back = decode_tile(&bytes).unwrap();
        assert_eq!(back.id, node.id);
        assert_eq!(back.bounds_min_m, node.bounds_min_m);
        assert_eq!(back.geometric_error_m, node.geometric_error_m);
        assert_eq!(back.mesh.vertex_count(), node.mesh.vertex_count());
        assert_eq!(back.mesh.triangle_count(), node.mesh.triangle_count());
        // Every vertex within half a step of one encoded (steps of extent / 65,535,
        // f32 offsets on top).
        let step = (0..3)
            .map(|a| (node.bounds_max_m[a] - node.bounds_min_m[a]) / 65_535.0)
            .fold(0.0, f64::max);
        let mut colours_in: Vec<[u8; 3]> = node.mesh.colours.clone();
        let mut colours_out: Vec<[u8; 3]> = back.mesh.colours.clone();
        colours_in.sort();
        colours_out.sort();
        assert_eq!(colours_in, colours_out);
        // Every decoded vertex is an encoded one moved by at most half a step (plus
        // f32 offsets), and the triangles are the same triangles.
        let map = match_vertices(node, &back, step + 1e-5);
        assert!(
            map.iter().all(Option::is_some),
            "{:?}: a vertex moved",
            node.id
        );
        // Triangles as the positions of their corners (an atlas gives each corner
        // its own vertex, so coincident vertices may match either way round).
        let key = |v: u32| node.mesh.positions[v as usize].map(f32::to_bits);
        let canonical = |t: [[u32; 3]; 3]| {
            // The same triangle whatever its first corner.
            let r = (0..3).min_by_key(|&k| t[k]).unwrap();
            [t[r], t[(r + 1) % 3], t[(r + 2) % 3]]
        };
        let mut want: Vec<[[u32; 3]; 3]> = node
            .mesh
            .triangles
            .iter()
            .map(|t| canonical(t.map(key)))
            .collect();
        let mut got: Vec<[[u32; 3]; 3]> = back
            .mesh
            .triangles
            .iter()
            .map(|t| canonical(t.map(|v| key(map[v as usize].unwrap()))))
            .collect();
        want.sort();
        got.sort();
        assert_eq!(want, got, "{:?}", node.id);
        for v in 0..back.mesh.vertex_count() {
            let p = back.mesh.world(v).unwrap();
            for k in 0..3 {
                assert!(p[k] >= node.bounds_min_m[k] - step && p[k] <= node.bounds_max_m[k] + step);
            }
        }
        // The atlas comes back texel for texel, each coordinate within half a
        // step (an eighth of a texel).
        assert_eq!(back.texture.is_some(), node.texture.is_some());
        let mut png = 0;
        if let (Some(texture), Some(back_texture)) = (&node.texture, &back.texture) {
            textured += 1;
            assert_eq!(
                (back_texture.width, back_texture.height),
                (texture.width, texture.height)
            );
            assert_eq!(back_texture.texel_m, texture.texel_m);
            assert!(
                back_texture.rgb == texture.rgb,
                "{:?}: texels changed",
                node.id
            );
            assert_eq!(back_texture.uvs.len(), back.mesh.vertex_count());
            for (v, uv) in back_texture.uvs.iter().enumerate() {
                assert!(uv.iter().all(|c| (0.0..=1.0).contains(c)));
                // The encoded vertex this one came from has the same coordinates
                // (coincident corners of different charts may match either way).
                let from = map[v].unwrap() as usize;
                let want = texture.uvs[from];
                // Within half an eighth of a texel.
                let sides = [texture.width, texture.height].map(f64::from);
                let close = (0..2)
                    .all(|k| f64::from((uv[k] - want[k]).abs()) <= 0.5 / (8.0 * sides[k]) + 1e-6);
                let shared = back
                    .mesh
                    .positions
                    .iter()
                    .filter(|p| **p == back.mesh.positions[v])
                    .count()
                    > 1;
                assert!(
                    close || shared,
                    "{:?}: vertex {v} at {uv:?}, not {want:?}",
                    node.id
                );
            }
            png = atlas_png(texture).unwrap().len();
        }
        // Both formats carry the same PNG: compare what is left.
        encoded += bytes.len() - png;
        glb += tile_glb(node, TileCompression::None).unwrap().len() - png;
    }
    assert!(textured > 0, "no tile has an atlas");
    // Quantised, reordered and delta-coded: well under half of the glTF's bytes
    // (besides the atlas, which both carry as the same PNG).
    assert!(encoded * 2 < glb, "{encoded} bytes against {glb} as glTF");
}

#[test]
fn bad_bytes_are_named_errors() {
    let node = street()
        .nodes
        .values()
        .find(|n| !n.mesh.is_empty())
        .unwrap();
    let bytes = encode_tile(node);
    assert!(matches!(
        decode_tile(&bytes[..10]),
        Err(TileCodecError::Truncated(10))
    ));
    let mut bad = bytes.clone();
    bad[0] = b'X';
    assert!(matches!(
        decode_tile(&bad),
        Err(TileCodecError::BadMagic(_))
    ));
    let mut bad = bytes.clone();
    bad[4] = 9;
    assert!(matches!(decode_tile(&bad), Err(TileCodecError::Version(9))));
    // A header claiming a billion vertices is refused before any allocation.
    let mut bad = bytes.clone();
    let at = 4 + 2 + 1 + 8 + 8 + 8 * 11 + 4;
    bad[at..at + 4].copy_from_slice(&1_000_000_000u32.to_le_bytes());
    assert!(matches!(
        decode_tile(&bad),
        Err(TileCodecError::TooLarge { .. })
    ));
    // Cut short inside the streams.
    let cut = decode_tile(&bytes[..bytes.len() - 7]);
    assert!(cut.is_err(), "{cut:?}");
}

/// Offset of the atlas PNG's length in the header, and where the PNG starts.
fn png_span(bytes: &[u8]) -> (usize, usize, usize) {
    let header = 4 + 2 + 1 + 8 + 8 + 8 * 11 + 4 * 4 + 8 + 4;
    let vertex_len_at = 4 + 2 + 1 + 8 + 8 + 8 * 11 + 12;
    let png_len_at = header - 4;
    let vertex_len =
        u32::from_le_bytes(bytes[vertex_len_at..vertex_len_at + 4].try_into().unwrap()) as usize;
    let png_len =
        u32::from_le_bytes(bytes[png_len_at..png_len_at + 4].try_into().unwrap()) as usize;
    (png_len_at, header + vertex_len, png_len)
}

#[test]
fn a_corrupt_or_oversized_atlas_is_a_named_error() {
    let node = street()
        .nodes
        .values()
        .find(|n| n.texture.is_some())
        .unwrap();
    let bytes = encode_tile(node);
    let (png_len_at, png_at, png_len) = png_span(&bytes);
    assert!(png_len > 0);
    assert_eq!(&bytes[png_at + 1..png_at + 4], b"PNG");
    // Garbage where the image's pixels are.
    let mut bad = bytes.clone();
    for b in &mut bad[png_at + 40..png_at + png_len - 12] {
        *b ^= 0x5a;
    }
    assert!(matches!(decode_tile(&bad), Err(TileCodecError::Invalid(_))));
    // A PNG length past the end of the bytes.
    let mut bad = bytes.clone();
    bad[png_len_at..png_len_at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(decode_tile(&bad), Err(TileCodecError::Invalid(_))));
    // The image cut short (the index stream then starts inside it).
    let mut bad = bytes.clone();
    bad[png_len_at..png_len_at + 4].copy_from_slice(&((png_len / 2) as u32).to_le_bytes());
    assert!(decode_tile(&bad).is_err());
    // An image header claiming 100,000 × 100,000 texels is refused before any
    // allocation (IHDR width and height follow the 8-byte signature and 8-byte chunk
    // head; the chunk's CRC is fixed up so only the size is wrong).
    let mut bad = bytes.clone();
    let ihdr = png_at + 8;
    bad[ihdr + 8..ihdr + 12].copy_from_slice(&100_000u32.to_be_bytes());
    bad[ihdr + 12..ihdr + 16].copy_from_slice(&100_000u32.to_be_bytes());
    let crc = crc32(&bad[ihdr + 4..ihdr + 8 + 13]);
    bad[ihdr + 21..ihdr + 25].copy_from_slice(&crc.to_be_bytes());
    assert!(decode_tile(&bad).is_err());
}

/// CRC-32 (IEEE), as PNG chunks carry it.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = u32::MAX;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

#[test]
fn a_tile_without_an_atlas_round_trips_without_one() {
    let mut node = street()
        .nodes
        .values()
        .find(|n| n.texture.is_some())
        .unwrap()
        .clone();
    node.texture = None;
    let back = decode_tile(&encode_tile(&node)).unwrap();
    assert!(back.texture.is_none());
    assert_eq!(back.mesh.triangle_count(), node.mesh.triangle_count());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Any flipped bytes and any truncation: an error or a tile whose every index
    /// names a vertex and whose every coordinate is finite; never a panic.
    #[test]
    fn corrupt_bytes_never_panic_nor_index_out_of_range(
        flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8),
        keep in 0.0f64..=1.0,
    ) {
        // A tile with an atlas: its PNG is corrupted too.
        let node = street().nodes.values().find(|n| n.texture.is_some()).unwrap();
        let mut bytes = encode_tile(node);
        for (at, value) in flips {
            let i = at.index(bytes.len());
            bytes[i] ^= value;
        }
        let len = ((bytes.len() as f64) * keep) as usize;
        if let Ok(tile) = decode_tile(&bytes[..len]) {
            let n = tile.mesh.vertex_count() as u32;
            prop_assert!(tile.mesh.triangles.iter().flatten().all(|&i| i < n));
            prop_assert!(tile.mesh.positions.iter().flatten().all(|x| x.is_finite()));
            if let Some(t) = &tile.texture {
                prop_assert_eq!(t.uvs.len(), tile.mesh.vertex_count());
                prop_assert_eq!(t.rgb.len(), t.width as usize * t.height as usize * 3);
            }
        }
    }
}
