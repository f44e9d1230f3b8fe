//! Slow and reconnecting viewers: a client that reads nothing does not hold up
//! ingest or the other clients, and is then resynchronised to the same model (or
//! disconnected with a message, by policy); a client that reconnects ends with the
//! same model as one connected throughout.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::path::Path;
use std::time::Duration;

use texel::PinholeCamera;
use texel::capture::PoseTopic;
use texel::model::Model;
use texel::wire::{Message, TextureFormat};
use texel_client::{Applied, Client, Replica};
use texel_daemon::config::{
    OverloadPolicy, RegistrationMode, ReplayConfig, SessionConfig, SlowClientPolicy,
};
use texel_daemon::pipeline::Session;
use texel_daemon::status::Counter;
use texel_e2e::captures;
use tokio_util::sync::CancellationToken;

fn config(capture: &Path, fast: bool) -> SessionConfig {
    let mut c = SessionConfig::default();
    // Every scan served: what this test follows is the stream, not retirement
    // (the synthetic frames overlap so much that most would retire).
    c.model.retirement.enabled = false;
    // No level-of-detail tree either: its tile listings would share the tiny client
    // queues this test sizes for scans, and its fusion the two cores.
    c.model.lod.enabled = false;
    c.source.replay = vec![ReplayConfig {
        name: "replay".into(),
        capture: capture.to_path_buf(),
        speed: 1.0,
        fast,
    }];
    c.pipeline.registration = RegistrationMode::CapturePoses;
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.status.log = false;
    c.status.interval_ms = 50;
    c.validate("test").unwrap();
    c
}

async fn follow_until(
    client: &mut Client,
    replica: &mut Replica,
    mut done: impl FnMut(&Replica, &Applied) -> bool,
) {
    tokio::time::timeout(Duration::from_secs(30), async {
        while let Some(m) = client.next_message().await.unwrap() {
            let applied = replica.apply(m).unwrap();
            if done(replica, &applied) {
                return;
            }
        }
        panic!(
            "the stream ended early: {} scans, {} resets",
            replica.model.len(),
            replica.resets
        );
    })
    .await
    .expect("the stream stalled");
}

fn assert_same_model(a: &Model, b: &Model) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.scans().iter().zip(b.scans()) {
        assert_eq!(x.id, y.id);
        assert_eq!(x.world_from_scan, y.world_from_scan);
        assert_eq!(x.scan, y.scan);
    }
}

/// 60 frames with a 320x240 texture sent raw: about 14 MB of stream, more than the
/// socket buffers of a client that reads nothing.
fn big_capture(path: &Path) -> u32 {
    let mut m = captures::sensor();
    m.eo = PinholeCamera::from_vertical_fov(320, 240, 40.0).unwrap();
    let frames = 60;
    captures::write_with(path, &m, frames, 10_000_000, Some(PoseTopic::Truth));
    frames
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_reads_nothing_holds_up_nobody_and_is_resynchronised_or_dropped() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("big.mcap");
    let frames = big_capture(&capture) as usize;

    for policy in [SlowClientPolicy::Resync, SlowClientPolicy::Disconnect] {
        // Paced (100 frames/s): the active client keeps up with its queue of 4 while
        // the stalled one's queue overflows. A fast replay publishes faster than a
        // client in this busy test process decodes, and would drop both.
        let mut c = config(&capture, false);
        c.serve.texture = TextureFormat::Rgb8;
        c.serve.client_queue = 4;
        c.serve.slow_client = policy;
        let shutdown = CancellationToken::new();
        let session = Session::start(c, shutdown.clone()).await.unwrap();
        let addr = session.local_addr.unwrap();
        let mut stalled = Client::connect(addr, "", "stalled").await.unwrap();
        let mut active = Client::connect(addr, "", "active").await.unwrap();
        let mut active_model = Replica::new();
        // The active client and ingest finish while the stalled one reads nothing.
        follow_until(&mut active, &mut active_model, |r, _| {
            r.model.resident_len() == frames
        })
        .await;
        tokio::time::timeout(Duration::from_secs(20), session.sources_done.cancelled())
            .await
            .unwrap();
        assert_eq!(session.hub.scan_count(), frames);

        let mut replica = Replica::new();
        match policy {
            SlowClientPolicy::Resync => {
                // It is sent a fresh snapshot and ends with the same model.
                // It is sent a fresh snapshot of listings and fetches every scan.
                follow_until(&mut stalled, &mut replica, |r, _| {
                    r.resets >= 2 && r.complete() && r.model.len() == frames
                })
                .await;
                assert_same_model(&replica.model, &active_model.model);
                assert!(session.metrics.get(Counter::ClientsResynced) >= 1);
            }
            SlowClientPolicy::Disconnect => {
                let reason = tokio::time::timeout(Duration::from_secs(20), async {
                    loop {
                        match stalled.next_message().await.unwrap() {
                            Some(Message::Goodbye { reason }) => return reason,
                            Some(_) => {}
                            None => panic!("closed without a goodbye"),
                        }
                    }
                })
                .await
                .unwrap();
                assert!(reason.contains("too slow"), "{reason}");
                assert_eq!(session.metrics.get(Counter::ClientsDropped), 1);
            }
        }
        shutdown.cancel();
        session.wait().await.unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reconnecting_client_ends_with_the_same_model_as_one_connected_throughout() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("paced.mcap");
    let frames = 24;
    // 24 frames 25 ms apart, replayed at x1: about 0.6 s.
    captures::write(&capture, frames, 25_000_000, Some(PoseTopic::Texel));
    let shutdown = CancellationToken::new();
    let session = Session::start(config(&capture, false), shutdown.clone())
        .await
        .unwrap();
    let addr = session.local_addr.unwrap();
    let mut steady = Client::connect(addr, "", "steady").await.unwrap();
    let mut steady_model = Replica::new();
    let mut flaky = Client::connect(addr, "", "flaky").await.unwrap();
    let mut flaky_model = Replica::new();

    // The flaky viewer sees a few scans and leaves...
    follow_until(&mut flaky, &mut flaky_model, |r, _| {
        r.model.resident_len() == 4
    })
    .await;
    flaky.close().await;
    // ...while the steady one keeps going...
    follow_until(&mut steady, &mut steady_model, |r, _| {
        r.model.resident_len() == 12
    })
    .await;
    // ...and the flaky one comes back mid-replay.
    let mut flaky = Client::connect(addr, "", "flaky again").await.unwrap();
    let mut flaky_model = Replica::new();
    let n = frames as usize;
    follow_until(&mut flaky, &mut flaky_model, |r, _| {
        r.complete() && r.model.resident_len() == n
    })
    .await;
    follow_until(&mut steady, &mut steady_model, |r, _| {
        r.model.resident_len() == n
    })
    .await;
    assert_eq!(steady_model.resets, 1);
    assert_eq!(flaky_model.resets, 1);
    assert_same_model(&flaky_model.model, &steady_model.model);
    for (i, s) in steady_model.model.scans().iter().enumerate() {
        assert_eq!(s.world_from_scan, captures::pose(i as u32));
    }
    shutdown.cancel();
    session.wait().await.unwrap();
}
