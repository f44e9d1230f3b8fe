//! `texeld export --format 3dtiles` on a simulated capture, read by independent
//! readers: tileset.json passes the 3D Tiles 1.1 JSON schema, every tile's content
//! passes the Khronos glTF validator with zero errors, and loaders.gl reads the whole
//! tileset back with the vertex counts we wrote and every vertex inside its tile's
//! bounding volume. The checks are shown to fail on a broken tileset and a broken tile.
//! CesiumJS in headless Chromium opens a street's tileset and shows the model in the
//! colours the tiles hold.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![allow(clippy::needless_range_loop)] // r, g and b side by side read clearer indexed

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;
use sims::{CaptureOptions, Scene, SimOptions, Simulator};

fn render_hall(path: &Path, frames: usize) {
    render("long-hall", path, frames);
}

fn render(scene: &str, path: &Path, frames: usize) {
    let scene =
        Scene::load(&texel_e2e::repo_root().join(format!("configs/scenes/{scene}.toml"))).unwrap();
    let sim = Simulator::with_options(
        scene,
        &SimOptions {
            seed: 3,
            frames: Some(frames),
            ..SimOptions::default()
        },
    )
    .unwrap();
    let options = CaptureOptions {
        writer: texel::capture::WriterOptions {
            sync_to_disk: false,
            ..Default::default()
        },
        ..Default::default()
    };
    sims::render_capture(&sim, path, &options, &mut |_, _| {}).unwrap();
}

