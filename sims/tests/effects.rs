//! Each effect's statistics or rule, against the clean frame of the same pose.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use common::{configs, fixed_camera_scene};
use sims::{Effect, Scene, SimOptions, Simulator};

/// A grey wall 2.5 m ahead (y = 2.5) with a box in front; ambient light only, so a
/// clean EO image of the wall is uniform.
fn wall_scene() -> Scene {
    let text = fixed_camera_scene(
        r#"
[[objects.plane]]
material = "grey"
position = [0.0, 2.5, 0.0]
rotation_deg = [90.0, 0.0, 0.0]
[[objects.box]]
material = "grey"
position = [0.3, 1.6, 1.2]
size = [0.4, 0.4, 0.4]
[lights]
ambient = [1.0, 1.0, 1.0]
"#,
    );
    Scene::from_toml_str(&text, "wall.toml", &configs().join("scenes")).unwrap()
}

fn sim_with(scene: Scene, seed: u64, effects: Vec<Effect>, lidar: u32) -> Simulator {
    Simulator::with_options(
        scene,
        &SimOptions {
            seed,
            effects: Some(effects),
            lidar_size: Some([lidar, lidar]),
            eo_size: Some([96, 72]),
            ..SimOptions::default()
        },
    )
    .unwrap()
}

fn effect(name: &str, params: &str) -> Effect {
    let table: toml::Table = toml::from_str(params).unwrap();
    Effect::from_name_and_params(name, table).unwrap()
}

#[test]
fn range_noise_has_the_sensors_sigma() {
    let sim = sim_with(wall_scene(), 9, vec![effect("range_noise", "")], 64);
    let noise = sim.sensor_model().range_noise;
    let (mut n, mut sum, mut sum2) = (0.0, 0.0, 0.0);
    for i in 0..2 {
        let pose = sim.true_pose(i);
        let clean = sim.clean_range_at(&pose, 0);
        let noisy = sim.frame(i).unwrap().pair.range;
        for (c, r) in clean.ranges_m.iter().zip(&noisy.ranges_m) {
            let z = (f64::from(*r) - f64::from(*c)) / noise.sigma_at(f64::from(*c));
            n += 1.0;
            sum += z;
            sum2 += z * z;
        }
    }
    let mean = sum / n;
    let std = (sum2 / n - mean * mean).sqrt();
    // 4-sigma bounds: mean 1/sqrt(n), std sqrt(1/(2n)).
    assert!(mean.abs() < 4.0 / n.sqrt(), "mean {mean} over {n}");
    assert!(
        (std - 1.0).abs() < 4.0 * (0.5 / n).sqrt() + 1e-3,
        "std {std}"
    );
}

#[test]
fn quantisation_rounds_to_the_step() {
    let sim = sim_with(
        wall_scene(),
        0,
        vec![effect("range_quantisation", "step_m = 0.01")],
        32,
    );
    let pose = sim.true_pose(0);
    let clean = sim.clean_range_at(&pose, 0);
    let q = sim.frame(0).unwrap().pair.range;
    let mut moved = 0;
    for (c, r) in clean.ranges_m.iter().zip(&q.ranges_m) {
        let steps = f64::from(*r) / 0.01;
        assert!(
            (steps - steps.round()).abs() < 1e-3,
            "{r} is not a multiple of 1 cm"
        );
        assert!((f64::from(*r) - f64::from(*c)).abs() <= 0.005 + 1e-6);
        moved += usize::from(r != c);
    }
    assert!(moved > clean.ranges_m.len() / 2);
}

