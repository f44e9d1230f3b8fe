//! The scans below the finest tiles: close to a wall the finest tiles are too coarse
//! for the view, so the scans under them are drawn with view-dependent blending and
//! the tiles give way on their surface (the frame matches drawing the scans alone);
//! from far off no scan is drawn (the frame is the tiles' alone); a tile in front of
//! the scans covers them and one behind them does not show through.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use texel::model::Model;
use texel_lod::{Hierarchy, LodConfig, LodModel, SelectConfig, build_from_field};
use texel_surface::{Sample, Tsdf, TsdfConfig};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::gpu::{RenderSettings, Renderer};
use texel_viewer::scenes;
use texel_viewer::tiles::hybrid::HybridSettings;
use texel_viewer::tiles::source::MemorySource;
use texel_viewer::tiles::{TileRenderer, TileSettings, look_at};

const WIDTH: u32 = 240;
const HEIGHT: u32 = 180;
/// Pixels no scan or tile drew: the scan renderer's and the tiles' background.
const BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];
const BACKGROUND_U8: [u8; 3] = [255, 0, 255];

fn config() -> LodConfig {
    LodConfig {
        leaf_voxel_m: 0.1,
        tile_voxels: 32,
        tile_triangle_budget: 2_000,
        ..LodConfig::default()
    }
}

/// The corridor: a wall at z = 5.05 seen by 12 scans a metre apart.
fn corridor() -> Model {
    scenes::corridor(&scenes::test_sensor(), 12)
}

/// The corridor's scans fused into a hierarchy.
fn corridor_tiles(model: &Model) -> Hierarchy {
    let mut lod = LodModel::new(config()).unwrap();
    for (s, scan) in model.resident() {
        lod.add_scan(scan, &s.world_from_scan);
    }
    lod.rebuild(usize::MAX);
    lod.hierarchy().unwrap()
}

/// A plane z = `z_m` over x in [0, 12], y in [-1.5, 0.5], in one colour, seen from
/// z = 0: a hierarchy with no scans of its own.
fn plane_tiles(z_m: f64, colour: [u8; 3]) -> Hierarchy {
    let config = config();
    let mut field = Tsdf::new(TsdfConfig {
        voxel_m: config.leaf_voxel_m,
        truncation_voxels: config.truncation_voxels,
    })
    .unwrap();
    let mut samples = Vec::new();
    for i in 0..=240 {
        for j in 0..=40 {
            let (x, y) = (f64::from(i) * 0.05, -1.5 + f64::from(j) * 0.05);
            samples.push(Sample {
                point_m: [x, y, z_m],
                centre_m: [x, y, 0.0],
                weight: 1.0,
                colour: Some(colour),
            });
        }
    }
    field.integrate(&samples);
    build_from_field(field, &config).unwrap()
}

fn camera(eye: [f64; 3], target: [f64; 3]) -> VirtualCamera {
    VirtualCamera::new(
        look_at(eye, target, [0.0, -1.0, 0.0]).unwrap(),
        60.0,
        WIDTH,
        HEIGHT,
    )
    .unwrap()
}

fn scan_settings() -> RenderSettings {
    let mut s = RenderSettings::default();
    s.composite.background = BACKGROUND;
    s
}

fn tile_settings(hybrid: bool, margin_m: f64) -> TileSettings {
    TileSettings {
        // Every finest tile in view too coarse for it (no easing towards the edges):
        // all of them show their scans.
        select: SelectConfig {
            max_error_px: 0.5,
            centre_weight: 0.0,
            ..SelectConfig::default()
        },
        fade_s: 0.0,
        background: BACKGROUND,
        hybrid: HybridSettings {
            enabled: hybrid,
            // Every scan reaching a tile: the frame can then match the scans alone.
            scans_per_tile: 64,
            margin_m,
            ..HybridSettings::default()
        },
        ..TileSettings::default()
    }
}

