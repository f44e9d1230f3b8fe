//! The Mitsuba backend against the built-in ray caster, an independent renderer of the
//! same scene (`configs/scenes/backend-check.toml`): range images agree within 1 mm on
//! every pixel both hit away from depth edges, EO images of the diffuse scene within
//! the tolerance stated in `docs/simulator.md`, effects apply identically on either
//! backend, and `global_illumination` selects Mitsuba and adds bounced light.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use std::process::Command;

use sims::render::{CameraRays, world_ray};
use sims::{BackendKind, Effect, Scene, SimOptions, Simulator};
use texel::{EoFrame, Pose};

const LIDAR: [u32; 2] = [64, 64];
const EO: [u32; 2] = [160, 120];

/// The check scene; `textured = false` makes every material a constant colour, so
/// the renderers differ only in shading, not in how they filter textures.
fn scene(textured: bool) -> Scene {
    let path = common::configs().join("scenes/backend-check.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let text = if textured {
        text
    } else {
        text.lines()
            .map(|l| {
                if ["checker =", "image =", "noise ="]
                    .iter()
                    .any(|k| l.starts_with(k))
                {
                    "color = [0.6, 0.55, 0.5]".to_string()
                } else {
                    l.to_string()
                }
            })
            .collect::<Vec<_>>()
            .join("\n")
    };
    Scene::from_toml_str(&text, "backend-check.toml", path.parent().unwrap()).unwrap()
}

fn sim(scene: Scene, backend: BackendKind, effects: Vec<Effect>) -> Simulator {
    Simulator::with_options(
        scene,
        &SimOptions {
            seed: 5,
            effects: Some(effects),
            lidar_size: Some(LIDAR),
            eo_size: Some(EO),
            backend,
            ..SimOptions::default()
        },
    )
    .unwrap()
}

/// Pixels whose 8 neighbours all see the same object as the pixel itself (or all
/// see nothing): everything but depth edges.
fn interior(w: usize, h: usize, object_of: &[Option<u32>]) -> Vec<bool> {
    (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            (-1..=1).all(|dy| {
                (-1..=1).all(|dx| {
                    let (nx, ny) = (x + dx, y + dy);
                    nx < 0
                        || ny < 0
                        || nx >= w as i64
                        || ny >= h as i64
                        || object_of[ny as usize * w + nx as usize] == object_of[i]
                })
            })
        })
        .collect()
}

/// Compares two range images on interior pixels: both hit or both miss; returns
/// (pixels both hit, max |diff| mm, mean |diff| mm).
fn compare_ranges(a: &[f32], b: &[f32], inside: &[bool], what: &str) -> (usize, f64, f64) {
    let (mut n, mut max, mut sum) = (0usize, 0.0f64, 0.0f64);
    for p in 0..a.len() {
        if !inside[p] {
            continue;
        }
        let (ra, rb) = (a[p], b[p]);
        assert_eq!(ra.is_nan(), rb.is_nan(), "{what} pixel {p}: {ra} vs {rb}");
        if ra.is_nan() {
            continue;
        }
        let d = f64::from((ra - rb).abs()) * 1e3;
        max = max.max(d);
        sum += d;
        n += 1;
    }
    (n, max, sum / n.max(1) as f64)
}

#[test]
fn ranges_agree_within_a_millimetre() {
    let scene = scene(true);
    let builtin = sim(scene.clone(), BackendKind::Builtin, vec![]);
    let mitsuba = sim(scene, BackendKind::Mitsuba, vec![]);
    assert_eq!(
        (builtin.backend_name(), mitsuba.backend_name()),
        ("builtin", "mitsuba")
    );
    let (w, h) = (LIDAR[0] as usize, LIDAR[1] as usize);
    let (mut both, mut max_mm, mut sum_mm, mut edges) = (0, 0.0f64, 0.0, 0);
    for i in 0..3 {
        let pose = builtin.true_pose(i);
        let (ea, eb) = (builtin.echoes_at(&pose), mitsuba.echoes_at(&pose));
        let objects: Vec<Option<u32>> = ea.iter().map(|e| e.map(|e| e.object)).collect();
        let inside = interior(w, h, &objects);
        edges += inside.iter().filter(|&&v| !v).count();
        let a = builtin.clean_range_at(&pose, 0);
        let b = mitsuba.clean_range_at(&pose, 0);
        let (n, max, mean) = compare_ranges(&a.ranges_m, &b.ranges_m, &inside, "range");
        assert!(max < 1.0, "pose {i}: max |diff| {max} mm");
        for p in (0..w * h).filter(|&p| inside[p]) {
            if let (Some(sa), Some(sb)) = (ea[p], eb[p]) {
                assert_eq!(sa.object, sb.object, "pose {i} pixel {p}");
                assert!((sa.cos_incidence - sb.cos_incidence).abs() < 1e-3);
            }
        }
        both += n;
        max_mm = max_mm.max(max);
        sum_mm += mean * n as f64;
    }
    assert!(mitsuba.backend_failure().is_none());
    eprintln!(
        "range, 3 poses at {w}x{h}: {both} pixels hit by both ({edges} depth-edge pixels \
         excluded): max |diff| {max_mm:.5} mm, mean {:.6} mm",
        sum_mm / both as f64
    );
    assert!(both > 3 * w * h / 2, "most pixels are compared ({both})");
}

