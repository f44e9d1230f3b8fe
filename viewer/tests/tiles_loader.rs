//! The decode thread: corrupt bytes give an error naming the tile and the other tiles
//! still load; a full queue hands the job back; through the frame driver, a corrupt
//! tile is reported and everything else becomes resident.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;
mod tiles_support;

use std::time::Duration;

use texel_lod::select::in_frustum;
use texel_lod::{LodNode, TileId, TileIndex, encode_tile};
use texel_surface::SurfaceMesh;
use texel_viewer::tiles::loader::TileLoader;
use texel_viewer::tiles::source::{EncodedTile, MemorySource};
use texel_viewer::tiles::{TileRenderer, TileSettings, lod_view};

fn node(x: i64) -> LodNode {
    let origin = [x as f64 * 4.0 + 2.0, 2.0, 0.0];
    let mut mesh = SurfaceMesh::empty(origin);
    for (i, p) in [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]
        .iter()
        .enumerate()
    {
        mesh.positions.push([p[0], p[1], 0.1 * i as f32]);
        mesh.colours.push([100, 150, 200]);
    }
    mesh.triangles = vec![[0, 1, 2], [0, 2, 3]];
    LodNode {
        id: TileId { lod: 0, x, y: 0 },
        mesh,
        bounds_min_m: [origin[0] - 1.0, 1.0, 0.0],
        bounds_max_m: [origin[0] + 1.0, 3.0, 0.3],
        geometric_error_m: 0.05,
        voxel_m: 0.1,
        merged_triangles: 2,
        texture: None,
    }
}

#[test]
fn corrupt_bytes_name_the_tile_and_the_others_load() {
    let mut loader = TileLoader::spawn(16).unwrap();
    let good: Vec<LodNode> = (0..4).map(node).collect();
    for (i, n) in good.iter().enumerate() {
        let job = EncodedTile {
            id: n.id,
            revision: 10 + i as u64,
            bytes: encode_tile(n),
        };
        loader.submit(job).unwrap();
    }
    // Truncated bytes; bytes with a flipped header; another tile's bytes.
    let mut truncated = encode_tile(&node(7));
    truncated.truncate(truncated.len() / 2);
    let mut flipped = encode_tile(&node(8));
    flipped[0] ^= 0xff;
    let jobs = [
        EncodedTile {
            id: node(7).id,
            revision: 3,
            bytes: truncated,
        },
        EncodedTile {
            id: node(8).id,
            revision: 3,
            bytes: flipped,
        },
        EncodedTile {
            id: node(9).id,
            revision: 3,
            bytes: encode_tile(&node(0)),
        },
    ];
    for job in jobs {
        loader.submit(job).unwrap();
    }
    // A tile already in flight is handed back.
    let again = EncodedTile {
        id: node(0).id,
        revision: 11,
        bytes: vec![],
    };
    assert_eq!(loader.submit(again.clone()), Err(again));
    let outcomes = loader.wait(Duration::from_secs(20));
    assert_eq!(outcomes.len(), 7);
    assert_eq!(loader.in_flight(), 0);
    let mut loaded: Vec<(TileId, u64)> = outcomes
        .iter()
        .filter_map(|o| o.as_ref().ok())
        .map(|d| (d.node.id, d.revision))
        .collect();
    loaded.sort();
    assert_eq!(
        loaded,
        good.iter()
            .enumerate()
            .map(|(i, n)| (n.id, 10 + i as u64))
            .collect::<Vec<_>>()
    );
    let mut errors: Vec<_> = outcomes.iter().filter_map(|o| o.as_ref().err()).collect();
    errors.sort_by_key(|e| e.id);
    assert_eq!(
        errors.iter().map(|e| e.id.x).collect::<Vec<_>>(),
        vec![7, 8, 9]
    );
    for e in &errors {
        println!("{e}");
        assert!(
            e.to_string().starts_with(&format!("tile 0/{}/0:", e.id.x)),
            "{e}"
        );
    }
    assert!(
        errors[2].to_string().contains("hold tile 0/0/0"),
        "{}",
        errors[2]
    );
}

#[test]
fn a_full_queue_hands_jobs_back() {
    let mut loader = TileLoader::spawn(1).unwrap();
    let (mut queued, mut refused) = (0, 0);
    for x in 0..200 {
        let n = node(x);
        match loader.submit(EncodedTile {
            id: n.id,
            revision: 1,
            bytes: encode_tile(&n),
        }) {
            Ok(()) => queued += 1,
            Err(job) => {
                assert_eq!(job.id, n.id);
                refused += 1;
            }
        }
    }
    let outcomes = loader.wait(Duration::from_secs(20));
    println!("queued {queued}, handed back {refused}");
    assert_eq!(outcomes.len(), queued);
    assert!(outcomes.iter().all(|o| o.is_ok()));
    assert_eq!(queued + refused, 200);
}

#[test]
fn the_frame_driver_reports_a_corrupt_tile_and_loads_the_rest() {
    let h = tiles_support::street(12.0, [0.0; 3]);
    let bad = *h.nodes.keys().find(|id| id.lod == 0).unwrap();
    let mut source = MemorySource::new(&h).with_delay(1);
    assert!(source.set_bytes(bad, b"TXLT not a tile".to_vec()));
    let settings = TileSettings {
        fade_s: 0.0,
        max_in_flight: 3,
        ..TileSettings::default()
    };
    let mut r = TileRenderer::new(support::gpu(), source, settings).unwrap();
    // Close to the ground over the bad tile, so every level down to it is wanted.
    let info = h.nodes[&bad].bounds_min_m;
    let cam = tiles_support::camera(
        [info[0] + 1.6, info[1] - 0.5, 1.0],
        [info[0] + 1.6, info[1] + 1.6, 0.0],
        [0.0; 3],
        160,
        120,
    );
    let mut errors = Vec::new();
    for frame in 0..60 {
        r.update(&cam, f64::from(frame) / 30.0);
        errors.extend(r.take_errors());
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(!errors.is_empty(), "no error reported");
    assert!(errors.iter().all(|e| e.id == bad), "{errors:?}");
    println!("{}", errors[0]);
    assert!(errors[0].to_string().contains(&bad.path()));
    assert!(!r.cache().contains(bad));
    // Everything else the view wanted loaded: the bad tile's ancestors and its
    // siblings in view.
    let view = lod_view(&cam);
    let parent = bad.parent().unwrap();
    assert!(r.cache().contains(parent));
    for sibling in parent.children().unwrap() {
        let Some(info) = h.tile(sibling) else {
            continue;
        };
        if sibling != bad && in_frustum(&view, &info) {
            assert!(r.cache().contains(sibling), "{sibling:?}");
        }
    }
    println!(
        "{} tiles resident, {} errors",
        r.cache().len(),
        errors.len()
    );
}