/// Draws `camera` three ways: hybrid, the scans alone, the tiles alone.
struct Frames {
    hybrid: image::RgbaImage,
    scans: image::RgbaImage,
    tiles: image::RgbaImage,
    tiles_with_scans: usize,
    scans_drawn: usize,
}

fn frames(model: &Model, h: &Hierarchy, camera: &VirtualCamera, margin_m: f64) -> Frames {
    frames_with(model, h, camera, tile_settings(true, margin_m), 2)
}

/// As [`frames`], with the hybrid's settings and number of frames given (the last is
/// returned; each feeds its coverage back).
fn frames_with(
    model: &Model,
    h: &Hierarchy,
    camera: &VirtualCamera,
    hybrid_settings: TileSettings,
    count: usize,
) -> Frames {
    let margin_m = hybrid_settings.hybrid.margin_m;
    let gpu = support::gpu();
    let mut renderer = Renderer::new(gpu);
    renderer.sync_model(model).unwrap();
    let settings = scan_settings();
    let mut hybrid = TileRenderer::new(gpu, MemorySource::new(h), hybrid_settings).unwrap();
    hybrid.preload_all(std::time::Duration::from_secs(60));
    let mut tiles_alone =
        TileRenderer::new(gpu, MemorySource::new(h), tile_settings(false, margin_m)).unwrap();
    tiles_alone.preload_all(std::time::Duration::from_secs(60));
    // Two frames at least: the first selects, the second draws what it settled on.
    let mut last = None;
    for now_s in (0..count.max(2)).map(|i| i as f64) {
        last = Some(
            hybrid
                .render_over_scans_to_image(&mut renderer, &settings, model.scans(), camera, now_s)
                .unwrap(),
        );
        tiles_alone.render_to_image(camera, now_s).unwrap();
    }
    let (hybrid_image, tile_stats, hybrid_stats) = last.unwrap();
    let (tiles, _) = tiles_alone.render_to_image(camera, 2.0).unwrap();
    let (scans, _) = renderer.render_to_image(camera, &settings).unwrap();
    Frames {
        hybrid: hybrid_image,
        scans,
        tiles,
        tiles_with_scans: tile_stats.tiles_with_scans,
        scans_drawn: hybrid_stats.scans.map_or(0, |s| s.drawn),
    }
}

fn drawn(p: &image::Rgba<u8>) -> bool {
    [p[0], p[1], p[2]] != BACKGROUND_U8
}

fn same(p: &image::Rgba<u8>, q: &image::Rgba<u8>, tol: u8) -> bool {
    (0..3).all(|k| p[k].abs_diff(q[k]) <= tol)
}

/// Of the pixels where `mask` holds, the share where `a` and `b` agree within `tol`.
fn agreement(
    a: &image::RgbaImage,
    b: &image::RgbaImage,
    mask: &dyn Fn(u32, u32) -> bool,
    tol: u8,
) -> (f64, usize) {
    let mut n = 0;
    let mut ok = 0;
    for (x, y, p) in a.enumerate_pixels() {
        if mask(x, y) {
            n += 1;
            if same(p, b.get_pixel(x, y), tol) {
                ok += 1;
            }
        }
    }
    (ok as f64 / n.max(1) as f64, n)
}

