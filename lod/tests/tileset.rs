//! The tileset read back with our own eyes (the independent readers run in the
//! end-to-end tests): the tree in tileset.json is the hierarchy's, every content file
//! exists and decodes to the tile's mesh at its world position (content +y up turned
//! back to +z up), and a geo-reference puts the world origin where WGS84 says.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![allow(clippy::needless_range_loop)] // x, y and z side by side read clearer indexed

mod support;

use std::collections::BTreeMap;

use serde_json::Value;
use texel_lod::{GeoReference, LodConfig, TileCompression, TileId, tileset_files};

const FAR: [f64; 3] = [5.0e6, 4.2e6, 120.0];

fn config() -> LodConfig {
    LodConfig {
        tile_voxels: 64,
        tile_triangle_budget: 3_000,
        ..LodConfig::default()
    }
}

/// A GLB's JSON chunk and BIN chunk.
fn chunks(glb: &[u8]) -> (Value, Vec<u8>) {
    assert_eq!(&glb[0..4], b"glTF");
    assert_eq!(u32::from_le_bytes(glb[4..8].try_into().unwrap()), 2);
    assert_eq!(
        u32::from_le_bytes(glb[8..12].try_into().unwrap()) as usize,
        glb.len()
    );
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    assert_eq!(&glb[16..20], b"JSON");
    let json: Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let bin_at = 20 + json_len;
    let bin_len = u32::from_le_bytes(glb[bin_at..bin_at + 4].try_into().unwrap()) as usize;
    assert_eq!(&glb[bin_at + 4..bin_at + 8], b"BIN\0");
    (json, glb[bin_at + 8..bin_at + 8 + bin_len].to_vec())
}

fn f32_at(bin: &[u8], offset: usize) -> f32 {
    f32::from_le_bytes(bin[offset..offset + 4].try_into().unwrap())
}

#[test]
fn the_tileset_is_the_hierarchy_and_every_content_decodes_to_its_mesh() {
    let h = support::street(40.0, FAR, &config());
    let files = tileset_files(&h, None, TileCompression::None).unwrap();
    assert_eq!(files[0].path, "tileset.json");
    let by_path: BTreeMap<&str, &[u8]> = files
        .iter()
        .map(|f| (f.path.as_str(), f.bytes.as_slice()))
        .collect();
    let tileset: Value = serde_json::from_slice(files[0].bytes.as_slice()).unwrap();
    assert_eq!(tileset["asset"]["version"], "1.1");
    assert_eq!(tileset["root"]["refine"], "REPLACE");
    assert!(tileset["root"].get("transform").is_none());
    assert!(tileset["root"].get("content").is_none());
    let root_error = tileset["root"]["geometricError"].as_f64().unwrap();
    let top: Vec<&Value> = tileset["root"]["children"]
        .as_array()
        .unwrap()
        .iter()
        .collect();
    assert_eq!(top.len(), h.roots().len());
    let mut seen = 0;
    // Walk the JSON tree alongside the hierarchy.
    let mut stack: Vec<(TileId, &Value, f64)> = h
        .roots()
        .into_iter()
        .zip(top)
        .map(|(id, tile)| (id, tile, root_error))
        .collect();
    while let Some((id, tile, parent_error)) = stack.pop() {
        seen += 1;
        let node = &h.nodes[&id];
        let error = tile["geometricError"].as_f64().unwrap();
        assert_eq!(error, node.geometric_error_m);
        assert!(error <= parent_error);
        let b: Vec<f64> = tile["boundingVolume"]["box"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        for a in 0..3 {
            let centre = 0.5 * (node.bounds_min_m[a] + node.bounds_max_m[a]);
            assert!((b[a] - centre).abs() < 1e-6);
            assert!(b[3 + 4 * a] >= 0.5 * (node.bounds_max_m[a] - node.bounds_min_m[a]) - 1e-9);
        }
        if node.mesh.is_empty() {
            assert!(tile.get("content").is_none());
        } else {
            let uri = tile["content"]["uri"].as_str().unwrap();
            let (json, bin) = chunks(by_path[uri]);
            // Positions: content +y up; turned back to +z up and offset by the node's
            // translation, they are the mesh's world vertices.
            let t: Vec<f64> = json["nodes"][0]["translation"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let count = json["accessors"][0]["count"].as_u64().unwrap() as usize;
            assert_eq!(count, node.mesh.vertex_count());
            assert_eq!(
                json["accessors"][2]["count"].as_u64().unwrap() as usize,
                node.mesh.triangle_count() * 3
            );
            for v in (0..count).step_by(97) {
                let q = [0, 1, 2].map(|k| f64::from(f32_at(&bin, v * 12 + k * 4)));
                let world = [t[0] + q[0], -(t[2] + q[2]), t[1] + q[1]];
                let truth = node.mesh.world(v).unwrap();
                for a in 0..3 {
                    assert!((world[a] - truth[a]).abs() < 1e-6, "{world:?} vs {truth:?}");
                }
            }
        }
        let children = tile["children"]
            .as_array()
            .map(Vec::as_slice)
            .unwrap_or(&[]);
        let expected: Vec<TileId> = h.children(id).map(|c| c.id).collect();
        assert_eq!(children.len(), expected.len());
        for (child, cid) in children.iter().zip(expected) {
            stack.push((cid, child, error));
        }
    }
    assert_eq!(seen, h.nodes.len());
    assert_eq!(
        files.len(),
        1 + h.nodes.values().filter(|n| !n.mesh.is_empty()).count()
    );
}

#[test]
fn a_geo_reference_places_the_world_origin_on_the_ellipsoid() {
    let h = support::street(20.0, [0.0; 3], &config());
    let geo = GeoReference {
        latitude_deg: 0.0,
        longitude_deg: 90.0,
        height_m: 10.0,
        world_point_m: [0.0; 3],
    };
    let files = tileset_files(&h, Some(&geo), TileCompression::None).unwrap();
    let tileset: Value = serde_json::from_slice(files[0].bytes.as_slice()).unwrap();
    let m: Vec<f64> = tileset["root"]["transform"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    // On the equator at 90° E: the origin at (0, a + h, 0), east is -x, north +z, up +y.
    let expect = [
        -1.0,
        0.0,
        0.0,
        0.0, //
        0.0,
        0.0,
        1.0,
        0.0, //
        0.0,
        1.0,
        0.0,
        0.0, //
        0.0,
        6_378_147.0,
        0.0,
        1.0,
    ];
    for (k, (got, want)) in m.iter().zip(expect).enumerate() {
        assert!((got - want).abs() < 1e-6, "entry {k}: {got} vs {want}");
    }
    // At the pole the origin sits at the semi-minor axis.
    let pole = GeoReference {
        latitude_deg: 90.0,
        longitude_deg: 0.0,
        height_m: 0.0,
        world_point_m: [0.0; 3],
    };
    let z = pole.ecef_from_world()[14];
    assert!((z - 6_356_752.314_245).abs() < 1e-3, "{z}");
    // A world point given as the reference lands there instead of the origin.
    let shifted = GeoReference {
        world_point_m: [100.0, 0.0, 0.0],
        ..geo
    };
    let t = shifted.ecef_from_world();
    assert!((t[12] - 100.0).abs() < 1e-6, "{}", t[12]);
    let bad = GeoReference {
        latitude_deg: 91.0,
        ..geo
    };
    assert!(
        tileset_files(&h, Some(&bad), TileCompression::None)
            .unwrap_err()
            .to_string()
            .contains("latitude")
    );
}
