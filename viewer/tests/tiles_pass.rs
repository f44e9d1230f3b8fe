//! The GPU tile pass against an independent CPU rasteriser of the same tiles (f64,
//! z-buffer, near-plane clipping, perspective-correct colours), on a street placed
//! 5,000 km from the world origin: coverage and colour agree, so the f64-relative
//! transforms and the display-colour convention hold.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;
mod tiles_support;

use std::collections::BTreeSet;

use texel_lod::{SelectConfig, TileId, select};
use texel_viewer::tiles::cache::TileCache;
use texel_viewer::tiles::image_target::render_tiles_to_image;
use texel_viewer::tiles::lod_view;
use texel_viewer::tiles::pass::TilePass;
use tiles_support::*;

const OFFSET: [f64; 3] = [4.0e5, 5.0e6, 120.0];

#[test]
fn gpu_tiles_match_the_cpu_rasteriser() {
    let start = std::time::Instant::now();
    let h = street(20.0, OFFSET);
    println!(
        "street: {} tiles in {:.1} s",
        h.nodes.len(),
        start.elapsed().as_secs_f64()
    );
    let gpu = support::gpu();
    let mut cache = TileCache::new(gpu, u64::MAX);
    let mut pass = TilePass::new(gpu);
    for (eye, target) in [
        ([5.0, -2.0, 2.5], [14.0, 1.0, 1.0]),
        ([-8.0, -14.0, 18.0], [12.0, 0.0, 0.0]),
    ] {
        let cam = camera(eye, target, OFFSET, 320, 240);
        let all: BTreeSet<TileId> = h.nodes.keys().copied().collect();
        let sel = select(
            &h,
            &lod_view(&cam),
            &|id| all.contains(&id),
            &BTreeSet::new(),
            &SelectConfig::default(),
        );
        let nodes: Vec<_> = sel.draw.iter().map(|id| &h.nodes[id]).collect();
        for n in &nodes {
            cache.insert(n, 1, 1).unwrap();
        }
        let tiles: Vec<_> = sel.draw.iter().map(|id| cache.get(*id).unwrap()).collect();
        let (img, counts) =
            render_tiles_to_image(gpu, &mut pass, &tiles, &cam, BACKGROUND).unwrap();
        let cpu = cpu_render(&nodes, &cam);
        let gpu_cov = covered(&img);
        let (mut both, mut either, mut close) = (0usize, 0usize, 0usize);
        let (mut sum_gpu, mut sum_cpu) = ([0.0f64; 3], [0.0f64; 3]);
        for (i, p) in img.pixels().enumerate() {
            let (g, c) = (gpu_cov[i], cpu[i]);
            if g || c.is_some() {
                either += 1;
            }
            let (true, Some(c)) = (g, c) else { continue };
            both += 1;
            for k in 0..3 {
                sum_gpu[k] += f64::from(p[k]);
                sum_cpu[k] += c[k];
            }
            if (0..3).all(|k| (f64::from(p[k]) - c[k]).abs() <= 3.0) {
                close += 1;
            }
        }
        let iou = both as f64 / either.max(1) as f64;
        let mean_gpu = sum_gpu.map(|s| s / both.max(1) as f64);
        let mean_cpu = sum_cpu.map(|s| s / both.max(1) as f64);
        let close_fraction = close as f64 / both.max(1) as f64;
        println!(
            "eye {eye:?}: {} tiles, {} triangles; {both} pixels covered by both, IoU {iou:.4}; \
             mean colour GPU {mean_gpu:.2?} CPU {mean_cpu:.2?}; within 3/255 {close_fraction:.4}",
            counts.tiles, counts.triangles
        );
        assert!(both > 20_000, "{both} pixels covered");
        assert!(iou > 0.99, "coverage IoU {iou}");
        for k in 0..3 {
            assert!(
                (mean_gpu[k] - mean_cpu[k]).abs() < 1.0,
                "{mean_gpu:?} vs {mean_cpu:?}"
            );
        }
        assert!(close_fraction > 0.97, "{close_fraction}");
    }
    println!("test took {:.1} s", start.elapsed().as_secs_f64());
}
