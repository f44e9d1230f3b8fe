//! Board detection on rendered images (noise, vignetting, lens distortion, mixed
//! pixels on): every corner found is within a fraction of a pixel of the true
//! corner's projection, and the board's indexing does not depend on the view.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod calib_common;

use std::collections::HashMap;

use calib::config::TargetConfig;
use calib::detect::{DetectFailure, DetectParams, detect_board};
use calib::gray::GrayImage;
use calib::lidar::detect_lidar_board;
use calib_common::*;
use texel_bench::calibration::simulate::{PoseStyle, sample_poses};

fn rms(d: &[f64]) -> f64 {
    (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt()
}

#[test]
fn eo_and_lidar_corners_match_the_truth_with_one_board_frame_for_every_view() {
    let sim = sim(target_scene(), 3, None);
    let target = TargetConfig::default();
    let poses = sample_poses(&sim, &target, 4, PoseStyle::Varied, 11);
    let model = sim.sensor_model().clone();
    // Board index (i, j) -> true corner index, which must be the same in every view.
    let mut frame_map: HashMap<(usize, usize), usize> = HashMap::new();
    let mut lidar_views = 0;
    for (k, pose) in poses.iter().enumerate() {
        let pair = sim.render_at(pose, k as u64, 0);
        let g = GrayImage::from_eo(&pair.eo).unwrap();
        let corners = detect_board(&g, &target, &DetectParams::eo(g.width, g.height)).unwrap();
        assert_eq!(corners.found(), 54, "view {k}");
        let truth = true_pixels(&model.eo, pose);
        let matches = match_corners(&corners, &truth);
        let d: Vec<f64> = matches.iter().map(|m| m.2).collect();
        assert!(rms(&d) < 0.15, "view {k}: EO corner RMS {} px", rms(&d));
        assert!(
            d.iter().all(|&x| x < 0.5),
            "view {k}: worst {:?}",
            d.iter().fold(0.0f64, |a, b| a.max(*b))
        );
        for (ij, t, _) in matches {
            let prev = *frame_map.entry(ij).or_insert(t);
            assert_eq!(
                prev, t,
                "view {k}: corner {ij:?} is a different board corner"
            );
        }
        // The lidar: plate, plane and intensity corners where the plate is whole.
        if let Ok(board) = detect_lidar_board(&pair.range, &model.lidar, &target, k) {
            lidar_views += 1;
            let n = board.plane.normal;
            let world_from_lidar = pose * model.eo_from_lidar;
            let true_normal = world_from_lidar.inverse().rotation * nalgebra::Vector3::y();
            let angle = n.dot(&true_normal).abs().min(1.0).acos().to_degrees();
            assert!(
                angle < 1.0,
                "view {k}: lidar plane normal off by {angle} deg"
            );
            let corners = board.corners.expect("intensity corners");
            let truth = true_pixels(&model.lidar, &world_from_lidar);
            let matches = match_corners(&corners, &truth);
            let d: Vec<f64> = matches.iter().map(|m| m.2).collect();
            assert!(rms(&d) < 0.2, "view {k}: lidar corner RMS {} px", rms(&d));
            for (ij, t, _) in matches {
                assert_eq!(frame_map.get(&ij), Some(&t), "lidar view {k}: {ij:?}");
            }
        }
    }
    assert!(
        lidar_views >= 2,
        "the lidar saw the whole plate in {lidar_views} views"
    );
}

#[test]
fn a_partly_occluded_board_keeps_its_visible_corners_and_indexing() {
    // A 12 cm tile 10 cm in front of the board's upper right part.
    let scene = target_scene_with(
        r#"
[[objects.plane]]
name = "occluder"
material = "plaster"
position = [0.1, -0.1, 1.27]
rotation_deg = [90.0, 0.0, 0.0]
size = [0.1, 0.1]
"#,
    );
    let sim = sim(scene, 4, None);
    let target = TargetConfig::default();
    let model = sim.sensor_model().clone();
    let clear = sim_clear_pose();
    let pair = sim.render_at(&clear, 0, 0);
    let g = GrayImage::from_eo(&pair.eo).unwrap();
    let corners = detect_board(&g, &target, &DetectParams::eo(g.width, g.height)).unwrap();
    assert!(
        (38..54).contains(&corners.found()),
        "{} corners found",
        corners.found()
    );
    let truth = true_pixels(&model.eo, &clear);
    let matches = match_corners(&corners, &truth);
    assert!(matches.iter().all(|m| m.2 < 0.5), "{matches:?}");
    // Without the occluder the same indices name the same corners.
    let plain = sim_plain();
    let pair = plain.render_at(&clear, 0, 0);
    let g = GrayImage::from_eo(&pair.eo).unwrap();
    let full = detect_board(&g, &target, &DetectParams::eo(g.width, g.height)).unwrap();
    let full_map: HashMap<(usize, usize), usize> = match_corners(&full, &truth)
        .into_iter()
        .map(|m| (m.0, m.1))
        .collect();
    for (ij, t, _) in matches {
        assert_eq!(full_map.get(&ij), Some(&t));
    }
}

fn sim_clear_pose() -> texel::Pose {
    sims::trajectory::look_at(
        nalgebra::Point3::new(-0.25, -1.05, 1.35),
        nalgebra::Point3::new(0.0, 0.0, 1.2),
        nalgebra::Vector3::z(),
    )
}

fn sim_plain() -> sims::Simulator {
    sim(target_scene(), 4, None)
}

#[test]
fn images_without_a_board_are_refused_without_panicking() {
    let target = TargetConfig::default();
    // Flat, noise, and a half-board (cut by the image edge).
    let flat = GrayImage::new(160, 120, vec![0.5; 160 * 120]).unwrap();
    assert_eq!(
        detect_board(&flat, &target, &DetectParams::eo(160, 120)),
        Err(DetectFailure::NoCorners)
    );
    let mut rng = texel_bench::calibration::simulate::Rng::new(5);
    let noise: Vec<f32> = (0..160 * 120)
        .map(|_| rng.uniform(0.0, 1.0) as f32)
        .collect();
    let noise = GrayImage::new(160, 120, noise).unwrap();
    assert!(detect_board(&noise, &target, &DetectParams::eo(160, 120)).is_err());
    let non_finite = GrayImage::new(64, 48, vec![f32::NAN; 64 * 48]).unwrap();
    assert!(detect_board(&non_finite, &target, &DetectParams::eo(64, 48)).is_err());
    // A synthetic checkerboard of 6 x 4 inner corners is not the 9 x 6 board.
    let (w, h) = (200usize, 160usize);
    let data: Vec<f32> = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as i64, (k / w) as i64);
            let (cx, cy) = ((x - 30) / 20, (y - 30) / 20);
            if !(0..7).contains(&cx) || !(0..5).contains(&cy) || x < 30 || y < 30 {
                0.9
            } else if (cx + cy) % 2 == 0 {
                0.1
            } else {
                0.9
            }
        })
        .collect();
    let small = GrayImage::new(w, h, data).unwrap().blurred(0.8);
    match detect_board(&small, &target, &DetectParams::eo(w, h)) {
        Err(DetectFailure::NoGrid {
            found_x, found_y, ..
        }) => {
            assert_eq!((found_x, found_y), (6, 4));
        }
        other => panic!("expected NoGrid, got {other:?}"),
    }
}
