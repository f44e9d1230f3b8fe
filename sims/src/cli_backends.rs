//! `texel-sims bench --mitsuba` (part of the binary): the built-in and the Mitsuba
//! backend timed on the same clean range and EO images in one run, with the ratio,
//! and how far their images differ.

use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use sims::{BackendKind, Effect, Scene, SimOptions, Simulator};

fn simulator(scene: &Scene, backend: BackendKind, effects: Vec<Effect>) -> Result<Simulator> {
    Ok(Simulator::with_options(
        scene.clone(),
        &SimOptions {
            effects: Some(effects),
            backend,
            ..SimOptions::default()
        },
    )?)
}

/// Mean wall-clock milliseconds of `f(i)` over `frames` calls (after one warm-up call,
/// which compiles Mitsuba's kernels).
fn time_ms<T>(frames: usize, mut f: impl FnMut(usize) -> T) -> f64 {
    std::hint::black_box(f(0));
    let start = Instant::now();
    for i in 0..frames {
        std::hint::black_box(f(i));
    }
    start.elapsed().as_secs_f64() * 1e3 / frames as f64
}

/// Range difference over pixels both renderers hit whose 8 neighbours see the same
/// object (depth edges excluded): (pixels, max mm, mean mm, pixels hit by one only).
fn range_difference(
    builtin: &Simulator,
    mitsuba: &Simulator,
    poses: usize,
) -> (usize, f64, f64, usize) {
    let model = builtin.sensor_model();
    let (w, h) = (model.lidar.width as i64, model.lidar.height as i64);
    let (mut n, mut max, mut sum, mut one) = (0usize, 0.0f64, 0.0f64, 0usize);
    for i in 0..poses {
        let pose = builtin.true_pose(i);
        let echoes = builtin.echoes_at(&pose);
        let object = |x: i64, y: i64| echoes[(y * w + x) as usize].map(|e| e.object);
        let a = builtin.clean_range_at(&pose, 0);
        let b = mitsuba.clean_range_at(&pose, 0);
        for y in 0..h {
            for x in 0..w {
                let interior = (-1..=1).all(|dy| {
                    (-1..=1).all(|dx| {
                        let (nx, ny) = (x + dx, y + dy);
                        nx < 0 || ny < 0 || nx >= w || ny >= h || object(nx, ny) == object(x, y)
                    })
                });
                let p = (y * w + x) as usize;
                let (ra, rb) = (a.ranges_m[p], b.ranges_m[p]);
                if !interior {
                    continue;
                }
                if ra.is_nan() != rb.is_nan() {
                    one += 1;
                } else if !ra.is_nan() {
                    let d = f64::from((ra - rb).abs()) * 1e3;
                    max = max.max(d);
                    sum += d;
                    n += 1;
                }
            }
        }
    }
    (n, max, sum / n.max(1) as f64, one)
}

/// 8-bit EO difference: (mean, p99, max, fraction of values more than 1 level apart).
fn eo_difference(builtin: &Simulator, mitsuba: &Simulator, poses: usize) -> (f64, u8, u8, f64) {
    let mut d: Vec<u8> = Vec::new();
    for i in 0..poses {
        let pose = builtin.true_pose(i);
        let a = builtin.clean_eo_at(&pose, 0);
        let b = mitsuba.clean_eo_at(&pose, 0);
        d.extend(a.rgb.iter().zip(&b.rgb).map(|(x, y)| x.abs_diff(*y)));
    }
    d.sort_unstable();
    if d.is_empty() {
        return (0.0, 0, 0, 0.0);
    }
    let mean = d.iter().map(|&v| f64::from(v)).sum::<f64>() / d.len() as f64;
    let over = d.iter().filter(|&&v| v > 1).count() as f64 / d.len() as f64;
    (mean, d[d.len() * 99 / 100], d[d.len() - 1], over)
}

pub fn bench_backends(scene_path: &Path, frames: usize) -> Result<()> {
    let scene = Scene::load(scene_path)?;
    let frames = frames.max(1);
    let builtin = simulator(&scene, BackendKind::Builtin, Vec::new())?;
    let start = Instant::now();
    let mitsuba = simulator(&scene, BackendKind::Mitsuba, Vec::new())?;
    let startup = start.elapsed().as_secs_f64();
    let (version, shapes) = mitsuba.mitsuba().map_or(("?".to_string(), 0), |r| {
        (r.version.clone(), r.shape_count())
    });
    let model = builtin.sensor_model();
    println!();
    println!(
        "backends, clean images (no effects), {frames} frames each, same poses; Mitsuba {} \
         ({} shapes), start-up (export, process, scene load) {startup:.2} s",
        version, shapes,
    );
    let n = builtin.frame_count();
    let pose = |i: usize| builtin.true_pose(i % n);
    let range_b = time_ms(frames, |i| builtin.clean_range_at(&pose(i), 0));
    let range_m = time_ms(frames, |i| mitsuba.clean_range_at(&pose(i), 0));
    println!(
        "range {}x{}:  builtin {range_b:>8.2} ms/frame   mitsuba {range_m:>8.2} ms/frame   \
         mitsuba/builtin {:.2}x",
        model.lidar.width,
        model.lidar.height,
        range_m / range_b.max(1e-9)
    );
    let eo_b = time_ms(frames, |i| builtin.clean_eo_at(&pose(i), 0));
    let eo_m = time_ms(frames, |i| mitsuba.clean_eo_at(&pose(i), 0));
    println!(
        "EO {}x{} direct light:  builtin {eo_b:>8.2} ms/frame   mitsuba {eo_m:>8.2} ms/frame   \
         mitsuba/builtin {:.2}x",
        model.eo.width,
        model.eo.height,
        eo_m / eo_b.max(1e-9)
    );
    let gi = Effect::with_defaults("global_illumination").map_err(anyhow::Error::msg)?;
    let gi_text = match &gi {
        Effect::GlobalIllumination(g) => {
            format!("max_depth {}, {} spp", g.max_depth, g.samples_per_pixel)
        }
        _ => String::new(),
    };
    let with_gi = simulator(&scene, BackendKind::Auto, vec![gi])?;
    let gi_frames = frames.min(5);
    let gi_ms = time_ms(gi_frames, |i| with_gi.frame(i % n));
    println!(
        "texel frame with global_illumination ({gi_text}): {gi_ms:.1} ms/frame over {gi_frames} frames \
         ({:.1}x the direct-light EO)",
        gi_ms / eo_m.max(1e-9)
    );
    let poses = n.min(3);
    let (px, max, mean, one) = range_difference(&builtin, &mitsuba, poses);
    println!(
        "range difference over {poses} poses: {px} pixels hit by both away from depth edges: \
         max {max:.5} mm, mean {mean:.6} mm; {one} interior pixels hit by one renderer only"
    );
    let (mean, p99, max, over) = eo_difference(&builtin, &mitsuba, poses);
    println!(
        "EO difference over {poses} poses (8-bit): mean {mean:.3} levels, p99 {p99}, max {max}, \
         {:.3} % of values > 1 level apart",
        100.0 * over
    );
    if let Some(f) = mitsuba.backend_failure() {
        anyhow::bail!("{f}");
    }
    Ok(())
}
