//! Exposure brackets through the daemon: a simulated session on a bracketed scene
//! pairs each lidar frame with the exposure taken with it and records every EO frame
//! with its exposure time and gain (`/eo/exposure`); a replay of that recording
//! records them again, unchanged.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![cfg(feature = "sim")]

use std::path::Path;
use std::process::Command;

use texel::EoExposure;
use texel::capture::{TexelItem, open_texel_frames};
use texel_daemon::config::{LatePolicy, OverloadPolicy, SessionConfig, SimConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::source::sim::build_simulator;
use texel_e2e::repo_root;
use tokio_util::sync::CancellationToken;

const FRAMES: usize = 5;

fn sim_config() -> SimConfig {
    SimConfig {
        scene: repo_root().join("configs/scenes/courtyard-hdr.toml"),
        seed: 4,
        frames: Some(FRAMES),
        eo_size: Some([64, 48]),
        fast: true,
        late: LatePolicy::Wait,
        render_threads: 2,
        ..SimConfig::default()
    }
}

/// Every texel frame of a capture: (timestamp, the EO frame's exposure).
fn exposures(path: &Path) -> Vec<(u64, Option<EoExposure>)> {
    open_texel_frames(path)
        .unwrap()
        .filter_map(|item| match item.unwrap() {
            TexelItem::Pair { pair, .. } => Some((pair.eo.timestamp_ns, pair.eo.exposure)),
            _ => None,
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_bracketed_frame_is_recorded_with_its_exposure_and_replays_with_it() {
    let dir = tempfile::tempdir().unwrap();
    let live = dir.path().join("live.mcap");
    let sim = build_simulator(&sim_config().setup()).unwrap();

    let mut config = SessionConfig::default();
    config.source.sim = vec![sim_config()];
    config.session.exit_when_sources_end = true;
    // Every frame is fused, however slow the machine.
    config.pipeline.overload = OverloadPolicy::Backpressure;
    config.serve.bind = "127.0.0.1:0".parse().unwrap();
    config.record.path = Some(live.clone());
    config.status.log = false;
    config.validate("test").unwrap();
    let session = Session::start(config, CancellationToken::new())
        .await
        .unwrap();
    let summary = session.wait().await.unwrap();
    assert_eq!(summary.scans, FRAMES);

    // Each frame's exposure is the one the simulator exposed it with: the bracket
    // -2, 0, +2 EV around -0.5 EV, cycled frame by frame.
    let recorded = exposures(&live);
    assert_eq!(recorded.len(), FRAMES);
    let mut distinct = Vec::new();
    for (i, (t, exposure)) in recorded.iter().enumerate() {
        assert_eq!(*t, sim.timestamp_ns(i));
        let want = sim.frame(i).unwrap().pair.eo.exposure.unwrap();
        assert_eq!(*exposure, Some(want), "frame {i}");
        if !distinct.contains(&want.exposure_time_s.to_bits()) {
            distinct.push(want.exposure_time_s.to_bits());
        }
    }
    assert_eq!(distinct.len(), 3, "a three-exposure bracket");

    // A replay records the frames again with the same exposures.
    let replayed = dir.path().join("replayed.mcap");
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(["replay".as_ref(), live.as_os_str()])
        .args(["--fast", "--no-serve", "--out"])
        .arg(&replayed)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(exposures(&replayed), recorded);
}
