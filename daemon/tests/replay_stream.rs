//! Replay source -> pipeline -> TCP clients: every scan of the capture arrives with
//! the capture's pose, a late client gets the same model from the snapshot, the
//! recording holds every raw frame and pose, and shutdown says goodbye.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::path::Path;
use std::time::Duration;

use texel::capture::{CaptureEvent, CaptureReader, PoseTopic};
use texel::pose::pose_difference;
use texel::wire::{Message, TextureFormat};
use texel_client::{Applied, Client, Replica};
use texel_daemon::config::{OverloadPolicy, RegistrationMode, ReplayConfig, SessionConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::status::Counter;
use texel_e2e::captures;
use tokio_util::sync::CancellationToken;

const FRAMES: u32 = 12;
const PERIOD_NS: u64 = 50_000_000;

fn config(capture: &Path, record: Option<&Path>) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.replay = vec![ReplayConfig {
        name: "replay".into(),
        capture: capture.to_path_buf(),
        speed: 1.0,
        fast: true,
    }];
    c.pipeline.registration = RegistrationMode::CapturePoses;
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.serve.texture = TextureFormat::Png;
    c.record.path = record.map(Path::to_path_buf);
    c.status.interval_ms = 100;
    c.status.log = false;
    c.validate("test").unwrap();
    c
}

/// Reads messages into a replica until `done` says so (or the stream ends).
async fn follow(
    client: &mut Client,
    replica: &mut Replica,
    mut done: impl FnMut(&Replica, &Applied) -> bool,
) {
    tokio::time::timeout(Duration::from_secs(20), async {
        while let Some(m) = client.next_message().await.unwrap() {
            let applied = replica.apply(m).unwrap();
            if done(replica, &applied) {
                return;
            }
        }
    })
    .await
    .expect("the stream stalled");
}

fn assert_has_capture_poses(replica: &Replica) {
    assert_eq!(replica.model.len(), FRAMES as usize);
    for (i, s) in replica.model.scans().iter().enumerate() {
        let i = i as u32;
        assert_eq!(s.listing.timestamp_ns, captures::timestamp(i, PERIOD_NS));
        let (angle, dist) = pose_difference(&s.world_from_scan, &captures::pose(i));
        assert!(
            angle < 1e-12 && dist < 1e-12,
            "scan {i}: {angle} rad {dist} m"
        );
        assert!(s.scan.as_ref().unwrap().usable_triangle_count() > 0);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_scan_reaches_early_and_late_clients_with_the_capture_poses() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("in.mcap");
    let out = dir.path().join("out.mcap");
    captures::write(&capture, FRAMES, PERIOD_NS, Some(PoseTopic::Truth));

    let shutdown = CancellationToken::new();
    let session = Session::start(config(&capture, Some(&out)), shutdown.clone())
        .await
        .unwrap();
    let addr = session.local_addr.unwrap();
    let mut early = Client::connect(addr, "", "early").await.unwrap();
    assert_eq!(early.server.version, texel::wire::PROTOCOL_VERSION);
    let mut early_model = Replica::new();
    follow(&mut early, &mut early_model, |r, _| {
        r.model.resident_len() == FRAMES as usize
    })
    .await;
    assert_has_capture_poses(&early_model);

    // A newcomer after the replay ended gets the whole model: the snapshot lists it,
    // the client fetches every scan.
    tokio::time::timeout(Duration::from_secs(10), session.sources_done.cancelled())
        .await
        .unwrap();
    let mut late = Client::connect(addr, "", "late").await.unwrap();
    let mut late_model = Replica::new();
    follow(&mut late, &mut late_model, |r, _| r.complete()).await;
    assert_eq!(late_model.resets, 1);
    assert_has_capture_poses(&late_model);
    for (a, b) in early_model
        .model
        .scans()
        .iter()
        .zip(late_model.model.scans())
    {
        assert_eq!(a.scan, b.scan, "PNG textures are exact");
    }
    // Statuses arrive on the stream.
    follow(&mut late, &mut late_model, |_, a| *a == Applied::Status).await;
    let status = late_model.status.clone().unwrap();
    assert_eq!(status.counters["scans"], u64::from(FRAMES));
    assert_eq!(status.counters["paired"], u64::from(FRAMES));
    assert_eq!(status.sources[0].state, "ended");
    assert!(status.recording.is_some());

    // Shutdown: each client is told why.
    let metrics = session.metrics.clone();
    shutdown.cancel();
    for client in [&mut early, &mut late] {
        let reason = tokio::time::timeout(Duration::from_secs(3), async {
            loop {
                match client.next_message().await.unwrap() {
                    Some(Message::Goodbye { reason }) => return reason,
                    Some(_) => continue,
                    None => panic!("closed without a goodbye"),
                }
            }
        })
        .await
        .unwrap();
        assert!(reason.contains("shutting down"), "{reason}");
    }
    let summary = session.wait().await.unwrap();
    assert_eq!(summary.scans, FRAMES as usize);
    assert_eq!(metrics.get(Counter::RegistrationFailures), 0);
    let rec = summary.recording.unwrap();
    assert_eq!(rec.errors, 0);

    // The recording: sensor, every raw frame, every estimated pose, the truth kept.
    let mut reader = CaptureReader::open(&out).unwrap();
    let (mut ranges, mut eos, mut texel, mut truth, mut calibrations) = (0, 0, 0, 0, 0);
    for event in reader.by_ref() {
        match event.unwrap() {
            CaptureEvent::Range(_) => ranges += 1,
            CaptureEvent::Eo(_) => eos += 1,
            CaptureEvent::LidarCalibration { .. } => calibrations += 1,
            CaptureEvent::Pose {
                topic: PoseTopic::Texel,
                timestamp_ns,
                world_from_eo,
            } => {
                let i = ((timestamp_ns - captures::timestamp(0, PERIOD_NS)) / PERIOD_NS) as u32;
                assert_eq!(world_from_eo, captures::pose(i));
                texel += 1;
            }
            CaptureEvent::Pose {
                topic: PoseTopic::Truth,
                ..
            } => truth += 1,
            _ => {}
        }
    }
    assert_eq!(
        (ranges, eos, texel, truth, calibrations),
        (12, 12, 12, 12, 1)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_without_a_pose_are_counted_not_placed() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("no-poses.mcap");
    captures::write(&capture, 3, PERIOD_NS, None);
    let mut c = config(&capture, None);
    c.session.exit_when_sources_end = true;
    let session = Session::start(c, CancellationToken::new()).await.unwrap();
    let metrics = session.metrics.clone();
    let summary = tokio::time::timeout(Duration::from_secs(10), session.wait())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(summary.scans, 0);
    assert_eq!(metrics.get(Counter::RegistrationFailures), 3);
    assert_eq!(metrics.get(Counter::Paired), 3);
}
