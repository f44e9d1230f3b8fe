//! `texel-viewer open`'s in-process replay (no daemon): every frame of a capture is
//! fused and placed as the capture says, the same model as loading the whole file,
//! and a frame dated far in the future does not stall a paced replay.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use std::path::Path;
use std::sync::mpsc::{Receiver, sync_channel};
use std::time::Duration;

use texel::capture::{CaptureWriter, EoEncoding, PoseTopic, RangeEncoding, WriterOptions};
use texel::model::Model;
use texel_viewer::capture_load::load_capture;
use texel_viewer::live::replay::{ReplayHandle, ReplayOptions, spawn};
use texel_viewer::live::{ConnectionState, EVENT_QUEUE, ViewerEvent, apply_to_model};
use texel_viewer::scenes;

/// Replays `capture` and applies every event to a model until the replay ends; the
/// model and the reason it ended.
fn replay(capture: &Path, speed: f64, fast: bool) -> (Model, String) {
    let (tx, rx) = sync_channel(EVENT_QUEUE);
    let handle: ReplayHandle = spawn(
        ReplayOptions {
            capture: capture.to_path_buf(),
            speed,
            fast,
        },
        tx,
    );
    let result = drain(&rx);
    drop(handle);
    result
}

fn drain(rx: &Receiver<ViewerEvent>) -> (Model, String) {
    let mut model = Model::new();
    let mut snapshot_seen = false;
    loop {
        // A liveness bound, not a speed target: a stalled replay fails here.
        let event = rx
            .recv_timeout(Duration::from_secs(120))
            .expect("the replay sends its events and ends");
        match &event {
            ViewerEvent::Connection(ConnectionState::Ended { reason }) => {
                assert!(snapshot_seen, "ended before the empty snapshot: {reason}");
                return (model, reason.clone());
            }
            ViewerEvent::SnapshotComplete { scans } => {
                assert_eq!(*scans, 0);
                snapshot_seen = true;
            }
            _ => {}
        }
        // Model changes must apply; connection and status events change nothing.
        if matches!(event, ViewerEvent::Model { .. } | ViewerEvent::Reset) {
            assert!(
                apply_to_model(&mut model, &event),
                "{event:?} does not apply"
            );
        }
    }
}

#[test]
fn every_scan_is_placed_at_the_captures_pose_as_loading_the_file_places_it() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("box.mcap");
    support::write_box_capture(&capture, PoseTopic::Texel);
    let (replayed, reason) = replay(&capture, 1.0, true);
    let loaded = load_capture(&capture).unwrap();
    let frames = scenes::box_scene_poses().len();
    assert_eq!(replayed.len(), frames, "{reason}");
    assert_eq!(loaded.model.len(), frames);
    assert!(
        reason.contains(&format!("{frames} scans placed")),
        "{reason}"
    );
    assert_eq!(replayed.resident_len(), frames);
    assert_eq!(loaded.model.resident_len(), frames);
    for ((a, sa), (b, sb)) in replayed.resident().zip(loaded.model.resident()) {
        assert_eq!(a.id, b.id);
        assert_eq!(
            a.world_from_scan, b.world_from_scan,
            "scan {} placed elsewhere",
            a.id
        );
        assert_eq!(**sa, **sb, "scan {} fused differently", a.id);
    }
}

#[test]
fn a_frame_dated_a_year_ahead_does_not_stall_a_paced_replay() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("jump.mcap");
    let sensor = scenes::test_sensor();
    let scene = scenes::box_scene();
    let poses = scenes::box_scene_poses();
    let last = poses.len() - 1;
    let year_ns = 365 * 24 * 3600 * 1_000_000_000u64;
    let mut w = CaptureWriter::create(&capture, WriterOptions::default()).unwrap();
    w.write_sensor(&sensor.model, 0).unwrap();
    for (i, pose) in poses.iter().enumerate() {
        let (mut range, mut eo) =
            scenes::frames(&scene, &sensor, pose, scenes::tint(i as u32), i as u32 + 1);
        if i == last {
            range.timestamp_ns += year_ns;
            eo.timestamp_ns += year_ns;
        }
        w.write_range(&range, RangeEncoding::F32Metres).unwrap();
        w.write_eo(&eo, EoEncoding::Rgb8).unwrap();
        w.write_pose(PoseTopic::Texel, range.timestamp_ns, pose)
            .unwrap();
    }
    w.finish().unwrap();
    // Paced at real time: the frames 0.1 s apart, then the jump, capped at
    // MAX_FRAME_GAP of waiting.
    let (model, reason) = replay(&capture, 1.0, false);
    assert_eq!(model.len(), poses.len(), "{reason}");
}

#[test]
fn a_missing_capture_ends_the_replay_with_its_name() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nothing-here.mcap");
    let (tx, rx) = sync_channel(EVENT_QUEUE);
    let _handle = spawn(
        ReplayOptions {
            capture: missing.clone(),
            speed: 1.0,
            fast: true,
        },
        tx,
    );
    let event = rx.recv_timeout(Duration::from_secs(60)).unwrap();
    match event {
        ViewerEvent::Connection(ConnectionState::Ended { reason }) => {
            assert!(reason.contains("nothing-here.mcap"), "{reason}");
        }
        other => panic!("expected the end, got {other:?}"),
    }
}
