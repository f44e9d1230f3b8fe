//! Loading captures into a model: pose matching by time, registered poses preferred,
//! frames without a pose left out and counted, bad files named. No GPU.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use texel::capture::{CaptureWriter, EoEncoding, PoseTopic, RangeEncoding, WriterOptions};
use texel_viewer::capture_load::{LoadError, PoseSource, load_capture};
use texel_viewer::scenes;

#[test]
fn poses_are_matched_by_time_and_unplaced_frames_counted() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.mcap");
    let sensor = scenes::test_sensor();
    let scene = scenes::box_scene();
    let poses = scenes::box_scene_poses();
    let mut w = CaptureWriter::create(&path, WriterOptions::default()).unwrap();
    w.write_sensor(&sensor.model, 0).unwrap();
    for (i, pose) in poses.iter().enumerate() {
        let (range, eo) = scenes::frames(&scene, &sensor, pose, [1.0; 3], i as u32 + 1);
        w.write_range(&range, RangeEncoding::F32Metres).unwrap();
        w.write_eo(&eo, EoEncoding::Rgb8).unwrap();
        // Truth for every frame, 5 ms late; registered poses for frames 0 and 2 only,
        // frame 2's 30 ms late (outside the 20 ms tolerance).
        w.write_pose(PoseTopic::Truth, range.timestamp_ns + 5_000_000, pose)
            .unwrap();
        match i {
            0 => w
                .write_pose(PoseTopic::Texel, range.timestamp_ns, pose)
                .unwrap(),
            2 => w
                .write_pose(PoseTopic::Texel, range.timestamp_ns + 30_000_000, pose)
                .unwrap(),
            _ => {}
        }
    }
    w.finish().unwrap();
    let loaded = load_capture(&path).unwrap();
    assert_eq!(loaded.pose_source, PoseSource::Registered);
    assert_eq!(loaded.model.len(), 1);
    assert_eq!(loaded.unplaced, 2);
    let (angle, dist) =
        texel::pose::pose_difference(&loaded.model.get(0).unwrap().world_from_scan, &poses[0]);
    assert!(angle < 1e-12 && dist < 1e-12);
    assert_eq!(loaded.eo_camera, sensor.model.eo);
    assert!(loaded.warnings.is_empty(), "{:?}", loaded.warnings);
}

#[test]
fn captures_without_frames_or_poses_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let garbage = dir.path().join("garbage.mcap");
    std::fs::write(&garbage, b"not an mcap file at all").unwrap();
    let e = load_capture(&garbage).unwrap_err();
    assert!(e.to_string().contains("garbage.mcap"), "{e}");
    let no_poses = dir.path().join("no_poses.mcap");
    let sensor = scenes::test_sensor();
    let mut w = CaptureWriter::create(&no_poses, WriterOptions::default()).unwrap();
    w.write_sensor(&sensor.model, 0).unwrap();
    let (range, eo) = scenes::frames(
        &scenes::box_scene(),
        &sensor,
        &scenes::box_scene_poses()[0],
        [1.0; 3],
        1,
    );
    w.write_range(&range, RangeEncoding::F32Metres).unwrap();
    w.write_eo(&eo, EoEncoding::Rgb8).unwrap();
    w.finish().unwrap();
    match load_capture(&no_poses) {
        Err(LoadError::NoPoses { frames: 1, path }) => assert!(path.contains("no_poses.mcap")),
        other => panic!("{other:?}"),
    }
}
