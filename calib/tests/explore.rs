#![allow(clippy::unwrap_used, clippy::expect_used)]
use calib::config::CalibConfig;
use calib::simulate::*;
use std::path::Path;

#[test]
fn explore() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let scene = sims::Scene::load(&root.join("configs/scenes/calib-target.toml")).unwrap();
    let sim = simulator(scene, 1, None).unwrap();
    let config = CalibConfig::default();
    let n: usize = std::env::var("NV").ok().and_then(|s| s.parse().ok()).unwrap_or(8);
    let t0 = std::time::Instant::now();
    let poses = sample_poses(&sim, &config.target, n + 4, PoseStyle::Varied, 7);
    let input = render_input(&sim, &poses[..n], 0);
    let held = render_input(&sim, &poses[n..], 100);
    println!("render {:?}", t0.elapsed());
    let t0 = std::time::Instant::now();
    let cal = calib::pipeline::calibrate(&input, &config, &mut |_, _, _| {}).unwrap();
    println!("calib {:?} detect {:.2} solve {:.2}", t0.elapsed(), cal.seconds_detect, cal.seconds_solve);
    let acc = accuracy(&cal, sim.sensor_model(), &held, &config.target);
    println!("{acc:?}");
    println!("eo only f {:?} joint {:?} std {:?}", &cal.eo_only.intrinsics[..4], &cal.eo.intrinsics[..4], &cal.eo.intrinsics_std[..4]);
    println!("rot std {:?} t std {:?} bias {} ± {}", cal.lidar.rotation_std_deg, cal.lidar.translation_std_m, cal.lidar.range_bias_m, cal.lidar.range_bias_std_m);
    for d in &cal.detections { if let Err(e) = &d.eo { println!("eo {}: {e}", d.index); } if let Err(e) = &d.lidar { println!("lidar {}: {e}", d.index); } }
}

#[test]
fn explore_model() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let scene = sims::Scene::load(&root.join("configs/scenes/calib-target.toml")).unwrap();
    let sim = simulator(scene, 1, None).unwrap();
    let config = CalibConfig::default();
    let poses = sample_poses(&sim, &config.target, 8, PoseStyle::Varied, 7);
    let input = render_input(&sim, &poses, 0);
    let cal = calib::pipeline::calibrate(&input, &config, &mut |_, _, _| {}).unwrap();
    let t = &sim.sensor_model().eo;
    let eo = &cal.sensor.eo;
    println!("{:?}\n{:?}", t, eo);
    for gy in 0..6 { for gx in 0..8 {
        let px = nalgebra::Vector2::new((gx as f64 + 0.5) / 8.0 * 640.0 - 0.5, (gy as f64 + 0.5) / 6.0 * 480.0 - 0.5);
        let ray = t.unproject_ray(px).unwrap();
        let q = eo.project(&ray).unwrap();
        print!("{:6.2} ", (q - px).norm());
    } println!(); }
    let img = image::RgbImage::from_raw(640, 480, input.views[1].pair.eo.rgb.clone()).unwrap();
    img.save("/tmp/v1.png").unwrap();
    let r = &input.views[1].pair.range;
    let d: Vec<u8> = r.ranges_m.iter().map(|v| if v.is_finite() { ((v - 0.5) / 3.0 * 255.0).clamp(0.0, 255.0) as u8 } else { 0 }).collect();
    image::GrayImage::from_raw(128, 128, d).unwrap().save("/tmp/r1.png").unwrap();
}

#[test]
fn print_poses() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let scene = sims::Scene::load(&root.join("configs/scenes/calib-target.toml")).unwrap();
    let sim = simulator(scene, 1, None).unwrap();
    let poses = sample_poses(&sim, &CalibConfig::default().target, 40, PoseStyle::Varied, 2024);
    for p in poses {
        let (t, q) = texel::pose::pose_to_parts(&p);
        println!("POSE    {{ position = [{:.4}, {:.4}, {:.4}], rotation_xyzw = [{:.6}, {:.6}, {:.6}, {:.6}] }},", t[0], t[1], t[2], q[0], q[1], q[2], q[3]);
    }
}

#[test]
fn cmp_truth() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let scene = sims::Scene::load(&root.join("configs/scenes/calib-target.toml")).unwrap();
    let sim = simulator(scene, 0, None).unwrap();
    for f in ["/tmp/ct/calibrated.toml", "/tmp/ct2/calibrated.toml"] {
        let m = texel::SensorModel::load(Path::new(f)).unwrap();
        let (a, d) = texel::pose::pose_difference(&sim.sensor_model().eo_from_lidar, &m.eo_from_lidar);
        println!("{f}: rot err {:.4} deg, trans {:.3} mm, cx {:.3} cy {:.3} fx {:.3}", a.to_degrees(), d*1e3, m.eo.cx, m.eo.cy, m.eo.fx);
    }
}