#[test]
fn dropouts_happen_exactly_where_their_rules_say() {
    // Range limits only: a sensor whose max range cuts through the wall.
    let mut scene = wall_scene();
    let mut model = scene.sensor().clone();
    model.max_range_m = 2.8;
    scene.set_sensor(model);
    let only_range = effect("dropouts", "max_incidence_deg = 90.0\nmin_signal = 0.0");
    let sim = sim_with(scene, 0, vec![only_range], 32);
    let pose = sim.true_pose(0);
    let clean = sim.clean_range_at(&pose, 0);
    let frame = sim.frame(0).unwrap().pair.range;
    let mut dropped = 0;
    for (c, r) in clean.ranges_m.iter().zip(&frame.ranges_m) {
        if f64::from(*c) > 2.8 {
            assert!(r.is_nan());
            dropped += 1;
        } else {
            assert_eq!(r, c);
        }
    }
    assert!(dropped > 0 && dropped < clean.ranges_m.len());

    // Grazing incidence: compare with the true normals.
    let sim = sim_with(
        wall_scene(),
        0,
        vec![effect(
            "dropouts",
            "max_incidence_deg = 12.0\nmin_signal = 0.0",
        )],
        32,
    );
    let truth = sim.lidar_truth(0);
    let frame = sim.frame(0).unwrap().pair.range;
    let origin = truth.world_from_lidar.translation.vector;
    let mut grazing = 0;
    for (h, r) in truth.hits.iter().zip(&frame.ranges_m) {
        let h = h.unwrap();
        let dir = (h.point.coords - origin).normalize();
        let cos = h.normal.dot(&dir).abs();
        let drop = cos < 12f64.to_radians().cos();
        assert_eq!(r.is_nan(), drop, "cos {cos}");
        grazing += usize::from(drop);
    }
    assert!(grazing > 0);

    // Low signal: reflectivity 0.5 (grey), signal = 0.5 cos (1/r)^2 against 0.07.
    let sim = sim_with(
        wall_scene(),
        0,
        vec![effect(
            "dropouts",
            "max_incidence_deg = 90.0\nmin_signal = 0.07",
        )],
        32,
    );
    let echoes = sim.echoes_at(&sim.true_pose(0));
    let frame = sim.frame(0).unwrap().pair.range;
    let mut weak = 0;
    for (e, r) in echoes.iter().zip(&frame.ranges_m) {
        let e = e.unwrap();
        let signal = f64::from(e.reflectivity) * e.cos_incidence / (e.range_m * e.range_m);
        assert_eq!(r.is_nan(), signal < 0.07, "signal {signal}");
        weak += usize::from(signal < 0.07);
    }
    assert!(weak > 0 && weak < frame.ranges_m.len());

    // Random: the observed rate is within 4 sigma of the probability.
    let sim = sim_with(
        wall_scene(),
        4,
        vec![effect(
            "dropouts",
            "max_incidence_deg = 90.0\nmin_signal = 0.0\nrandom_probability = 0.2",
        )],
        64,
    );
    let frame = sim.frame(0).unwrap().pair.range;
    let n = frame.ranges_m.len() as f64;
    let rate = frame.ranges_m.iter().filter(|r| r.is_nan()).count() as f64 / n;
    assert!(
        (rate - 0.2).abs() < 4.0 * (0.2f64 * 0.8 / n).sqrt(),
        "{rate}"
    );
}