/// EO pixels that see the scene nearer than 1 km (or nothing): Mitsuba's stand-in for
/// an unbounded plane ends at 1 km, so the horizon differs.
fn near_pixels(sim: &Simulator, world_from_eo: &Pose) -> Vec<bool> {
    let rays = CameraRays::new(&sim.sensor_model().eo);
    rays.rays
        .iter()
        .map(|r| {
            world_ray(world_from_eo, r)
                .and_then(|ray| sim.scene().cast_ray(ray.origin, ray.dir))
                .is_none_or(|h| h.distance_m < 1000.0)
        })
        .collect()
}

/// Sorted |difference| of two 8-bit images, per channel value of the pixels kept.
fn sorted_abs_diff(a: &EoFrame, b: &EoFrame, keep: &[bool]) -> Vec<u8> {
    assert_eq!((a.width, a.height), (b.width, b.height));
    let mut d: Vec<u8> = a
        .rgb
        .chunks_exact(3)
        .zip(b.rgb.chunks_exact(3))
        .zip(keep)
        .filter(|(_, k)| **k)
        .flat_map(|((x, y), _)| (0..3).map(move |c| x[c].abs_diff(y[c])))
        .collect();
    d.sort_unstable();
    d
}

/// Asserts the documented EO tolerance on the pixels that see the scene within 1 km:
/// mean |diff| below 0.05 of an 8-bit level and at most 0.1 % of values more than one
/// level apart.
fn assert_eo_close(sim: &Simulator, pose: &Pose, a: &EoFrame, b: &EoFrame, what: &str) {
    let keep = near_pixels(sim, pose);
    let horizon = keep.iter().filter(|k| !**k).count();
    let d = sorted_abs_diff(a, b, &keep);
    let mean = d.iter().map(|&v| f64::from(v)).sum::<f64>() / d.len() as f64;
    let over1 = d.iter().filter(|&&v| v > 1).count();
    eprintln!(
        "{what}: mean |diff| {mean:.4} levels, p99 {}, max {}, {over1} of {} values > 1 level \
         ({horizon} horizon pixels excluded)",
        d[d.len() * 99 / 100],
        d[d.len() - 1],
        d.len()
    );
    assert!(mean < 0.05, "{what}: mean {mean}");
    assert!(over1 * 1000 <= d.len(), "{what}: {over1} values > 1 level");
}

#[test]
fn eo_images_of_the_diffuse_scene_agree() {
    let scene = scene(false);
    let builtin = sim(scene.clone(), BackendKind::Builtin, vec![]);
    let mitsuba = sim(scene, BackendKind::Mitsuba, vec![]);
    for i in 0..3 {
        let pose = builtin.true_pose(i);
        let a = builtin.clean_eo_at(&pose, 0);
        let b = mitsuba.clean_eo_at(&pose, 0);
        assert_eo_close(&builtin, &pose, &a, &b, &format!("EO pose {i}"));
    }
    assert!(mitsuba.backend_failure().is_none());
}

