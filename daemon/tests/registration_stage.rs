//! What the pipeline does with the registration stage's answers, driven by a scripted
//! stage over a replayed capture: a failed scan stays out of the model (but in the
//! recording) until a later call places it with the next id; a pose revision reaches
//! viewers as `PoseRevised`, is recorded as a later `/texel/pose` at the scan's frame
//! timestamp with a later log time, and readers (capture-poses, the model export)
//! take it; the counters say what happened.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::sync::Arc;
use std::time::Duration;

use texel::capture::{CaptureReader, PoseTopic, topics};
use texel::model::ModelEvent;
use texel::pose::pose_from_parts;
use texel::wire::TextureFormat;
use texel::{Pose, TexelScan};
use texel_client::{Client, Replica};
use texel_daemon::config::{OverloadPolicy, RegistrationMode, ReplayConfig, SessionConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::pipeline::placement::{
    CapturePoses, Placement, PlacementFailure, Registration, ScanInput, StageOutput,
};
use texel_daemon::status::Counter;
use texel_e2e::captures;
use tokio_util::sync::CancellationToken;

const FRAMES: u32 = 6;
const PERIOD_NS: u64 = 50_000_000;

/// Frame 1 fails and is placed (as id 4) together with frame 4; after frame 5, scan 0
/// is revised.
struct Scripted {
    truth: CapturePoses,
    calls: u32,
    next_id: u64,
    held: Option<Arc<TexelScan>>,
}

fn revised_pose() -> Pose {
    pose_from_parts([0.5, -0.25, 1.0], [0.0, 0.0, 0.0, 1.0]).unwrap()
}

impl Registration for Scripted {
    fn name(&self) -> &str {
        "scripted"
    }

    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput {
        let k = self.calls;
        self.calls += 1;
        if k == 1 {
            self.held = Some(Arc::clone(scan));
            return StageOutput {
                placement: Placement::Failed(PlacementFailure {
                    kind: "too-little-overlap",
                    reason: "scripted".into(),
                }),
                events: Vec::new(),
                recovered: 0,
                anchors: Vec::new(),
            };
        }
        let mut events = Vec::new();
        let mut add = |s: &Arc<TexelScan>, next_id: &mut u64| {
            let id = *next_id;
            *next_id += 1;
            events.push(ModelEvent::ScanAdded {
                id,
                scan: Arc::clone(s),
                world_from_scan: self.truth.pose_at(s.timestamp_ns).unwrap(),
            });
            id
        };
        let id = add(scan, &mut self.next_id);
        let mut recovered = 0;
        if k == 4
            && let Some(held) = self.held.take()
        {
            add(&held, &mut self.next_id);
            recovered = 1;
        }
        if k == FRAMES - 1 {
            events.push(ModelEvent::PoseRevised {
                id: 0,
                world_from_scan: revised_pose(),
            });
        }
        assert_eq!(input.timestamp_ns, scan.timestamp_ns);
        StageOutput {
            placement: Placement::Placed {
                id,
                degenerate: k == 2,
            },
            events,
            recovered,
            anchors: Vec::new(),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn failures_recoveries_and_revisions_reach_viewers_and_the_recording() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("in.mcap");
    let out = dir.path().join("out.mcap");
    captures::write(&capture, FRAMES, PERIOD_NS, Some(PoseTopic::Truth));

    let mut c = SessionConfig::default();
    // Every scan served: what this test follows is the stream, not retirement
    // (the synthetic frames overlap so much that most would retire).
    c.model.retirement.enabled = false;
    c.source.replay = vec![ReplayConfig {
        name: "replay".into(),
        capture: capture.clone(),
        speed: 1.0,
        fast: true,
    }];
    c.session.exit_when_sources_end = true;
    c.pipeline.registration = RegistrationMode::CapturePoses;
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.serve.texture = TextureFormat::Png;
    c.record.path = Some(out.clone());
    c.status.log = false;
    c.validate("test").unwrap();
    let stage = Scripted {
        truth: CapturePoses::from_capture(&capture).unwrap(),
        calls: 0,
        next_id: 0,
        held: None,
    };
    let session = Session::start_with_registration(c, Box::new(stage), CancellationToken::new())
        .await
        .unwrap();
    let metrics = session.metrics.clone();
    let mut client = Client::connect(session.local_addr.unwrap(), "", "t")
        .await
        .unwrap();
    let mut replica = Replica::new();
    tokio::time::timeout(Duration::from_secs(20), async {
        while let Some(m) = client.next_message().await.unwrap() {
            replica.apply(m).unwrap();
        }
    })
    .await
    .unwrap();
    session.wait().await.unwrap();

    // Every frame ended in the model; frame 1 as the fifth scan.
    let ts = |i: u32| captures::timestamp(i, PERIOD_NS);
    let order: Vec<u64> = replica
        .model
        .scans()
        .iter()
        .map(|s| s.listing.timestamp_ns)
        .collect();
    assert_eq!(order, vec![ts(0), ts(2), ts(3), ts(4), ts(1), ts(5)]);
    assert_eq!(replica.model.scans()[0].world_from_scan, revised_pose());
    // At least one revision reached the viewer; a fetch of scan 0 that crosses the
    // revision carries the revised pose again after the (older) frame, so a viewer
    // may count two messages for the one revision the daemon made.
    assert!(replica.model.scans()[0].revisions >= 1);
    assert_eq!(metrics.get(Counter::RegistrationFailures), 1);
    assert_eq!(metrics.get(Counter::RegistrationRecovered), 1);
    assert_eq!(metrics.get(Counter::RegistrationDegenerate), 1);
    assert_eq!(metrics.get(Counter::PoseRevisions), 1);
    assert_eq!(metrics.get(Counter::Scans), u64::from(FRAMES));

    // The recording: one /texel/pose per scan, then the revision of scan 0 at frame
    // 0's timestamp, logged at the latest frame's time.
    let mut reader = CaptureReader::open(&out).unwrap();
    let mut poses = Vec::new();
    while let Some(m) = reader.next_message() {
        let m = m.unwrap();
        if m.channel.topic == topics::TEXEL_POSE
            && let texel::capture::CaptureEvent::Pose {
                timestamp_ns,
                world_from_eo,
                ..
            } = reader.decode(&m).unwrap()
        {
            poses.push((timestamp_ns, m.log_time, world_from_eo));
        }
    }
    let stamps: Vec<u64> = poses.iter().map(|p| p.0).collect();
    assert_eq!(
        stamps,
        vec![ts(0), ts(2), ts(3), ts(4), ts(1), ts(5), ts(0)]
    );
    let revision = poses.last().unwrap();
    assert_eq!(revision.2, revised_pose());
    assert!(revision.1 > ts(0), "log time {} ns", revision.1);
    for p in &poses[..FRAMES as usize] {
        assert_eq!(p.0, p.1, "a first pose is logged at its frame's time");
    }

    // Readers take the last pose of a timestamp.
    let read = CapturePoses::from_capture(&out).unwrap();
    assert_eq!(read.pose_at(ts(0)), Some(revised_pose()));
}