#[test]
fn mixed_pixels_lie_between_surfaces_only_at_depth_edges() {
    let sim = sim_with(wall_scene(), 0, vec![effect("mixed_pixels", "")], 48);
    let pose = sim.true_pose(0);
    let clean = sim.clean_range_at(&pose, 0);
    let mixed = sim.frame(0).unwrap().pair.range;
    let truth = sim.lidar_truth(0);
    let w = 48usize;
    let mut between = 0;
    for v in 1..w - 1 {
        for u in 1..w - 1 {
            let i = v * w + u;
            let objects: Vec<u32> = [
                i - w - 1,
                i - w,
                i - w + 1,
                i - 1,
                i,
                i + 1,
                i + w - 1,
                i + w,
                i + w + 1,
            ]
            .iter()
            .map(|&j| truth.hits[j].unwrap().object)
            .collect();
            let (c, m) = (f64::from(clean.ranges_m[i]), f64::from(mixed.ranges_m[i]));
            if objects.iter().all(|&o| o == objects[0]) {
                // Inside one surface the footprint average stays on it (to 1 mm).
                assert!((m - c).abs() < 1e-3, "pixel {u},{v}: {m} vs {c}");
            } else {
                let neighbours: Vec<f64> = [
                    i - w - 1,
                    i - w + 1,
                    i + w - 1,
                    i + w + 1,
                    i - 1,
                    i + 1,
                    i - w,
                    i + w,
                ]
                .iter()
                .map(|&j| f64::from(clean.ranges_m[j]))
                .collect();
                let lo = neighbours.iter().cloned().fold(c, f64::min);
                let hi = neighbours.iter().cloned().fold(c, f64::max);
                assert!(m >= lo - 1e-3 && m <= hi + 1e-3);
                if m > lo + 0.05 && m < hi - 0.05 {
                    between += 1;
                }
            }
        }
    }
    assert!(between > 0, "no mixed pixel at the box's edges");
    // A pulse resolution below the step resolves the echoes: no pixel in between.
    let sharp = sim_with(
        wall_scene(),
        0,
        vec![effect("mixed_pixels", "pulse_resolution_m = 0.05")],
        48,
    );
    let r = sharp.frame(0).unwrap().pair.range;
    for (m, c) in r.ranges_m.iter().zip(&clean.ranges_m) {
        let (m, c) = (f64::from(*m), f64::from(*c));
        let near_box = (m - 1.4).abs() < 0.5;
        let near_wall = (m - c).abs() < 1e-3 || m > 2.0;
        assert!(near_box || near_wall, "{m}");
    }
}

#[test]
fn lidar_and_eo_are_untouched_by_effects_that_are_not_listed() {
    let eo_only = vec![
        effect("vignetting", ""),
        effect("sensor_noise", ""),
        effect("exposure", ""),
    ];
    let sim = sim_with(wall_scene(), 3, eo_only, 32);
    let pose = sim.true_pose(1);
    let frame = sim.frame(1).unwrap();
    let clean = sim.clean_range_at(&pose, 0);
    let same = frame
        .pair
        .range
        .ranges_m
        .iter()
        .zip(&clean.ranges_m)
        .all(|(a, b)| a.to_bits() == b.to_bits());
    assert!(same);
    let lidar_only = vec![
        effect("range_noise", ""),
        effect("dropouts", ""),
        effect("mixed_pixels", ""),
    ];
    let sim = sim_with(wall_scene(), 3, lidar_only, 32);
    assert_eq!(
        sim.frame(1).unwrap().pair.eo.rgb,
        sim.clean_eo_at(&pose, 0).rgb
    );
}

/// Mean and standard deviation of the red channel over the central region.
fn stats(rgb: &[u8], w: usize, h: usize) -> (f64, f64) {
    let mut v = Vec::new();
    for y in h / 4..3 * h / 4 {
        for x in w / 8..w / 3 {
            v.push(f64::from(rgb[3 * (y * w + x)]));
        }
    }
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n;
    (mean, var.sqrt())
}

#[test]
fn sensor_noise_has_shot_plus_read_variance() {
    let linear = effect("exposure", "ev = 0.0\nresponse = \"linear\"");
    let sim = sim_with(
        wall_scene(),
        5,
        vec![
            linear.clone(),
            effect("sensor_noise", "full_well_e = 2000.0\nread_noise_e = 10.0"),
        ],
        32,
    );
    let noisy = sim.frame(0).unwrap().pair.eo;
    let clean = sim_with(wall_scene(), 5, vec![linear], 32)
        .frame(0)
        .unwrap()
        .pair
        .eo;
    let (cm, cs) = stats(&clean.rgb, 96, 72);
    assert!(cs < 0.6, "the clean wall is uniform ({cs})");
    let (nm, ns) = stats(&noisy.rgb, 96, 72);
    let x = cm / 255.0;
    let expected = 255.0 * (x * 2000.0 + 100.0).sqrt() / 2000.0;
    // Quantisation adds 1/12 code² of variance.
    let expected = (expected * expected + 1.0 / 12.0).sqrt();
    assert!((nm - cm).abs() < 1.0, "mean {nm} vs {cm}");
    assert!((ns / expected - 1.0).abs() < 0.15, "std {ns} vs {expected}");
}

