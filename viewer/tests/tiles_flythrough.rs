//! Fly-throughs of a street from close to an overview. With loading asynchronous
//! (tiles arrive frames after they are wanted) the drawn ground never has a hole
//! against a render of every finest tile; and the cross-fade makes the largest
//! frame-to-frame change at a switch smaller than switching at once.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;
mod tiles_support;

use std::sync::OnceLock;
use std::time::Duration;

use texel_lod::{Hierarchy, SelectConfig};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::tiles::cache::TileCache;
use texel_viewer::tiles::image_target::render_tiles_to_image;
use texel_viewer::tiles::measure::{popping_excess, popping_measure, switch_measure};
use texel_viewer::tiles::pass::TilePass;
use texel_viewer::tiles::source::MemorySource;
use texel_viewer::tiles::{TileRenderer, TileSettings};
use tiles_support::*;

const FRAMES: usize = 96;
const POP_FRAMES: usize = 180;
/// A coarse threshold for the popping test: switches between visibly different levels.
const POP_ERROR_PX: f64 = 8.0;
const FRAME_S: f64 = 1.0 / 30.0;
const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

fn street_h() -> &'static Hierarchy {
    static STREET: OnceLock<Hierarchy> = OnceLock::new();
    STREET.get_or_init(|| street(24.0, [0.0; 3]))
}

/// Frame `i` of the fly-through: from 6 m from the ground to an overview 70 m out, the
/// distance growing geometrically (the same relative motion every frame).
fn path(i: usize) -> VirtualCamera {
    camera_at(i as f64 / (FRAMES - 1) as f64)
}

/// The fly-through's camera at `s` (0: close, 1: the overview).
fn camera_at(s: f64) -> VirtualCamera {
    let target = [14.0 - 2.0 * s, 0.0, 0.5 - 0.5 * s];
    // Inside the street (between the facades) until above the roofs.
    let near_dir = [-0.9, -0.2, 0.35];
    let far_dir = [-0.6, -0.05, 0.8];
    let dir = [0, 1, 2].map(|k| near_dir[k] + s * (far_dir[k] - near_dir[k]));
    let norm = dir.iter().map(|d| d * d).sum::<f64>().sqrt();
    let distance = 6.0 * (70.0f64 / 6.0).powf(s);
    let eye = [0, 1, 2].map(|k| target[k] + dir[k] / norm * distance);
    camera(eye, target, [0.0; 3], WIDTH, HEIGHT)
}

/// Every camera drawn with every finest tile (no level of detail).
fn full_detail_frames(cameras: &[VirtualCamera]) -> Vec<image::RgbaImage> {
    let h = street_h();
    let gpu = support::gpu();
    let mut cache = TileCache::new(gpu, u64::MAX);
    for n in h.nodes.values().filter(|n| n.id.lod == 0) {
        cache.insert(n, 1, 1).unwrap();
    }
    let tiles: Vec<_> = cache.ids().map(|id| cache.get(id).unwrap()).collect();
    let mut pass = TilePass::new(gpu);
    cameras
        .iter()
        .map(|cam| {
            render_tiles_to_image(gpu, &mut pass, &tiles, cam, BACKGROUND)
                .unwrap()
                .0
        })
        .collect()
}

fn settings(fade_s: f64, max_error_px: f64) -> TileSettings {
    TileSettings {
        select: SelectConfig {
            max_error_px,
            ..SelectConfig::default()
        },
        fade_s,
        background: BACKGROUND,
        max_in_flight: 4,
        ..TileSettings::default()
    }
}

/// Pixels covered in `full` and not in `lod`, over all pixels: on the ground (where
/// `full` shows the ground) and anywhere.
fn hole_fraction(full: &image::RgbaImage, lod: &image::RgbaImage) -> (f64, f64) {
    let (a, b) = (covered(full), covered(lod));
    let (mut ground, mut any) = (0usize, 0usize);
    for (k, p) in full.pixels().enumerate() {
        if a[k] && !b[k] {
            any += 1;
            ground += usize::from(is_ground(p));
        }
    }
    let n = a.len() as f64;
    (ground as f64 / n, any as f64 / n)
}