#[test]
fn close_to_the_wall_the_scans_show_and_the_tiles_give_way() {
    let model = corridor();
    let h = corridor_tiles(&model);
    let cam = camera([5.0, -0.3, 1.5], [5.3, -0.2, 5.05]);
    let f = frames(&model, &h, &cam, 0.5);
    assert!(f.tiles_with_scans > 0, "no finest tile asked for its scans");
    assert!(f.scans_drawn > 0, "no scan drawn");
    let scans = &f.scans;
    let (same_as_scans, n) = agreement(&f.hybrid, scans, &|x, y| drawn(scans.get_pixel(x, y)), 2);
    assert!(
        n > (WIDTH * HEIGHT / 2) as usize,
        "the scans drew {n} pixels"
    );
    assert!(
        same_as_scans > 0.98,
        "where the scans drew, the hybrid frame matches them at {same_as_scans:.4}"
    );
    // The tiles alone look different: the hybrid's agreement is the scans' doing.
    let (same_as_tiles, _) =
        agreement(&f.hybrid, &f.tiles, &|x, y| drawn(scans.get_pixel(x, y)), 2);
    assert!(
        same_as_tiles < 0.8,
        "the tiles alone match the scans' pixels at {same_as_tiles:.4}: the test shows nothing"
    );
    // Nowhere is the hybrid empty where the tiles alone drew (no hole).
    let holes = f
        .tiles
        .enumerate_pixels()
        .filter(|(x, y, p)| drawn(p) && !drawn(f.hybrid.get_pixel(*x, *y)))
        .count();
    assert_eq!(holes, 0, "{holes} pixels drawn by the tiles are empty");
}

#[test]
fn far_from_the_wall_no_scan_is_drawn() {
    let model = corridor();
    let h = corridor_tiles(&model);
    let cam = camera([5.0, -0.3, -120.0], [5.0, -0.3, 5.05]);
    let f = frames(&model, &h, &cam, 0.5);
    assert_eq!(f.tiles_with_scans, 0);
    assert_eq!(f.scans_drawn, 0);
    let (same, n) = agreement(&f.hybrid, &f.tiles, &|_, _| true, 0);
    assert!(n > 0);
    assert_eq!(same, 1.0, "far off the hybrid frame is the tiles' alone");
    assert!(f.tiles.pixels().any(drawn), "the tiles drew nothing");
}

#[test]
fn a_tile_in_front_of_the_scans_covers_them_and_one_behind_does_not_show() {
    let model = corridor();
    let cam = camera([5.0, -0.3, 1.5], [5.3, -0.2, 5.05]);
    // A red plane a metre in front of the wall: it covers the scans where it is.
    let front = plane_tiles(4.0, [250, 20, 20]);
    let f = frames(&model, &front, &cam, 1.5);
    assert!(f.scans_drawn > 0);
    let tiles = &f.tiles;
    let (covered, n) = agreement(&f.hybrid, tiles, &|x, y| drawn(tiles.get_pixel(x, y)), 2);
    assert!(n > 1_000, "the plane covers {n} pixels");
    assert!(covered > 0.98, "the plane in front shows at {covered:.4}");
    let scans = &f.scans;
    let (beside, m) = agreement(
        &f.hybrid,
        scans,
        &|x, y| !drawn(tiles.get_pixel(x, y)) && drawn(scans.get_pixel(x, y)),
        2,
    );
    assert!(m > 1_000, "the scans show beside the plane on {m} pixels");
    assert!(
        beside > 0.98,
        "beside the plane the scans show at {beside:.4}"
    );
    // The same plane a metre behind the wall: the scans cover it wherever they drew.
    let behind = plane_tiles(6.0, [250, 20, 20]);
    let f = frames(&model, &behind, &cam, 1.5);
    assert!(f.scans_drawn > 0);
    let scans = &f.scans;
    let (shown, n) = agreement(&f.hybrid, scans, &|x, y| drawn(scans.get_pixel(x, y)), 2);
    assert!(n > 1_000);
    assert!(shown > 0.98, "the scans in front show at {shown:.4}");
    let red_through: usize = f
        .hybrid
        .enumerate_pixels()
        .filter(|(x, y, p)| drawn(scans.get_pixel(*x, *y)) && p[0] > 240 && p[1] < 40)
        .count();
    assert_eq!(red_through, 0, "the plane behind shows through the scans");
}

