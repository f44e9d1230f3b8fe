//! The atlas's cost on the street at the default configuration, printed (run with
//! `--ignored --nocapture`, release): encoded bytes per tile with and without atlases,
//! atlas sizes, PNG against JPEG for the atlas, and build time per tile.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use std::time::Instant;

use texel_lod::tiles::tile_glb;
use texel_lod::{LodConfig, atlas_png, build_from_field, encode_tile};

#[test]
#[ignore = "prints figures; slow in debug"]
fn atlas_figures_on_the_street() {
    let offset = [5.0e6, 4.2e6, 120.0];
    let small_tiles = LodConfig {
        tile_voxels: 64,
        tile_triangle_budget: 3_000,
        ..LodConfig::default()
    };
    for (length_m, base) in [(60.0, LodConfig::default()), (120.0, small_tiles)] {
        println!(
            "street {length_m} m, tile_voxels {}, budget {}",
            base.tile_voxels, base.tile_triangle_budget
        );
        for atlas_max_px in [0, 1024] {
            let config = LodConfig {
                atlas_max_px,
                ..base
            };
            let field = support::street_field(length_m, offset, &config);
            let start = Instant::now();
            let h = build_from_field(field, &config).unwrap();
            let seconds = start.elapsed().as_secs_f64();
            let tiles: Vec<_> = h.nodes.values().filter(|n| !n.mesh.is_empty()).collect();
            let n = tiles.len() as f64;
            let start = Instant::now();
            let encoded: usize = tiles.iter().map(|t| encode_tile(t).len()).sum();
            println!(
                "  encode {:.1} ms/tile",
                1e3 * start.elapsed().as_secs_f64() / tiles.len() as f64
            );
            let vertex_len_at = 4 + 2 + 1 + 8 + 8 + 8 * 11 + 12;
            let vertex_stream: usize = tiles
                .iter()
                .map(|t| {
                    let b = encode_tile(t);
                    u32::from_le_bytes(b[vertex_len_at..vertex_len_at + 4].try_into().unwrap())
                        as usize
                })
                .sum();
            println!("  vertex stream {:.0} B/tile", vertex_stream as f64 / n);
            let glb: usize = tiles.iter().map(|t| tile_glb(t).unwrap().len()).sum();
            println!(
                "atlas_max_px {atlas_max_px}: {} tiles (levels 0..={}), build {:.1} ms/tile, \
             {:.0} B/tile encoded, {:.0} B/tile glb, {:.0} triangles/tile, {:.0} vertices/tile",
                tiles.len(),
                h.top_lod,
                1e3 * seconds / n,
                encoded as f64 / n,
                glb as f64 / n,
                tiles.iter().map(|t| t.mesh.triangle_count()).sum::<usize>() as f64 / n,
                tiles.iter().map(|t| t.mesh.vertex_count()).sum::<usize>() as f64 / n,
            );
            let (mut png_total, mut jpeg_total) = (0usize, 0usize);
            for t in &tiles {
                let Some(texture) = &t.texture else { continue };
                let png = atlas_png(texture).unwrap().len();
                let mut jpeg = Vec::new();
                image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
                    .encode(
                        &texture.rgb,
                        texture.width,
                        texture.height,
                        image::ExtendedColorType::Rgb8,
                    )
                    .unwrap();
                png_total += png;
                jpeg_total += jpeg.len();
                if t.id.x % 4 == 0 {
                    println!(
                        "  {:?}: {} triangles, atlas {}×{} at {:.2} m, PNG {} B, JPEG q90 {} B",
                        t.id,
                        t.mesh.triangle_count(),
                        texture.width,
                        texture.height,
                        texture.texel_m,
                        png,
                        jpeg.len()
                    );
                }
            }
            if png_total > 0 {
                println!(
                    "  atlases: PNG {:.0} B/tile, JPEG q90 {:.0} B/tile",
                    png_total as f64 / n,
                    jpeg_total as f64 / n
                );
            }
        }
    }
}