#[test]
fn the_drawn_ground_never_has_a_hole_while_tiles_load() {
    let start = std::time::Instant::now();
    let h = street_h();
    let levels = h.nodes.keys().map(|id| id.lod).max().unwrap() + 1;
    println!(
        "street: {} tiles, {levels} levels, {:.1} s",
        h.nodes.len(),
        start.elapsed().as_secs_f64()
    );
    let cameras: Vec<VirtualCamera> = (0..FRAMES).map(path).collect();
    let full = full_detail_frames(&cameras);
    // The levels' own coverage differs from the finest level's at silhouettes: the
    // same fly-through with every tile resident and no fade gives that floor.
    let (settled, _, _) = lod_frames(0.0, 2.0, &cameras);
    let floor = full
        .iter()
        .zip(&settled)
        .map(|(a, b)| hole_fraction(a, b))
        .fold((0.0f64, 0.0f64), |m, h| (m.0.max(h.0), m.1.max(h.1)));
    let source = MemorySource::new(h).with_delay(2);
    let mut r = TileRenderer::new(support::gpu(), source, settings(0.25, 2.0)).unwrap();
    // Start-up: until the top tiles are in, their ground is empty by design.
    for _ in 0..100 {
        r.update(&path(0), 0.0);
        r.finish_loads(Duration::from_secs(5));
        if h.roots().iter().all(|id| r.cache().contains(*id)) {
            break;
        }
    }
    let (mut worst, mut worst_frame, mut worst_any) = (0.0f64, 0, 0.0f64);
    let (mut waiting_frames, mut switches, mut max_in_flight) = (0, 0, 0);
    for (i, reference) in full.iter().enumerate() {
        let (img, stats) = r.render_to_image(&path(i), i as f64 * FRAME_S).unwrap();
        let (fraction, any) = hole_fraction(reference, &img);
        worst_any = worst_any.max(any);
        if fraction > worst {
            (worst, worst_frame) = (fraction, i);
            if std::env::var_os("TEXEL_TILE_DEBUG").is_some() {
                img.save("/tmp/tiles_lod.png").unwrap();
                reference.save("/tmp/tiles_full.png").unwrap();
                let (a, b) = (covered(reference), covered(&img));
                let diff = image::RgbaImage::from_fn(WIDTH, HEIGHT, |x, y| {
                    let k = (y * WIDTH + x) as usize;
                    image::Rgba(if a[k] && !b[k] {
                        [255, 255, 255, 255]
                    } else {
                        [0, 0, 0, 255]
                    })
                });
                diff.save("/tmp/tiles_holes.png").unwrap();
            }
        }
        waiting_frames += usize::from(stats.tiles_wanted > 0);
        switches += usize::from(stats.selection_changed);
        max_in_flight = max_in_flight.max(stats.loads_in_flight);
        if i % 8 == 0 {
            println!(
                "frame {i}: {stats:?}, holes {:.4} % on the ground, {:.4} % anywhere",
                100.0 * fraction,
                100.0 * any
            );
        }
    }
    println!(
        "worst hole on the ground {:.4} % of the image at frame {worst_frame} (all resident, \
         no fade: {:.4} %); anywhere {:.4} % (all resident, no fade: {:.4} %: coarser levels \
         end short of the finest at the edges of what was seen); {waiting_frames} frames waited for \
         tiles, {switches} switches, at most {max_in_flight} loads in flight; {:.1} s",
        100.0 * worst,
        100.0 * floor.0,
        100.0 * worst_any,
        100.0 * floor.1,
        start.elapsed().as_secs_f64()
    );
    assert!(r.take_errors().is_empty());
    assert!(
        waiting_frames >= 5,
        "loading was not asynchronous: {waiting_frames}"
    );
    assert!(switches >= 3, "{switches}");
    assert!(
        worst < 0.01,
        "{:.4} % of the image a hole in the ground at frame {worst_frame}",
        100.0 * worst
    );
    assert!(
        worst_any < 0.03,
        "{:.4} % of the image a hole",
        100.0 * worst_any
    );
}

