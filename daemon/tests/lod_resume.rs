//! A resumed session's level-of-detail tree holds what the live session's held: the
//! scans retirement took out of the served model stay in the tree's fields live
//! (they still average the surface down), so a resumed session fuses them too, read
//! back from the store, not only the scans it serves.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![cfg(feature = "sim")]

use std::sync::Arc;
use std::time::Duration;

use texel::TexelScan;
use texel::model::{ModelEvent, ScanId};
use texel::wire::{LodStatus, ModelStatus, TextureFormat};
use texel_client::{Client, Replica};
use texel_daemon::config::{LatePolicy, OverloadPolicy, SessionConfig, SimConfig};
use texel_daemon::pipeline::Session;
use texel_e2e::repo_root;
use texel_register::placement::{Placement, Registration, ScanInput, StageOutput};
use tokio_util::sync::CancellationToken;

const FRAMES: usize = 10;

/// Places every scan at the simulator's truth; a resumed session goes on after the
/// restored ids.
struct AtTruth {
    next: ScanId,
}

impl Registration for AtTruth {
    fn name(&self) -> &str {
        "at-truth"
    }

    fn restore(&mut self, _: &Arc<TexelScan>, _: ScanInput<'_>, id: ScanId, _: texel::Pose) {
        self.next = self.next.max(id + 1);
    }

    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput {
        let id = self.next;
        self.next += 1;
        StageOutput {
            placement: Placement::Placed {
                id,
                degenerate: false,
            },
            events: vec![ModelEvent::ScanAdded {
                id,
                scan: Arc::clone(scan),
                world_from_scan: input.truth.expect("the simulator knows the truth"),
            }],
            recovered: 0,
            anchors: Vec::new(),
        }
    }
}

fn session(recording: &std::path::Path, resume: bool) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.sim = vec![SimConfig {
        scene: repo_root().join("configs/scenes/wall.toml"),
        seed: 1,
        frames: Some(FRAMES),
        eo_size: Some([160, 120]),
        fast: true,
        late: LatePolicy::Wait,
        render_threads: 2,
        ..SimConfig::default()
    }];
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.session.exit_when_sources_end = false;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.serve.texture = TextureFormat::Png;
    c.status.interval_ms = 100;
    c.status.log = false;
    c.record.path = Some(recording.to_path_buf());
    c.record.flush_interval_ms = 100;
    c.record.resume = resume;
    assert!(c.model.retirement.enabled, "retirement is on by default");
    c.validate("test").unwrap();
    c
}

/// Runs a session until its model holds every frame and its tree has settled on
/// `fused` scans, and returns the tree's and the model's status.
async fn settled(
    recording: &std::path::Path,
    resume: bool,
    fused: u64,
) -> (LodStatus, ModelStatus) {
    let stop = CancellationToken::new();
    let session = Session::start_with_registration(
        session(recording, resume),
        Box::new(AtTruth { next: 0 }),
        stop.clone(),
    )
    .await
    .unwrap();
    let mut client = Client::connect(session.local_addr.unwrap(), "", "lod-resume")
        .await
        .unwrap();
    client.set_max_in_flight(0);
    let mut replica = Replica::new();
    let outcome = tokio::time::timeout(Duration::from_secs(120), async {
        loop {
            let m = client.next_message().await.unwrap().expect("stream ended");
            replica.apply(m).unwrap();
            let Some(status) = replica.status.as_ref() else {
                continue;
            };
            if let (Some(lod), Some(model)) = (&status.lod, &status.model)
                && lod.scans_fused >= fused
                && model.scans == FRAMES as u64
                && lod.pending_scans == 0
                && lod.pending_tiles == 0
            {
                return (lod.clone(), model.clone());
            }
        }
    })
    .await;
    let Ok(outcome) = outcome else {
        panic!(
            "the tree never settled on {fused} scans: {:?}",
            replica.status
        );
    };
    client.close().await;
    stop.cancel();
    session.wait().await.unwrap();
    outcome
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resumed_sessions_tree_fuses_the_retired_scans_too() {
    let dir = tempfile::tempdir().unwrap();
    let recording = dir.path().join("wall.mcap");
    let (live_lod, live_model) = settled(&recording, false, FRAMES as u64).await;
    eprintln!("live: {live_model:?}\n{live_lod:?}");
    // The walk along the wall overlaps enough that retirement takes some scans out of
    // the served model: what the resumed tree could otherwise miss.
    assert!(live_model.retired > 0, "{live_model:?}");
    assert_eq!(live_lod.scans_fused, FRAMES as u64);

    let (resumed_lod, resumed_model) = settled(&recording, true, FRAMES as u64).await;
    eprintln!("resumed: {resumed_model:?}\n{resumed_lod:?}");
    assert!(resumed_model.retired > 0, "{resumed_model:?}");
    assert_eq!(resumed_lod.scans_fused, FRAMES as u64);
    assert_eq!(resumed_lod.read_errors, 0);
    assert_eq!(resumed_lod.tiles, live_lod.tiles);
}