#[test]
fn effects_apply_identically_on_either_backend() {
    // Same noise keys, same pipelines: the effected frames differ only by the clean
    // signals' difference.
    let effects = common::effects(&[
        "range_noise",
        "dropouts",
        "range_quantisation",
        "lens_distortion",
        "vignetting",
        "exposure",
        "sensor_noise",
    ]);
    let scene = scene(false);
    let builtin = sim(scene.clone(), BackendKind::Builtin, effects.clone());
    let mitsuba = sim(scene, BackendKind::Mitsuba, effects);
    let (a, b) = (builtin.frame(1).unwrap(), mitsuba.frame(1).unwrap());
    assert_eq!(
        (a.timestamp_ns, a.pair.range.seq),
        (b.timestamp_ns, b.pair.range.seq)
    );
    let ea = builtin.echoes_at(&a.world_from_eo);
    let objects: Vec<Option<u32>> = ea.iter().map(|e| e.map(|e| e.object)).collect();
    let inside = interior(LIDAR[0] as usize, LIDAR[1] as usize, &objects);
    // Range noise is drawn identically; quantisation to 1 mm may round the two
    // clean ranges (µm apart) to neighbouring steps.
    let (n, max, _) = compare_ranges(
        &a.pair.range.ranges_m,
        &b.pair.range.ranges_m,
        &inside,
        "effected range",
    );
    assert!(n > 1000 && max <= 1.0 + 1e-3, "{n} pixels, max {max} mm");
    assert_eo_close(
        &builtin,
        &a.world_from_eo,
        &a.pair.eo,
        &b.pair.eo,
        "effected EO",
    );
}

#[test]
fn global_illumination_selects_mitsuba_and_adds_bounced_light() {
    let gi = |max_depth: u32| {
        Effect::from_toml(&toml::Value::Table(
            toml::from_str(&format!(
                "name = \"global_illumination\"\nmax_depth = {max_depth}\nsamples_per_pixel = 8"
            ))
            .unwrap(),
        ))
        .unwrap()
    };
    // Asking the built-in backend for it is an error naming both.
    let err = Simulator::with_options(
        scene(false),
        &SimOptions {
            effects: Some(vec![gi(4)]),
            backend: BackendKind::Builtin,
            ..SimOptions::default()
        },
    )
    .err()
    .unwrap()
    .to_string();
    assert!(
        err.contains("global_illumination") && err.contains("Mitsuba"),
        "{err}"
    );
    // Left to choose (the default), it takes Mitsuba.
    let bounced = sim(scene(false), BackendKind::Auto, vec![gi(4)]);
    assert_eq!(bounced.backend_name(), "mitsuba");
    let direct = sim(scene(false), BackendKind::Auto, vec![gi(2)]);
    let plain = sim(scene(false), BackendKind::Builtin, vec![]);
    let pose = plain.true_pose(0);
    let (b, d, p) = (
        bounced.frame(0).unwrap().pair.eo,
        direct.frame(0).unwrap().pair.eo,
        plain.clean_eo_at(&pose, 0),
    );
    // Paths of two segments are direct light only: the built-in image.
    assert_eo_close(
        &plain,
        &pose,
        &d,
        &p,
        "global_illumination max_depth 2 vs builtin",
    );
    // Longer paths only add light: brighter on average, and in the shadowed ground
    // between the objects (lit by them) most of all.
    let mean = |f: &EoFrame| f.rgb.iter().map(|&v| f64::from(v)).sum::<f64>() / f.rgb.len() as f64;
    let (mb, md) = (mean(&b), mean(&d));
    eprintln!("mean 8-bit level: direct {md:.2}, with bounces {mb:.2}");
    assert!(mb > md + 1.0, "bounced {mb} vs direct {md}");
    let darker = b
        .rgb
        .iter()
        .zip(&d.rgb)
        .filter(|(x, y)| **x + 8 < **y)
        .count();
    assert!(
        darker * 100 < b.rgb.len(),
        "{darker} values darker with bounces"
    );
    // The clean render of the same simulator has no global illumination.
    assert_eo_close(
        &plain,
        &pose,
        &bounced.clean_eo_at(&pose, 0),
        &p,
        "clean EO of a GI simulator",
    );
}

#[test]
fn the_cli_renders_with_mitsuba() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("plane.mcap");
    let scene = common::configs().join("scenes/plane.toml");
    let o = Command::new(env!("CARGO_BIN_EXE_texel-sims"))
        .args(["render", "--scene"])
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .args(["--frames", "1", "--backend", "mitsuba"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("wrote 1 frames") && stdout.contains("mitsuba"),
        "{stdout}"
    );
    let pairs = texel::capture::open_texel_frames(&out)
        .unwrap()
        .filter(|i| matches!(i, Ok(texel::capture::TexelItem::Pair { .. })))
        .count();
    assert_eq!(pairs, 1);
    // The built-in backend with an effect only Mitsuba simulates is refused.
    let o = Command::new(env!("CARGO_BIN_EXE_texel-sims"))
        .args(["render", "--scene"])
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .args(["--backend", "builtin", "--effects", "global_illumination"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("global_illumination"), "{err}");
}
