//! Every shipped scene loads, and renders frames that see it.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use common::{configs, small};

#[test]
fn every_shipped_scene_loads_and_renders() {
    let mut names = Vec::new();
    for entry in std::fs::read_dir(configs().join("scenes")).unwrap() {
        let path = entry.unwrap().path();
        let scene = sims::Scene::load(&path).unwrap();
        names.push(scene.name.clone());
        let sim = small(scene, 1, None);
        let last = sim.frame_count() - 1;
        // A bracketed scene's frames are under- and over-exposed by design: its
        // exposure is judged by the bracket's best frame.
        let bracket = sim
            .effects()
            .exposure
            .as_ref()
            .map_or(1, |e| e.bracket_ev.len().max(1));
        for start in [0, last + 1 - bracket.min(last + 1)] {
            let mut best: Option<(usize, f64)> = None;
            for i in start..(start + bracket).min(last + 1) {
                let f = sim.frame(i).unwrap();
                let returns = f.pair.range.return_count();
                assert!(
                    returns > 32 * 32 / 4,
                    "{}: frame {i} has {returns} returns",
                    path.display()
                );
                let mean = f.pair.eo.rgb.iter().map(|&v| f64::from(v)).sum::<f64>()
                    / f.pair.eo.rgb.len() as f64;
                if best.is_none_or(|(_, b)| (mean - 128.0).abs() < (b - 128.0).abs()) {
                    best = Some((i, mean));
                }
            }
            let (i, mean) = best.unwrap();
            assert!(
                mean > 30.0 && mean < 230.0,
                "{}: frame {i} mean {mean}",
                path.display()
            );
        }
    }
    names.sort();
    assert_eq!(
        names,
        [
            "backend-check",
            "calib-target",
            "corridor",
            "corridor-plain",
            "courtyard",
            "courtyard-hdr",
            "interior-window",
            "lab",
            "lab-walk",
            "long-hall",
            "plane",
            "street",
            "tunnel",
            "wall"
        ]
    );
}

#[test]
fn the_calibration_board_is_seen_from_every_pose() {
    let scene = common::load("calib-target");
    let sim = small(scene, 0, Some(&[]));
    let model = sim.sensor_model().clone();
    // The 0.6 x 0.45 m plate stands in the plane y = 0, centred 1.2 m up. Every other
    // view keeps the whole plate inside the lidar's view; every view sees its centre.
    let corners = [(-0.3, 0.975), (0.3, 0.975), (-0.3, 1.425), (0.3, 1.425)];
    for i in 0..sim.frame_count() {
        let world_from_eo = sim.true_pose(i);
        let world_from_lidar = world_from_eo * model.eo_from_lidar;
        let centre = world_from_eo.inverse_transform_point(&nalgebra::Point3::new(0.0, 0.0, 1.2));
        let px = model.eo.project(&centre.coords).unwrap();
        assert!(model.eo.contains_pixel(px), "pose {i}: centre at {px:?}");
        if i % 2 == 0 {
            for (x, z) in corners {
                let p = world_from_lidar.inverse_transform_point(&nalgebra::Point3::new(x, 0.0, z));
                let px = model.lidar.project(&p.coords).unwrap();
                assert!(
                    model.lidar.contains_pixel(px),
                    "pose {i}: corner ({x}, {z}) at lidar {px:?}"
                );
            }
        }
    }
}

#[test]
fn the_plain_corridor_looks_the_same_along_its_axis() {
    // Two clean range frames 1 m apart along the axis, same orientation: equal away
    // from the open ends (the degenerate direction for registration).
    let sim = small(common::load("corridor-plain"), 0, Some(&[]));
    let pose = texel::pose::pose_from_parts([10.0, 0.0, 1.5], [-0.5, 0.5, -0.5, 0.5]).unwrap();
    let mut moved = pose;
    moved.translation.vector.x += 1.0;
    let a = sim.clean_range_at(&pose, 0);
    let b = sim.clean_range_at(&moved, 0);
    let mut compared = 0;
    for (x, y) in a.ranges_m.iter().zip(&b.ranges_m) {
        if x.is_finite() && *x < 10.0 {
            assert!((x - y).abs() < 1e-4, "{x} vs {y}");
            compared += 1;
        }
    }
    assert!(compared > 500);
}
