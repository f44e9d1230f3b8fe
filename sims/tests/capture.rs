//! Captures read back with `texel::capture`: calibrations equal the simulator's sensor
//! model, frames equal the simulator's, `/truth/pose` equals the trajectory.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use common::{load, small};
use texel::capture::{CaptureEvent, CaptureReader, PoseTopic, TexelItem, open_texel_frames};

#[test]
fn a_capture_reads_back_with_its_calibration_frames_and_truth() {
    let sim = small(load("lab"), 5, None);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("lab.mcap");
    let options = sims::CaptureOptions {
        writer: texel::capture::WriterOptions {
            sync_to_disk: false,
            ..Default::default()
        },
        ..Default::default()
    };
    let sim = sims::Simulator::with_options(
        sim.scene().clone(),
        &sims::SimOptions {
            seed: 5,
            frames: Some(3),
            lidar_size: Some([32, 32]),
            eo_size: Some([80, 60]),
            ..Default::default()
        },
    )
    .unwrap();
    let mut calls = Vec::new();
    let summary = sims::render_capture(&sim, &path, &options, &mut |done, total| {
        calls.push((done, total))
    })
    .unwrap();
    assert_eq!(summary.frames, 3);
    assert_eq!(calls, vec![(1, 3), (2, 3), (3, 3)]);

    // Low level: the sensor messages and truth poses.
    let mut reader = CaptureReader::open(&path).unwrap();
    let (mut lidar_cal, mut eo_cal, mut tf, mut info, mut truths) =
        (None, None, None, None, Vec::new());
    while let Some(message) = reader.next_message() {
        match reader.decode(&message.unwrap()).unwrap() {
            CaptureEvent::LidarCalibration { camera, .. } => lidar_cal = Some(camera),
            CaptureEvent::EoCalibration { camera, .. } => eo_cal = Some(camera),
            CaptureEvent::EoFromLidar { pose, .. } => tf = Some(pose),
            CaptureEvent::Sensor { info: i, .. } => info = Some(i),
            CaptureEvent::Pose {
                topic: PoseTopic::Truth,
                timestamp_ns,
                world_from_eo,
            } => truths.push((timestamp_ns, world_from_eo)),
            _ => {}
        }
    }
    let model = sim.sensor_model();
    assert_eq!(lidar_cal.as_ref(), Some(&model.lidar));
    assert_eq!(eo_cal.as_ref(), Some(&model.eo));
    // The lab's lens_distortion effect puts the sensor file's coefficients in the calibration.
    assert!(matches!(
        model.eo.distortion,
        texel::Distortion::PlumbBob(_)
    ));
    let (angle, dist) = texel::pose::pose_difference(&tf.unwrap(), &model.eo_from_lidar);
    assert!(angle < 1e-12 && dist < 1e-12);
    assert_eq!(info.unwrap(), model.info());
    assert_eq!(truths.len(), 3);
    for (i, (ts, pose)) in truths.iter().enumerate() {
        assert_eq!(*ts, sim.timestamp_ns(i));
        let (a, d) = texel::pose::pose_difference(pose, &sim.true_pose(i));
        assert!(a < 1e-9 && d < 1e-9, "frame {i}: {a} {d}");
    }

    // Texel frames: bit-identical to the simulator's, with equal timestamps.
    let mut frames = open_texel_frames(&path).unwrap();
    let mut n = 0;
    for item in frames.by_ref() {
        if let TexelItem::Pair { pair, sensor } = item.unwrap() {
            let expected = sim.frame(n).unwrap();
            assert_eq!(pair.range.timestamp_ns, pair.eo.timestamp_ns);
            assert_eq!(pair.eo, expected.pair.eo);
            let same = pair
                .range
                .ranges_m
                .iter()
                .zip(&expected.pair.range.ranges_m)
                .all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()));
            assert!(same, "frame {n}");
            assert_eq!(*sensor, *model);
            n += 1;
        }
    }
    assert_eq!(n, 3);
}

#[test]
fn without_lens_distortion_the_capture_says_pinhole() {
    let sim = small(load("lab"), 0, Some(&["range_noise"]));
    assert_eq!(sim.sensor_model().eo.distortion, texel::Distortion::None);
    assert_eq!(
        sim.sensor_model().eo.fx,
        sim.scene().sensor().eo.fx * 80.0 / 640.0
    );
}