#[test]
fn coverage_feedback_brings_in_the_scans_where_the_tiles_still_showed() {
    // One scan a tile leaves most of what the scans alone draw to the tiles; each
    // frame's feedback then asks for scans holding the points where tiles showed.
    let model = corridor();
    let h = corridor_tiles(&model);
    // Six metres from the wall, the view takes in more of it than three scans saw.
    let cam = camera([6.0, -0.3, -1.0], [6.3, -0.2, 5.05]);
    let settings = |feedback: usize| {
        let mut s = tile_settings(true, 0.5);
        s.hybrid.scans_per_tile = 1;
        s.hybrid.feedback_scans_per_tile = feedback;
        s
    };
    let matched = |f: &Frames| {
        let scans = &f.scans;
        agreement(&f.hybrid, scans, &|x, y| drawn(scans.get_pixel(x, y)), 2).0
    };
    let without = frames_with(&model, &h, &cam, settings(0), 6);
    let with = frames_with(&model, &h, &cam, settings(16), 6);
    let (a, b) = (matched(&without), matched(&with));
    eprintln!(
        "where the scans alone drew: {a:.4} matched without the feedback ({} scans), {b:.4} with it ({} scans)",
        without.scans_drawn, with.scans_drawn
    );
    assert!(
        with.scans_drawn > without.scans_drawn,
        "the feedback drew {} scans, without it {}",
        with.scans_drawn,
        without.scans_drawn
    );
    assert!(
        b > a + 0.05 && b > 0.9,
        "where the scans alone drew, the hybrid frame matches them at {b:.4} with the feedback, {a:.4} without"
    );
}

/// A wall scanned once from the origin by a 320x240 lidar with isolated samples
/// knocked out (dropouts), and a red tile plane on the wall.
fn holey_wall() -> (Model, Hierarchy, VirtualCamera) {
    let sensor = scenes::sensor(320, 240, 320, 240);
    let scene = scenes::Scene {
        surfaces: vec![scenes::Surface {
            shape: scenes::Shape::Plane {
                normal: [0.0, 0.0, 1.0],
                offset: 5.05,
            },
            checker_m: 0.4,
            colour_a: [200, 190, 170],
            colour_b: [50, 90, 60],
        }],
    };
    let pose = scenes::look_at([0.0, 0.0, 0.0], [2.5, -0.5, 5.05]);
    let (mut range, eo) = scenes::frames(&scene, &sensor, &pose, [1.0; 3], 0);
    let w = range.width;
    for v in (3..range.height - 3).step_by(5) {
        for u in (3..w - 3).step_by(5) {
            range.ranges_m[(v * w + u) as usize] = f32::NAN;
        }
    }
    let scan = texel::fuse(&range, eo, &sensor, &texel::FuseConfig::default()).unwrap();
    let mut model = Model::new();
    model
        .apply(texel::model::ModelEvent::ScanAdded {
            id: model.next_id(),
            scan: std::sync::Arc::new(scan),
            world_from_scan: pose,
        })
        .unwrap();
    let camera = VirtualCamera::new(pose, 60.0, WIDTH, HEIGHT).unwrap();
    (model, plane_tiles(5.05, [255, 0, 0]), camera)
}

