//! The GPU tile cache: never above its budget, evicts the least recently used tiles
//! first and never one used in the current frame, a new revision replaces the old
//! (and is what the pass draws).
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;
mod tiles_support;

use texel_lod::{LodNode, TileId, TileTexture};
use texel_surface::SurfaceMesh;
use texel_viewer::tiles::cache::{Inserted, TileCache, tile_gpu_bytes};
use texel_viewer::tiles::image_target::render_tiles_to_image;
use texel_viewer::tiles::pass::TilePass;

/// A tile holding `quads` unit squares at height 0 of one colour, over tile (x, 0).
fn node(x: i64, quads: usize, colour: [u8; 3]) -> LodNode {
    let origin = [x as f64 * 4.0, 0.0, 0.0];
    let mut mesh = SurfaceMesh::empty(origin);
    for q in 0..quads {
        let base = mesh.positions.len() as u32;
        let dx = q as f32 * 0.01;
        for p in [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]] {
            mesh.positions.push([p[0] + dx, p[1], 0.0]);
            mesh.colours.push(colour);
        }
        mesh.triangles.push([base, base + 1, base + 2]);
        mesh.triangles.push([base, base + 2, base + 3]);
    }
    LodNode {
        id: TileId { lod: 0, x, y: 0 },
        mesh,
        bounds_min_m: [origin[0] - 1.0, -1.0, 0.0],
        bounds_max_m: [origin[0] + 1.0, 1.0, 0.0],
        geometric_error_m: 0.05,
        voxel_m: 0.1,
        merged_triangles: 2 * quads,
        texture: None,
    }
}

fn id(x: i64) -> TileId {
    TileId { lod: 0, x, y: 0 }
}

#[test]
fn the_cache_keeps_its_budget_and_evicts_least_recently_used() {
    let start = std::time::Instant::now();
    let gpu = support::gpu();
    let one = tile_gpu_bytes(&node(0, 10, [0; 3]));
    assert_eq!(one, 10 * 4 * 24 + 10 * 2 * 12);
    let mut cache = TileCache::new(gpu, 3 * one + one / 2);
    for (frame, x) in [(1, 0), (2, 1), (3, 2)] {
        assert_eq!(
            cache.insert(&node(x, 10, [0; 3]), 1, frame).unwrap(),
            Inserted::Uploaded { evicted: vec![] }
        );
    }
    assert_eq!((cache.len(), cache.resident_bytes()), (3, 3 * one));
    // Tile 0 is the least recently used.
    assert_eq!(
        cache.insert(&node(3, 10, [0; 3]), 1, 4).unwrap(),
        Inserted::Uploaded {
            evicted: vec![id(0)]
        }
    );
    // Tile 1 drawn again: now tile 2 is the oldest.
    assert!(cache.mark_used(id(1), 5));
    assert_eq!(
        cache.insert(&node(4, 10, [0; 3]), 1, 5).unwrap(),
        Inserted::Uploaded {
            evicted: vec![id(2)]
        }
    );
    // Everything resident used in frame 6: nothing may go, the new tile is refused.
    for t in [1, 3, 4] {
        cache.mark_used(id(t), 6);
    }
    assert_eq!(
        cache.insert(&node(5, 10, [0; 3]), 1, 6).unwrap(),
        Inserted::OverBudget { needed_bytes: one }
    );
    assert_eq!(cache.len(), 3);
    // Larger than the whole budget: refused, nothing evicted.
    assert!(matches!(
        cache.insert(&node(6, 40, [0; 3]), 1, 7).unwrap(),
        Inserted::OverBudget { .. }
    ));
    assert_eq!(cache.len(), 3);
    // A long run of mixed sizes and uses: never above the budget, the accounting
    // exact, tiles used in the current frame never evicted.
    let mut seed = 12345u64;
    let mut rand = move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 33) as usize
    };
    let mut peak = 0;
    for frame in 10..200u64 {
        let used: Vec<TileId> = cache.ids().filter(|_| rand() % 3 == 0).collect();
        for t in &used {
            cache.mark_used(*t, frame);
        }
        let x = (rand() % 40) as i64;
        let quads = 1 + rand() % 12;
        let outcome = cache.insert(&node(x, quads, [0; 3]), frame, frame).unwrap();
        if let Inserted::Uploaded { evicted } = &outcome {
            for t in evicted {
                assert!(!used.contains(t), "{t:?} used in frame {frame} was evicted");
            }
        }
        let sum: u64 = cache.ids().map(|t| cache.get(t).unwrap().bytes).sum();
        assert_eq!(sum, cache.resident_bytes());
        assert!(cache.resident_bytes() <= cache.budget_bytes());
        peak = peak.max(cache.resident_bytes());
    }
    println!(
        "budget {} bytes, peak {peak} bytes, {} tiles at the end; {:.2} s",
        cache.budget_bytes(),
        cache.len(),
        start.elapsed().as_secs_f64()
    );
}