/// The fly-through with every tile resident from the start: images, per frame
/// whether the selection switched or a fade was under way, and per frame the previous
/// frame's tiles and this frame's drawn from this frame's camera.
#[allow(clippy::type_complexity)]
fn lod_frames(
    fade_s: f64,
    max_error_px: f64,
    cameras: &[VirtualCamera],
) -> (
    Vec<image::RgbaImage>,
    Vec<bool>,
    Vec<(image::RgbaImage, image::RgbaImage)>,
) {
    let mut r = TileRenderer::new(
        support::gpu(),
        MemorySource::new(street_h()),
        settings(fade_s, max_error_px),
    )
    .unwrap();
    r.preload_all(Duration::from_secs(30));
    assert_eq!(r.cache().len(), street_h().nodes.len());
    let (mut frames, mut switched, mut pairs) = (Vec::new(), Vec::new(), Vec::new());
    for (i, cam) in cameras.iter().enumerate() {
        let before = r.draw_to_image(cam).unwrap();
        let (img, stats) = r.render_to_image(cam, i as f64 * FRAME_S).unwrap();
        switched.push(stats.selection_changed || stats.fading);
        if i > 0 {
            pairs.push((before, img.clone()));
        }
        frames.push(img);
    }
    (frames, switched, pairs)
}

#[test]
fn the_cross_fade_lowers_the_largest_change_at_a_switch() {
    let start = std::time::Instant::now();
    // Slowly (0.4 % nearer a frame, 6 s at 30 Hz), so camera motion changes the
    // image less than a switch does: from 12 to 24 m out.
    let cameras: Vec<VirtualCamera> = (0..POP_FRAMES)
        .map(|i| camera_at(0.283 + 0.283 * i as f64 / (POP_FRAMES - 1) as f64))
        .collect();
    let (faded, faded_switch, faded_pairs) = lod_frames(0.25, POP_ERROR_PX, &cameras);
    let (popped, popped_switch, popped_pairs) = lod_frames(0.0, POP_ERROR_PX, &cameras);
    let full = full_detail_frames(&cameras);
    let m_fade = popping_measure(&faded, &faded_switch);
    let m_pop = popping_measure(&popped, &popped_switch);
    let m_full = popping_measure(&full, &popped_switch);
    let s_fade = switch_measure(&faded_pairs);
    let s_pop = switch_measure(&popped_pairs);
    println!("frame to frame, fade 0.25 s: {m_fade:?}");
    println!("frame to frame, fade 0:      {m_pop:?}");
    println!("frame to frame, full detail at the switch frames: {m_full:?}");
    println!("switches alone, fade 0.25 s: {s_fade:?}");
    println!("switches alone, fade 0:      {s_pop:?}");
    let e_fade = popping_excess(&faded, &full, &faded_switch);
    let e_pop = popping_excess(&popped, &full, &popped_switch);
    println!(
        "largest excess over full detail at a switch frame: fade 0.25 s {e_fade:.3}, fade 0 {e_pop:.3}"
    );
    println!("{:.1} s", start.elapsed().as_secs_f64());
    assert!(m_pop.switch_frames >= 3, "{m_pop:?}");
    // Held still, a switch without fade changes the image at once; the fade spreads
    // it over fade_s (7.5 frames at 30 Hz).
    assert!(
        s_fade.max_change < 0.3 * s_pop.max_change,
        "fade {} vs none {}",
        s_fade.max_change,
        s_pop.max_change
    );
    // Frame to frame (camera motion included) the largest change at a switch is
    // smaller with the fade, and so is what it adds to the camera motion's change.
    assert!(e_fade < e_pop, "excess: fade {e_fade} vs none {e_pop}");
    assert!(
        m_fade.max_switch_change < 0.75 * m_pop.max_switch_change,
        "fade {} vs none {}",
        m_fade.max_switch_change,
        m_pop.max_switch_change
    );
}