#[test]
fn vignetting_follows_the_cos4_law_and_exposure_scales_and_saturates() {
    let linear = "ev = 0.0\nresponse = \"linear\"";
    let clean = sim_with(wall_scene(), 0, vec![effect("exposure", linear)], 32);
    let vig = sim_with(
        wall_scene(),
        0,
        vec![effect("exposure", linear), effect("vignetting", "")],
        32,
    );
    let a = clean.frame(0).unwrap().pair.eo;
    let b = vig.frame(0).unwrap().pair.eo;
    let cam = &vig.sensor_model().eo;
    for (x, y) in [(0u32, 0u32), (95, 71), (48, 36), (10, 60)] {
        let ray = cam
            .unproject_ray(nalgebra::Vector2::new(f64::from(x), f64::from(y)))
            .unwrap();
        let i = 3 * (y as usize * 96 + x as usize);
        let want = f64::from(a.rgb[i]) * ray.z.powi(4);
        assert!(
            (f64::from(b.rgb[i]) - want).abs() <= 1.0,
            "({x},{y}): {} vs {want}",
            b.rgb[i]
        );
    }
    let bright = sim_with(
        wall_scene(),
        0,
        vec![effect("exposure", "ev = 1.0\nresponse = \"linear\"")],
        32,
    );
    let c = bright.frame(0).unwrap().pair.eo;
    for (p, q) in a.rgb.iter().zip(&c.rgb) {
        let want = (2.0 * f64::from(*p)).min(255.0);
        assert!((f64::from(*q) - want).abs() <= 1.0, "{q} vs {want}");
    }
}

#[test]
fn motion_blur_and_specular_change_the_image_only_when_they_apply() {
    let lab = common::load("lab");
    let base = sim_with(lab.clone(), 0, vec![], 16);
    let blur = sim_with(
        lab.clone(),
        0,
        vec![effect("motion_blur", "shutter_s = 0.05\nsamples = 4")],
        16,
    );
    let no_shutter = sim_with(
        lab.clone(),
        0,
        vec![effect("motion_blur", "shutter_s = 0.0\nsamples = 2")],
        16,
    );
    let clean = base.frame(3).unwrap().pair.eo;
    assert_ne!(blur.frame(3).unwrap().pair.eo.rgb, clean.rgb);
    assert_eq!(no_shutter.frame(3).unwrap().pair.eo.rgb, clean.rgb);
    // The lab's cube and ball are glossy: highlights appear; the grey wall scene has
    // no glossy material: nothing changes.
    let glossy = sim_with(lab, 0, vec![effect("specular", "")], 16);
    let with = glossy.frame(3).unwrap().pair.eo;
    let brighter = with
        .rgb
        .iter()
        .zip(&clean.rgb)
        .filter(|(a, b)| a > b)
        .count();
    let darker = with
        .rgb
        .iter()
        .zip(&clean.rgb)
        .filter(|(a, b)| a < b)
        .count();
    assert!(brighter > 100 && darker == 0, "{brighter} {darker}");
    let matte = sim_with(wall_scene(), 0, vec![effect("specular", "")], 16);
    assert_eq!(
        matte.frame(0).unwrap().pair.eo.rgb,
        sim_with(wall_scene(), 0, vec![], 16)
            .frame(0)
            .unwrap()
            .pair
            .eo
            .rgb
    );
}