fn texeld(args: &[&OsStr]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `texeld export CAPTURE --format 3dtiles EXTRA --out OUT`.
fn export_3dtiles(capture: &Path, out: &Path, extra: &[&OsStr]) -> (bool, String, String) {
    let mut args = vec![
        OsStr::new("export"),
        capture.as_os_str(),
        OsStr::new("--format"),
        OsStr::new("3dtiles"),
    ];
    args.extend_from_slice(extra);
    args.extend([OsStr::new("--out"), out.as_os_str()]);
    texeld(&args)
}

fn schema_dir() -> PathBuf {
    texel_e2e::repo_root().join("lod/tests/schema/3d-tiles-1.1")
}

fn check(dir: &Path) -> Value {
    let out = texel_e2e::run_node(
        "check-tileset.mjs",
        &[dir.as_os_str(), schema_dir().as_os_str()],
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Vertex count of a GLB's first accessor, read from its JSON chunk.
fn glb_vertices(bytes: &[u8]) -> u64 {
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let json: Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
    json["accessors"][0]["count"].as_u64().unwrap()
}

fn content_uris(tile: &Value, out: &mut Vec<String>) {
    if let Some(uri) = tile["content"]["uri"].as_str() {
        out.push(uri.to_string());
    }
    for child in tile["children"]
        .as_array()
        .map(Vec::as_slice)
        .unwrap_or(&[])
    {
        content_uris(child, out);
    }
}

fn copy_dir(from: &Path, to: &Path) {
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            std::fs::create_dir_all(&target).unwrap();
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

#[test]
fn a_3d_tiles_export_passes_the_schema_the_gltf_validator_and_loaders_gl() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("hall.mcap");
    render_hall(&capture, 45);
    // Small tiles, so a few metres of hall make a tree of several levels.
    let lod = dir.path().join("lod.toml");
    std::fs::write(
        &lod,
        "leaf_voxel_m = 0.05\ntile_voxels = 16\ntile_triangle_budget = 1500\n",
    )
    .unwrap();
    let tiles = dir.path().join("tiles");
    let (ok, stdout, stderr) = export_3dtiles(
        &capture,
        &tiles,
        &[
            OsStr::new("--lod-config"),
            lod.as_os_str(),
            OsStr::new("--georef"),
            OsStr::new("47.3769,8.5417,408"),
        ],
    );
    assert!(ok, "{stderr}");
    assert!(
        stdout.contains("exported the model as 3D Tiles"),
        "{stdout}"
    );
    let tileset: Value =
        serde_json::from_slice(&std::fs::read(tiles.join("tileset.json")).unwrap()).unwrap();
    assert_eq!(tileset["root"]["transform"].as_array().unwrap().len(), 16);
    let mut uris = Vec::new();
    content_uris(&tileset["root"], &mut uris);
    assert!(uris.len() >= 6, "{} tiles", uris.len());
    assert!(uris.iter().any(|u| u.starts_with("tiles/2/")), "{uris:?}");
    let written: u64 = uris
        .iter()
        .map(|u| glb_vertices(&std::fs::read(tiles.join(u)).unwrap()))
        .sum();

    let report = check(&tiles);
    eprintln!("{stdout}{report}");
    assert_eq!(report["schemaErrors"], Value::Array(vec![]), "{report}");
    assert_eq!(report["gltfErrors"], 0, "{report}");
    assert_eq!(report["contents"].as_u64().unwrap() as usize, uris.len());
    assert_eq!(report["loaderTiles"].as_u64().unwrap() as usize, uris.len());
    assert_eq!(
        report["loaderVertices"].as_u64().unwrap(),
        written,
        "{report}"
    );
    assert_eq!(report["outsideBox"], 0, "{report}");

    // The fields paged out after every scan and tile build the same tileset, byte for
    // byte.
    let paged = dir.path().join("tiles-paged");
    let (ok, stdout_paged, stderr) = export_3dtiles(
        &capture,
        &paged,
        &[
            OsStr::new("--lod-config"),
            lod.as_os_str(),
            OsStr::new("--georef"),
            OsStr::new("47.3769,8.5417,408"),
            OsStr::new("--field-memory-mb"),
            OsStr::new("0"),
        ],
    );
    assert!(ok, "{stderr}");
    eprintln!("{stdout_paged}");
    assert!(
        stdout_paged.contains("fields at most 0 MiB in memory"),
        "{stdout_paged}"
    );
    for uri in uris.iter().map(String::as_str).chain(["tileset.json"]) {
        assert!(
            std::fs::read(paged.join(uri)).unwrap() == std::fs::read(tiles.join(uri)).unwrap(),
            "{uri} differs when the fields are paged"
        );
    }

    // The same tileset with its geometry meshopt-compressed: the validator knows the
    // extension, and loaders.gl decodes it to the same vertices, inside their boxes.
    let compressed = dir.path().join("tiles-meshopt");
    let (ok, stdout_meshopt, stderr) = export_3dtiles(
        &capture,
        &compressed,
        &[
            OsStr::new("--lod-config"),
            lod.as_os_str(),
            OsStr::new("--meshopt"),
        ],
    );
    assert!(ok, "{stderr}");
    let report = check(&compressed);
    eprintln!("{stdout_meshopt}{report}");
    assert_eq!(report["gltfErrors"], 0, "{report}");
    assert_eq!(report["loaderTiles"].as_u64().unwrap() as usize, uris.len());
    assert_eq!(
        report["loaderVertices"].as_u64().unwrap(),
        written,
        "{report}"
    );
    assert_eq!(report["outsideBox"], 0, "{report}");
    let geometry_bytes = |root: &Path| -> (u64, u64) {
        let mut total = (0, 0);
        for uri in &uris {
            let glb = std::fs::read(root.join(uri)).unwrap();
            let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
            let json: Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
            // The image, where there is one, is the same PNG in both.
            let image = json["images"][0]["bufferView"].as_u64().map_or(0, |v| {
                json["bufferViews"][v as usize]["byteLength"]
                    .as_u64()
                    .unwrap()
            });
            total.0 += glb.len() as u64 - image;
            total.1 += glb.len() as u64;
        }
        total
    };
    let (plain, plain_all) = geometry_bytes(&tiles);
    let (packed, packed_all) = geometry_bytes(&compressed);
    eprintln!(
        "meshopt: geometry {packed} bytes against {plain} ({:.2}x smaller); whole tiles {packed_all} against {plain_all}",
        plain as f64 / packed as f64
    );
    // Lossless codecs on f32 positions: about half the bytes (1.91x on this hall).
    assert!(packed * 3 < plain * 2, "{packed} against {plain}");

    // The checks can fail: a tileset without its asset and a tile that claims more
    // vertices than it holds are both caught.
    let broken = dir.path().join("broken");
    std::fs::create_dir_all(&broken).unwrap();
    copy_dir(&tiles, &broken);
    let mut bad = tileset.clone();
    bad.as_object_mut().unwrap().remove("asset");
    std::fs::write(
        broken.join("tileset.json"),
        serde_json::to_vec(&bad).unwrap(),
    )
    .unwrap();
    let glb_path = broken.join(&uris[0]);
    let mut glb = std::fs::read(&glb_path).unwrap();
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let text = String::from_utf8(glb[20..20 + json_len].to_vec()).unwrap();
    // Same length, so the container stays well formed: only the primitive's mode
    // (4, triangles) becomes one glTF does not have.
    assert!(text.contains("\"mode\":4"), "{text}");
    let patched = text.replacen("\"mode\":4", "\"mode\":9", 1);
    glb[20..20 + json_len].copy_from_slice(patched.as_bytes());
    std::fs::write(&glb_path, &glb).unwrap();
    let report = check(&broken);
    assert!(report["gltfErrors"].as_u64().unwrap() > 0, "{report}");
    assert!(
        !report["schemaErrors"].as_array().unwrap().is_empty(),
        "{report}"
    );
}

#[test]
fn bad_3d_tiles_arguments_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("hall.mcap");
    render_hall(&capture, 3);
    let out = dir.path().join("t");
    let (ok, _, stderr) = export_3dtiles(
        &capture,
        &out,
        &[OsStr::new("--georef"), OsStr::new("95,8,400")],
    );
    assert!(!ok && stderr.contains("latitude"), "{stderr}");
    let lod = dir.path().join("lod.toml");
    std::fs::write(&lod, "tile_voxel = 16\n").unwrap();
    let (ok, _, stderr) = export_3dtiles(
        &capture,
        &out,
        &[OsStr::new("--lod-config"), lod.as_os_str()],
    );
    assert!(
        !ok && stderr.contains("tile_voxel") && stderr.contains("lod.toml"),
        "{stderr}"
    );
    let (ok, _, stderr) = export_3dtiles(&capture, &out, &[OsStr::new("--frame"), OsStr::new("0")]);
    assert!(!ok && stderr.contains("whole model"), "{stderr}");
    assert!(!out.join("tileset.json").exists());
    // --meshopt shapes a tileset: with another format it is refused by name.
    let (ok, _, stderr) = texeld(&[
        OsStr::new("export"),
        capture.as_os_str(),
        OsStr::new("--format"),
        OsStr::new("ply"),
        OsStr::new("--meshopt"),
        OsStr::new("--out"),
        dir.path().join("m.ply").as_os_str(),
    ]);
    assert!(!ok && stderr.contains("--meshopt"), "{stderr}");
}

/// Mean sRGB colour of the vertices of the coarsest tiles: decoded from the GLBs'
/// linear 16-bit COLOR_0 with the sRGB transfer function, or, for a tile coloured by
/// its atlas, the atlas's (sRGB) texel under each vertex's TEXCOORD_0.
fn finest_tiles_mean_colour(dir: &Path, tileset: &Value) -> [f64; 3] {
    let mut uris = Vec::new();
    content_uris(&tileset["root"], &mut uris);
    let deepest = uris
        .iter()
        .filter_map(|u| u.split('/').nth(1).and_then(|l| l.parse::<u32>().ok()))
        .max()
        .unwrap();
    let mut sum = [0.0f64; 3];
    let mut count = 0.0;
    for uri in uris
        .iter()
        .filter(|u| u.starts_with(&format!("tiles/{deepest}/")))
    {
        let bytes = std::fs::read(dir.join(uri)).unwrap();
        let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
        let json: Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
        let bin = &bytes[20 + json_len + 8..];
        let n = json["accessors"][1]["count"].as_u64().unwrap() as usize;
        let offset = json["bufferViews"][1]["byteOffset"].as_u64().unwrap() as usize;
        let attributes = &json["meshes"][0]["primitives"][0]["attributes"];
        if attributes.get("TEXCOORD_0").is_some() {
            assert!(attributes.get("COLOR_0").is_none());
            assert_eq!(json["accessors"][1]["componentType"], 5126);
            let view =
                &json["bufferViews"][json["images"][0]["bufferView"].as_u64().unwrap() as usize];
            let at = view["byteOffset"].as_u64().unwrap() as usize;
            let len = view["byteLength"].as_u64().unwrap() as usize;
            let atlas =
                image::load_from_memory_with_format(&bin[at..at + len], image::ImageFormat::Png)
                    .unwrap()
                    .to_rgb8();
            let f = |at: usize| f32::from_le_bytes(bin[at..at + 4].try_into().unwrap());
            for v in 0..n {
                let uv = [f(offset + v * 8), f(offset + v * 8 + 4)];
                let x = ((uv[0] * atlas.width() as f32) as u32).min(atlas.width() - 1);
                let y = ((uv[1] * atlas.height() as f32) as u32).min(atlas.height() - 1);
                let p = atlas.get_pixel(x, y);
                for k in 0..3 {
                    sum[k] += f64::from(p[k]);
                }
                count += 1.0;
            }
            continue;
        }
        assert_eq!(json["accessors"][1]["componentType"], 5123);
        for v in 0..n {
            for k in 0..3 {
                let at = offset + v * 8 + k * 2;
                let linear = f64::from(u16::from_le_bytes([bin[at], bin[at + 1]])) / 65535.0;
                let srgb = if linear <= 0.0031308 {
                    12.92 * linear
                } else {
                    1.055 * linear.powf(1.0 / 2.4) - 0.055
                };
                sum[k] += srgb * 255.0;
            }
            count += 1.0;
        }
    }
    sum.map(|s| s / count)
}

#[test]
fn cesium_opens_a_street_tileset_and_shows_the_model_in_its_colours() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("street.mcap");
    // Two seconds of the street: the camera pans from the road to the left facades.
    render("street", &capture, 60);
    let tiles = dir.path().join("tiles");
    let (ok, stdout, stderr) = export_3dtiles(
        &capture,
        &tiles,
        &[OsStr::new("--georef"), OsStr::new("47.3769,8.5417,408")],
    );
    assert!(ok, "{stderr}");
    let tileset: Value =
        serde_json::from_slice(&std::fs::read(tiles.join("tileset.json")).unwrap()).unwrap();
    let expected = finest_tiles_mean_colour(&tiles, &tileset);
    let png = dir.path().join("cesium.png");
    let out = texel_e2e::run_node("cesium-view.mjs", &[tiles.as_os_str(), png.as_os_str()]);
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("{stdout}{report} expected mean colour {expected:?}");
    assert!(report.get("error").is_none(), "{report}");
    assert_eq!(report["pageErrors"], Value::Array(vec![]), "{report}");
    assert_eq!(report["allLoaded"], true, "{report}");
    assert!(report["tilesLoaded"].as_u64().unwrap() >= 1, "{report}");
    assert!(png.exists());
    // The model fills a real part of the view (framed on its bounding sphere)...
    let coverage = report["coverage"].as_f64().unwrap();
    assert!(coverage > 0.01, "coverage {coverage}");
    // ...in the colours the tiles hold: unlit vertex colours come out as stored, so a
    // wrong transfer function (linear shown as sRGB brightens mid-greys by ~40 %) or
    // lit shading would move the mean far more than what framing changes.
    let mean: Vec<f64> = report["meanRgb"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let brightness = |c: &[f64]| (c[0] + c[1] + c[2]) / 3.0;
    let ratio = brightness(&mean) / brightness(&expected);
    assert!(
        (0.85..1.15).contains(&ratio),
        "shown {mean:?}, held {expected:?}"
    );
    for k in 0..3 {
        assert!(
            (mean[k] - expected[k]).abs() < 30.0,
            "shown {mean:?}, held {expected:?}"
        );
    }

    // The same tileset meshopt-compressed: CesiumJS decodes it and shows the same
    // picture (the same view, so the same coverage and colours within a little).
    let compressed = dir.path().join("tiles-meshopt");
    let (ok, _, stderr) = export_3dtiles(
        &capture,
        &compressed,
        &[
            OsStr::new("--georef"),
            OsStr::new("47.3769,8.5417,408"),
            OsStr::new("--meshopt"),
        ],
    );
    assert!(ok, "{stderr}");
    let png = dir.path().join("cesium-meshopt.png");
    let out = texel_e2e::run_node(
        "cesium-view.mjs",
        &[compressed.as_os_str(), png.as_os_str()],
    );
    let packed: Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("meshopt: {packed}");
    assert!(packed.get("error").is_none(), "{packed}");
    assert_eq!(packed["pageErrors"], Value::Array(vec![]), "{packed}");
    assert_eq!(packed["allLoaded"], true, "{packed}");
    let packed_coverage = packed["coverage"].as_f64().unwrap();
    assert!(
        (packed_coverage - coverage).abs() < 0.1 * coverage,
        "coverage {packed_coverage} against {coverage}"
    );
    for k in 0..3 {
        let c = packed["meanRgb"][k].as_f64().unwrap();
        assert!((c - mean[k]).abs() < 5.0, "shown {packed}, plain {mean:?}");
    }
}