#[test]
fn a_new_revision_replaces_the_old_one() {
    let gpu = support::gpu();
    let mut cache = TileCache::new(gpu, 1 << 20);
    let red = node(0, 1, [250, 10, 10]);
    let green = node(0, 3, [10, 250, 10]);
    assert!(matches!(
        cache.insert(&red, 1, 1).unwrap(),
        Inserted::Uploaded { .. }
    ));
    assert!(matches!(
        cache.insert(&green, 2, 2).unwrap(),
        Inserted::Uploaded { .. }
    ));
    assert_eq!((cache.len(), cache.revision(id(0))), (1, Some(2)));
    assert_eq!(cache.resident_bytes(), tile_gpu_bytes(&green));
    // An older or equal revision arriving late changes nothing.
    assert_eq!(
        cache.insert(&red, 1, 3).unwrap(),
        Inserted::Stale {
            resident_revision: 2
        }
    );
    assert_eq!(
        cache.insert(&red, 2, 3).unwrap(),
        Inserted::Stale {
            resident_revision: 2
        }
    );
    // The pass draws the new revision.
    let cam = tiles_support::camera([0.0, -0.01, 3.0], [0.0, 0.0, 0.0], [0.0; 3], 64, 48);
    let mut pass = TilePass::new(gpu);
    let tile = cache.get(id(0)).unwrap();
    let (img, counts) =
        render_tiles_to_image(gpu, &mut pass, &[tile], &cam, tiles_support::BACKGROUND).unwrap();
    assert_eq!(counts.triangles, 6);
    let centre = img.get_pixel(32, 24);
    assert_eq!([centre[0], centre[1], centre[2]], [10, 250, 10]);
    assert_eq!(cache.remove(id(0)), Some(tile_gpu_bytes(&green)));
    assert_eq!((cache.len(), cache.resident_bytes()), (0, 0));
}

/// Through the frame driver: a rebuilt tile listed with a new revision is loaded
/// again while the old one is still drawn, then replaces it.
#[test]
fn the_driver_reloads_a_tile_listed_with_a_new_revision() {
    use std::time::Duration;
    use texel_viewer::tiles::source::MemorySource;
    use texel_viewer::tiles::{TileRenderer, TileSettings};
    let red = node(0, 1, [250, 10, 10]);
    let green = node(0, 3, [10, 250, 10]);
    let settings = TileSettings {
        fade_s: 0.0,
        background: tiles_support::BACKGROUND,
        ..TileSettings::default()
    };
    let mut r = TileRenderer::new(
        support::gpu(),
        MemorySource::from_nodes([&red]).with_delay(2),
        settings,
    )
    .unwrap();
    let cam = tiles_support::camera([0.0, -0.01, 3.0], [0.0, 0.0, 0.0], [0.0; 3], 64, 48);
    let centre = |img: &image::RgbaImage| {
        let p = img.get_pixel(32, 24);
        [p[0], p[1], p[2]]
    };
    r.update(&cam, 0.0);
    r.finish_loads(Duration::from_secs(10));
    let (img, stats) = r.render_to_image(&cam, 0.1).unwrap();
    assert_eq!(centre(&img), [250, 10, 10], "{stats:?}");
    assert_eq!(r.source_mut().replace(&green), 2);
    // The next frame asks for revision 2 and still draws revision 1.
    let (img, stats) = r.render_to_image(&cam, 0.2).unwrap();
    assert_eq!(centre(&img), [250, 10, 10], "{stats:?}");
    r.finish_loads(Duration::from_secs(10));
    let (img, stats) = r.render_to_image(&cam, 0.3).unwrap();
    assert_eq!(centre(&img), [10, 250, 10], "{stats:?}");
    assert_eq!(r.cache().revision(id(0)), Some(2));
    assert_eq!((stats.resident_tiles, stats.triangles_drawn), (1, 6));
    assert_eq!(r.source_mut().requests(), 2);
}

/// A tile with an atlas draws the atlas's colours, not its vertex colours, and its
/// texels count against the budget.
#[test]
fn a_textured_tile_draws_its_atlas() {
    let gpu = support::gpu();
    let (red, blue) = ([250, 10, 10], [10, 10, 250]);
    // The vertex colours are green: none of it may show.
    let mut textured = node(0, 1, [10, 250, 10]);
    // One quad (two triangles) over x in [-1, 1]; u runs with x over a 4 × 1 atlas,
    // red on the left half, blue on the right.
    let uvs = textured
        .mesh
        .positions
        .iter()
        .map(|p| [(p[0] + 1.0) / 2.0, 0.5])
        .collect();
    textured.texture = Some(TileTexture {
        width: 4,
        height: 1,
        texel_m: 0.5,
        rgb: [red, red, blue, blue].concat(),
        uvs,
    });
    assert_eq!(tile_gpu_bytes(&textured), 4 * 24 + 2 * 12 + 4 * 4);
    let mut cache = TileCache::new(gpu, 1 << 20);
    cache.insert(&textured, 1, 1).unwrap();
    assert_eq!(cache.resident_bytes(), tile_gpu_bytes(&textured));
    let cam = tiles_support::camera([0.0, -0.01, 3.0], [0.0, 0.0, 0.0], [0.0; 3], 64, 48);
    let mut pass = TilePass::new(gpu);
    let tile = cache.get(id(0)).unwrap();
    let (img, _) =
        render_tiles_to_image(gpu, &mut pass, &[tile], &cam, tiles_support::BACKGROUND).unwrap();
    let (mut reds, mut blues) = ([0usize; 2], [0usize; 2]);
    for (x, _, p) in img.enumerate_pixels() {
        let c = [p[0], p[1], p[2]];
        assert!(p[1] < 200, "vertex colour shows at column {x}: {c:?}");
        let half = usize::from(x >= 32);
        if c == red {
            reds[half] += 1;
        }
        if c == blue {
            blues[half] += 1;
        }
    }
    // World x increases to the right of the image in this view (see the camera).
    let (left, right) = if reds[0] > reds[1] { (0, 1) } else { (1, 0) };
    assert!(
        reds[left] > 20 && blues[right] > 20,
        "red {reds:?}, blue {blues:?}"
    );
    assert_eq!(
        (reds[right], blues[left]),
        (0, 0),
        "red {reds:?}, blue {blues:?}"
    );
}