/// Adaptive footprint sampling against sampling every footprint, on the lab (a room
/// with a checkered cube, a sphere and a drum: depth edges, creases, curved surfaces,
/// reflectivity steps and noise textures seen obliquely, and objects cut by the image
/// border): the two agree to 1 mm on nearly every pixel and never differ in having a
/// return.
#[test]
fn adaptive_mixed_pixels_match_sampling_every_footprint() {
    let scene = Scene::load(&configs().join("scenes/lab.toml")).unwrap();
    let with = |adaptive: bool| {
        Simulator::with_options(
            scene.clone(),
            &SimOptions {
                effects: Some(vec![effect(
                    "mixed_pixels",
                    &format!("adaptive = {adaptive}"),
                )]),
                ..SimOptions::default()
            },
        )
        .unwrap()
    };
    let (adaptive, full) = (with(true), with(false));
    let (mut n, mut within_1mm, mut worst, mut sum) = (0usize, 0usize, 0.0f64, 0.0f64);
    let mut validity_differs = 0usize;
    for frame in [0, 9, 18, 27] {
        let a = adaptive.frame(frame).unwrap().pair.range;
        let f = full.frame(frame).unwrap().pair.range;
        for (ra, rf) in a.ranges_m.iter().zip(&f.ranges_m) {
            match (ra.is_finite(), rf.is_finite()) {
                (true, true) => {
                    let d = (f64::from(*ra) - f64::from(*rf)).abs();
                    n += 1;
                    within_1mm += usize::from(d <= 1e-3);
                    worst = worst.max(d);
                    sum += d;
                }
                (false, false) => {}
                _ => validity_differs += 1,
            }
        }
    }
    let share = within_1mm as f64 / n as f64;
    println!(
        "{n} pixels: {:.3} % within 1 mm, mean {:.4} mm, worst {:.1} mm; {validity_differs} differ in having a return",
        100.0 * share,
        1e3 * sum / n as f64,
        1e3 * worst
    );
    assert!(share > 0.995, "only {share} within 1 mm");
    assert!(
        sum / (n as f64) < 1e-4,
        "mean difference {} m",
        sum / n as f64
    );
    assert!(worst < 0.05, "worst difference {worst} m");
    assert_eq!(validity_differs, 0);
}

/// `moving_lights`: from one pose, frames at two instants have different EO images
/// (the lamps swing and flicker) and the same lidar ranges; without it, or with a
/// swing and flicker of zero, the two instants look the same. The frames are
/// deterministic in their time.
#[test]
fn moving_lights_change_the_shading_and_never_the_geometry() {
    let lab = common::load("lab");
    let pose = lab.trajectory.frame_pose(3);
    let (t1, t2) = (1_000_000_000, 1_700_000_000);
    let moving = sim_with(lab.clone(), 0, vec![effect("moving_lights", "")], 32);
    let a = moving.render_at(&pose, 0, t1);
    let b = moving.render_at(&pose, 0, t2);
    let changed =
        a.eo.rgb
            .iter()
            .zip(&b.eo.rgb)
            .filter(|(x, y)| x != y)
            .count();
    assert!(changed > a.eo.rgb.len() / 10, "{changed} values changed");
    let bits = |r: &texel::RangeFrame| r.ranges_m.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.range), bits(&b.range));
    assert_eq!(moving.render_at(&pose, 0, t2).eo.rgb, b.eo.rgb);
    for still in [
        sim_with(lab.clone(), 0, vec![], 32),
        sim_with(
            lab.clone(),
            0,
            vec![effect(
                "moving_lights",
                "amplitude_m = 0.0\nintensity_modulation = 0.0",
            )],
            32,
        ),
    ] {
        let a = still.render_at(&pose, 0, t1);
        let b = still.render_at(&pose, 0, t2);
        assert_eq!(a.eo.rgb, b.eo.rgb);
        assert_eq!(bits(&a.range), bits(&b.range));
        assert_eq!(a.eo.rgb, moving.clean_eo_at(&pose, t1).rgb);
    }
    // The Mitsuba backend exports the lights once: it refuses the effect.
    let refused = Simulator::with_options(
        lab,
        &SimOptions {
            effects: Some(vec![effect("moving_lights", "")]),
            backend: sims::BackendKind::Mitsuba,
            ..SimOptions::default()
        },
    );
    assert!(
        matches!(refused, Err(sims::SimError::BadOption(ref m)) if m.contains("moving_lights"))
    );
}
