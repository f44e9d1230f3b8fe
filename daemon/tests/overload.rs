//! When registration falls behind, the `keep-newest` policy registers the newest pair
//! next and counts the ones it skipped, every frame is still recorded, and no queue
//! grows; `backpressure` registers every pair.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::sync::Arc;
use std::time::Duration;

use texel::TexelScan;
use texel::capture::{CaptureEvent, CaptureReader, PoseTopic};
use texel_daemon::config::{OverloadPolicy, RegistrationMode, ReplayConfig, SessionConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::pipeline::placement::{CapturePoses, Registration, ScanInput, StageOutput};
use texel_daemon::status::Counter;
use texel_e2e::captures;
use tokio_util::sync::CancellationToken;

/// The capture's poses, but 20 ms per scan: slower than a fast replay.
struct Slow(CapturePoses);

impl Registration for Slow {
    fn name(&self) -> &str {
        "slow capture poses"
    }

    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput {
        std::thread::sleep(Duration::from_millis(20));
        self.0.register(scan, input)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn keep_newest_skips_and_counts_while_recording_everything() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("c.mcap");
    let out = dir.path().join("out.mcap");
    let frames = 40u32;
    captures::write(&capture, frames, 10_000_000, Some(PoseTopic::Truth));
    for policy in [OverloadPolicy::KeepNewest, OverloadPolicy::Backpressure] {
        let mut c = SessionConfig::default();
        c.source.replay = vec![ReplayConfig {
            name: "replay".into(),
            capture: capture.clone(),
            speed: 1.0,
            fast: true,
        }];
        c.pipeline.registration = RegistrationMode::CapturePoses;
        c.session.exit_when_sources_end = true;
        c.pipeline.overload = policy;
        c.pipeline.pair_queue = 1;
        c.serve.enabled = false;
        c.record.path = Some(out.clone());
        c.status.log = false;
        c.validate("test").unwrap();
        let registration = Box::new(Slow(CapturePoses::from_capture(&capture).unwrap()));
        let session = Session::start_with_registration(c, registration, CancellationToken::new())
            .await
            .unwrap();
        let metrics = session.metrics.clone();
        let summary = tokio::time::timeout(Duration::from_secs(20), session.wait())
            .await
            .unwrap()
            .unwrap();
        let paired = metrics.get(Counter::Paired);
        let skipped = metrics.get(Counter::SkippedByOverload);
        assert_eq!(paired, u64::from(frames));
        // Every pair was either registered or counted as skipped.
        assert_eq!(summary.scans as u64 + skipped, paired, "{policy:?}");
        match policy {
            OverloadPolicy::KeepNewest => {
                assert!(
                    skipped > 0,
                    "a 20 ms stage cannot keep up with a fast replay"
                );
                // The newest pair is never the one skipped: the last frame is placed.
                let last = captures::timestamp(frames - 1, 10_000_000);
                assert_eq!(metrics.get(Counter::Scans), summary.scans as u64);
                let mut texel_poses = Vec::new();
                for event in CaptureReader::open(&out).unwrap() {
                    if let CaptureEvent::Pose {
                        topic: PoseTopic::Texel,
                        timestamp_ns,
                        ..
                    } = event.unwrap()
                    {
                        texel_poses.push(timestamp_ns);
                    }
                }
                assert_eq!(texel_poses.last(), Some(&last));
            }
            OverloadPolicy::Backpressure => assert_eq!(skipped, 0),
        }
        // Skipped or not, every raw frame is in the recording.
        let ranges = CaptureReader::open(&out)
            .unwrap()
            .filter(|e| matches!(e, Ok(CaptureEvent::Range(_))))
            .count();
        assert_eq!(ranges, frames as usize, "{policy:?}");
    }
}