#[test]
fn holes_the_drawn_scans_enclose_are_filled_from_them_and_the_tiles_give_way() {
    let (model, tiles, cam) = holey_wall();
    let red = |p: &image::Rgba<u8>| p[0] > 200 && p[1] < 60 && p[2] < 60;
    let run = |fill: bool| {
        let mut s = tile_settings(true, 0.5);
        s.hybrid.fill_scan_holes = fill;
        s.hybrid.feedback_scans_per_tile = 0;
        frames_with(&model, &tiles, &cam, s, 2)
    };
    let (holes, filled) = (run(false), run(true));
    assert!(holes.scans_drawn > 0 && filled.scans_drawn > 0);
    // Where both the scan and the tiles draw: the tile shows through the scan's
    // holes unless they are filled.
    // Where the tiles draw, inside the scan's outline (its holes included).
    let both = |x: u32, y: u32| {
        drawn(holes.tiles.get_pixel(x, y))
            && (x.saturating_sub(2)..=x + 2)
                .any(|u| u < WIDTH && drawn(holes.scans.get_pixel(u, y)))
    };
    let count = |img: &image::RgbaImage| {
        img.enumerate_pixels()
            .filter(|(x, y, p)| both(*x, *y) && red(p))
            .count()
    };
    let area = holes
        .hybrid
        .enumerate_pixels()
        .filter(|(x, y, _)| both(*x, *y))
        .count();
    let (red_holes, red_filled) = (count(&holes.hybrid), count(&filled.hybrid));
    eprintln!("the tile shows in {red_holes} of {area} pixels unfilled, {red_filled} filled");
    assert!(area > 5_000, "the scan and the tiles share {area} pixels");
    assert!(
        red_holes > 200,
        "the tile shows through the holes in {red_holes} pixels only"
    );
    assert!(
        red_filled * 3 < red_holes,
        "filled: the tile still shows in {red_filled} pixels, {red_holes} unfilled"
    );
    // The filled frame is the scan's colour: every pixel neither background nor red
    // where both drew is within the wall's colours (its two checker colours and the
    // mixes of them a blend or a fill makes).
    for (x, y, p) in filled.hybrid.enumerate_pixels() {
        if both(x, y) && !red(p) {
            assert!(drawn(p), "({x}, {y}) left empty");
        }
    }
}

#[test]
fn at_a_silhouette_the_scans_edge_shows_not_the_tiles_coarser_one() {
    // A box in front of a wall, every scan drawn: the tiles' box, rounded outward by
    // its voxels, reaches past the scans' edge and lies in front of the wall they
    // show there. The scans show the box right beside such a pixel, so the tile
    // gives way to them; an occluder the scans lack still covers them (the test
    // above with the plane in front).
    let model = scenes::model_of(
        &scenes::box_scene(),
        &scenes::test_sensor(),
        &scenes::box_scene_poses(),
        &texel::Pose::identity(),
    );
    let h = corridor_tiles(&model);
    let cam = camera([1.2, -0.6, -0.4], [0.0, 0.0, 5.0]);
    let f = frames_with(&model, &h, &cam, tile_settings(true, 1.5), 2);
    assert!(
        f.scans_drawn == model.scans().len(),
        "{} scans drawn",
        f.scans_drawn
    );
    let scans = &f.scans;
    // Where the scans alone drew, within 2 pixels of the box's outline in their
    // image: the box is red or yellow, the wall white or blue.
    let boxy = |p: &image::Rgba<u8>| p[0] > 200 && p[2] < 120;
    let near_outline = |x: u32, y: u32| {
        let here = boxy(scans.get_pixel(x, y));
        (x.saturating_sub(2)..(x + 3).min(WIDTH)).any(|u| {
            (y.saturating_sub(2)..(y + 3).min(HEIGHT))
                .any(|v| drawn(scans.get_pixel(u, v)) && boxy(scans.get_pixel(u, v)) != here)
        })
    };
    let (outline, n) = agreement(
        &f.hybrid,
        scans,
        &|x, y| drawn(scans.get_pixel(x, y)) && near_outline(x, y),
        8,
    );
    let (elsewhere, m) = agreement(
        &f.hybrid,
        scans,
        &|x, y| drawn(scans.get_pixel(x, y)) && !near_outline(x, y),
        8,
    );
    eprintln!(
        "the hybrid matches the scans at {outline:.4} of {n} pixels by the box's outline, {elsewhere:.4} of {m} elsewhere"
    );
    assert!(n > 300 && m > 10_000, "{n} outline and {m} other pixels");
    assert!(elsewhere > 0.99, "away from the outline {elsewhere:.4}");
    assert!(outline > 0.95, "by the box's outline {outline:.4}");
}
