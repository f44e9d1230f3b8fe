//! The viewer against a real daemon: the daemon's library runs in the test (a replay
//! of a simulator capture of the `lab` scene, served on a loopback port, recorded),
//! and the `texel-viewer` binary connects to it over TCP.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

#[path = "../../viewer/tests/support/mod.rs"]
mod support;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use support::*;
use texel::PinholeCamera;
use texel::wire::TextureFormat;
use texel_daemon::cli::{ReplayArgs, RunOverrides, build_config};
use texel_daemon::pipeline::Session;
use texel_viewer::live::connection::{ConnectOptions, spawn};
use texel_viewer::live::{ConnectionState, ViewerEvent, apply_to_model};
use tokio_util::sync::CancellationToken;

const FRAMES: usize = 4;

/// A small simulator capture of `lab` (its default effects; 48x36 lidar, 160x120 EO).
fn lab_capture(dir: &Path) -> (PathBuf, sims::Simulator) {
    let scene = sims::Scene::load(&repo_root().join("configs/scenes/lab.toml")).unwrap();
    let options = sims::SimOptions {
        seed: 3,
        frames: Some(FRAMES),
        lidar_size: Some([48, 36]),
        eo_size: Some([160, 120]),
        ..Default::default()
    };
    let sim = sims::Simulator::with_options(scene, &options).unwrap();
    let path = dir.join("lab.mcap");
    sims::render_capture(&sim, &path, &Default::default(), &mut |_, _| {}).unwrap();
    (path, sim)
}

fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A daemon replaying `capture` (as fast as it goes, then staying), serving viewers on
/// a free loopback port with PNG textures (lossless) and recording to `record`.
struct Daemon {
    runtime: tokio::runtime::Runtime,
    shutdown: CancellationToken,
    session: Option<Session>,
    addr: SocketAddr,
}

impl Daemon {
    fn start(capture: &Path, record: &Path, bind: SocketAddr, speed: f64, fast: bool) -> Self {
        let replay = ReplayArgs {
            capture: capture.to_path_buf(),
            speed,
            fast,
            stay: true,
            registration: None,
        };
        let overrides = RunOverrides {
            bind: Some(bind),
            record: Some(record.to_path_buf()),
            status_interval_ms: Some(200),
            ..Default::default()
        };
        let mut config = build_config(None, Some(&replay), &overrides).unwrap();
        config.serve.texture = TextureFormat::Png;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let shutdown = CancellationToken::new();
        let session = runtime
            .block_on(Session::start(config, shutdown.clone()))
            .unwrap();
        let addr = session.local_addr.unwrap();
        Self {
            runtime,
            shutdown,
            session: Some(session),
            addr,
        }
    }

    fn wait_for_scans(&self, n: usize) {
        let hub = &self.session.as_ref().unwrap().hub;
        let start = Instant::now();
        while hub.scan_count() < n {
            assert!(start.elapsed() < Duration::from_secs(60), "daemon too slow");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Stops the daemon (the recording is finalised).
    fn stop(mut self) {
        self.shutdown.cancel();
        if let Some(s) = self.session.take() {
            self.runtime.block_on(s.wait()).unwrap();
        }
    }
}

fn run_viewer(args: &[&str], display: Option<&str>, cwd: &Path) -> std::process::Output {
    let mut cmd = Command::new(viewer_binary());
    cmd.args(args).current_dir(cwd);
    match display {
        Some(d) => cmd.env("DISPLAY", d),
        None => cmd.env_remove("DISPLAY"),
    };
    cmd.env_remove("WAYLAND_DISPLAY");
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "texel-viewer {args:?}: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    out
}

/// PSNR over the pixels `a` covers (not the background).
fn psnr_covered(a: &image::RgbaImage, truth: &[u8]) -> (f64, f64) {
    let (mut sq, mut n) = (0.0f64, 0usize);
    for (i, p) in a.pixels().enumerate() {
        if p[0] == 0 && p[1] == 0 && p[2] == 0 {
            continue;
        }
        for c in 0..3 {
            let d = f64::from(p[c]) - f64::from(truth[3 * i + c]);
            sq += d * d;
        }
        n += 1;
    }
    let mse = sq / (3.0 * n.max(1) as f64);
    (
        10.0 * (255.0f64 * 255.0 / mse.max(1e-9)).log10(),
        n as f64 / f64::from(a.width() * a.height()),
    )
}

#[test]
fn render_connect_matches_the_recording_and_the_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let (capture, sim) = lab_capture(dir.path());
    let record = dir.path().join("recorded.mcap");
    let daemon = Daemon::start(&capture, &record, "127.0.0.1:0".parse().unwrap(), 1.0, true);
    let addr = daemon.addr.to_string();
    let fov = texel_viewer::camera::VirtualCamera::fov_y_deg_of(&sim.sensor_model().eo);
    let fov_arg = format!("{fov}");
    let common = [
        "--acquisition",
        "2",
        "--fov-deg",
        &fov_arg,
        "--width",
        "160",
        "--height",
        "120",
        "--mode",
        "blended",
    ];
    let live = dir.path().join("live.png");
    let mut args = vec![
        "render",
        "--connect",
        &addr,
        "--wait-scans",
        "4",
        "--out",
        live.to_str().unwrap(),
    ];
    args.extend_from_slice(&common);
    run_viewer(&args, None, dir.path());
    // Rendering again gives the same bytes (deterministic).
    let again = dir.path().join("again.png");
    args[6] = again.to_str().unwrap();
    run_viewer(&args, None, dir.path());
    assert_eq!(
        std::fs::read(&live).unwrap(),
        std::fs::read(&again).unwrap(),
        "render --connect is not deterministic"
    );
    daemon.stop();

    let recorded = dir.path().join("recorded.png");
    let mut args = vec![
        "render",
        "--capture",
        record.to_str().unwrap(),
        "--out",
        recorded.to_str().unwrap(),
    ];
    args.extend_from_slice(&common);
    run_viewer(&args, None, dir.path());
    let a = image::open(&live).unwrap().to_rgba8();
    let b = image::open(&recorded).unwrap().to_rgba8();
    // The stream's PNG textures and the recording's raw frames are the same pixels, and
    // the recording's /texel/pose the poses the stream carried.
    let within = fraction_within(&a, &b, 1);
    assert!(within > 0.999, "{:.4} of pixels within 1/255", within);

    // Against the simulator's effect-free view from the same pose.
    let pose = sim.true_pose(2);
    let camera = PinholeCamera::from_vertical_fov(160, 120, fov).unwrap();
    let truth = sim.scene().render_view(&pose, &camera);
    let (psnr, coverage) = psnr_covered(&a, &truth.rgb);
    assert!(coverage > 0.8, "model covers {coverage:.2} of the view");
    assert!(
        psnr > 20.0,
        "PSNR {psnr:.1} dB against the simulator's view"
    );
}

#[test]
fn the_connection_reconnects_and_resynchronises() {
    let dir = tempfile::tempdir().unwrap();
    let (capture, _) = lab_capture(dir.path());
    let daemon = Daemon::start(
        &capture,
        &dir.path().join("a.mcap"),
        "127.0.0.1:0".parse().unwrap(),
        1.0,
        true,
    );
    daemon.wait_for_scans(FRAMES);
    let addr = daemon.addr;
    let (tx, rx) = std::sync::mpsc::sync_channel(64);
    let mut options = ConnectOptions::new(addr.to_string(), "");
    options.backoff_min = Duration::from_millis(50);
    options.backoff_max = Duration::from_millis(200);
    // This test asks for no scans: the request channel stays empty.
    let (_requests, request_rx) = std::sync::mpsc::sync_channel(1);
    let mut handle = spawn(options, tx, request_rx);
    let mut model = texel::model::Model::new();
    let mut seen = Vec::new();
    let wait_until =
        |model: &mut texel::model::Model,
         seen: &mut Vec<String>,
         done: &dyn Fn(&ViewerEvent, &texel::model::Model) -> bool| {
            let start = Instant::now();
            loop {
                let event = rx
                    .recv_timeout(Duration::from_secs(30).saturating_sub(start.elapsed()))
                    .unwrap_or_else(|_| panic!("timed out; events so far: {seen:?}"));
                apply_to_model(model, &event);
                seen.push(match &event {
                    ViewerEvent::Model { .. } => "model".into(),
                    ViewerEvent::Reset => "reset".into(),
                    ViewerEvent::SnapshotComplete { scans } => format!("snapshot {scans}"),
                    ViewerEvent::Status { .. } => "status".into(),
                    ViewerEvent::Connection(c) => c.describe(),
                    ViewerEvent::ScanUnavailable { id, .. } => format!("unavailable {id}"),
                    ViewerEvent::EoResponse(_) => "response".into(),
                });
                if done(&event, model) {
                    return;
                }
            }
        };
    wait_until(&mut model, &mut seen, &|e, m| {
        matches!(e, ViewerEvent::SnapshotComplete { .. }) && m.len() == FRAMES
    });
    // The daemon's status reaches the viewer.
    wait_until(
        &mut model,
        &mut seen,
        &|e, _| matches!(e, ViewerEvent::Status { status, .. } if status.counters.get("scans") == Some(&(FRAMES as u64))),
    );
    // The daemon goes away: the connection says so and keeps trying.
    daemon.stop();
    wait_until(&mut model, &mut seen, &|e, _| {
        matches!(e, ViewerEvent::Connection(ConnectionState::Retrying { .. }))
    });
    // It comes back on the same port: the viewer reconnects, resets and gets the
    // whole model again.
    let daemon = Daemon::start(&capture, &dir.path().join("b.mcap"), addr, 1.0, true);
    wait_until(&mut model, &mut seen, &|e, _| {
        matches!(e, ViewerEvent::Reset)
    });
    assert!(model.is_empty());
    // The new daemon may still be registering when the viewer connects: its snapshot
    // then holds the scans so far and the rest follow live.
    wait_until(&mut model, &mut seen, &|_, m| m.len() == FRAMES);
    assert!(
        seen.iter().filter(|s| s.starts_with("connected")).count() >= 2,
        "{seen:?}"
    );
    handle.stop();
    daemon.stop();
}

/// One snapshot of a live daemon's `lab` model after four scans, taken without a
/// display (`extra`: more viewer arguments): the viewer's stdout and stderr, and how
/// many pixels of the snapshot are lit.
fn one_live_snapshot(extra: &[&str]) -> (String, String, usize) {
    let dir = tempfile::tempdir().unwrap();
    let (capture, _) = lab_capture(dir.path());
    let daemon = Daemon::start(
        &capture,
        &dir.path().join("rec.mcap"),
        "127.0.0.1:0".parse().unwrap(),
        1.0,
        true,
    );
    let addr = daemon.addr.to_string();
    let mut args = vec![
        "--connect",
        &addr,
        "--width",
        "160",
        "--height",
        "120",
        "--every-scans",
        "4",
        "--max-snapshots",
        "1",
    ];
    args.extend_from_slice(extra);
    let out = run_viewer(&args, None, dir.path());
    daemon.stop();
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(
        stdout.contains("snapshot-0001.png (4 scans)"),
        "{stdout}\n{stderr}"
    );
    let shot = dir.path().join("texel-snapshots").join("snapshot-0001.png");
    let img = image::open(&shot).unwrap().to_rgba8();
    let lit = img
        .pixels()
        .filter(|p| p[0] > 20 || p[1] > 20 || p[2] > 20)
        .count();
    (stdout, stderr, lit)
}

#[test]
fn without_a_display_connect_writes_snapshots_of_the_live_model() {
    let (stdout, _, lit) = one_live_snapshot(&[]);
    assert!(
        stdout.contains("texel-snapshots") && stdout.contains("no DISPLAY"),
        "{stdout}"
    );
    assert!(lit > 160 * 120 / 2, "{lit} lit pixels");
}

#[test]
fn snapshots_of_the_live_model_by_view_dependent_texture_mapping() {
    // The daemon sends no camera model: the EO camera is fitted from the scans.
    let (_, stderr, lit) = one_live_snapshot(&["--mode", "vdtm"]);
    assert!(stderr.contains("VDTM: 4 scans, 4 views"), "{stderr}");
    assert!(lit > 160 * 120 / 2, "{lit} lit pixels");
}

#[test]
fn the_window_follows_a_live_daemon() {
    let dir = tempfile::tempdir().unwrap();
    let (capture, _) = lab_capture(dir.path());
    // Paced at real time (10 frames/s): the window joins while the model grows.
    let daemon = Daemon::start(
        &capture,
        &dir.path().join("rec.mcap"),
        "127.0.0.1:0".parse().unwrap(),
        1.0,
        false,
    );
    let addr = daemon.addr.to_string();
    let (_xvfb, display) = start_xvfb();
    let shot = dir.path().join("shot.png");
    let out = run_viewer(
        &[
            "--connect",
            &addr,
            "--width",
            "320",
            "--height",
            "240",
            "--frames",
            "6",
            "--min-scans",
            "4",
            "--screenshot",
            shot.to_str().unwrap(),
        ],
        Some(&display),
        dir.path(),
    );
    daemon.stop();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("4 scans in the model"), "{stdout}");
    let img = image::open(&shot).unwrap().to_rgba8();
    let mut colours: Vec<[u8; 3]> = img.pixels().map(|p| [p[0], p[1], p[2]]).collect();
    colours.sort_unstable();
    colours.dedup();
    assert!(colours.len() > 200, "{} distinct colours", colours.len());
}

#[test]
fn the_window_draws_a_daemons_level_of_detail_tiles() {
    let dir = tempfile::tempdir().unwrap();
    let (capture, _) = lab_capture(dir.path());
    let daemon = Daemon::start(
        &capture,
        &dir.path().join("rec.mcap"),
        "127.0.0.1:0".parse().unwrap(),
        1.0,
        true,
    );
    daemon.wait_for_scans(FRAMES);
    // The tree is built in the background: wait for its first tiles.
    let hub = &daemon.session.as_ref().unwrap().hub;
    let start = Instant::now();
    while hub.tile_counts().tiles == 0 {
        assert!(start.elapsed() < Duration::from_secs(60), "no tiles");
        std::thread::sleep(Duration::from_millis(20));
    }
    let addr = daemon.addr.to_string();
    let (_xvfb, display) = start_xvfb();
    let shot = dir.path().join("tiles.png");
    run_viewer(
        &[
            "--connect",
            &addr,
            "--lod",
            "--width",
            "320",
            "--height",
            "240",
            "--frames",
            "20",
            "--min-scans",
            "1",
            "--screenshot",
            shot.to_str().unwrap(),
        ],
        Some(&display),
        dir.path(),
    );
    daemon.stop();
    // The window drew the tiles (the scans were not drawn: `--lod`), from the first
    // scan's view: the merged room covers much of the frame.
    let img = image::open(&shot).unwrap().to_rgba8();
    let covered = img
        .pixels()
        .filter(|p| [p[0], p[1], p[2]] != [0, 0, 0])
        .count();
    let fraction = covered as f64 / f64::from(img.width() * img.height());
    let mut colours: Vec<[u8; 3]> = img.pixels().map(|p| [p[0], p[1], p[2]]).collect();
    colours.sort_unstable();
    colours.dedup();
    eprintln!(
        "tiles cover {:.1} % of the window, {} colours",
        fraction * 100.0,
        colours.len()
    );
    assert!(fraction > 0.2, "{fraction}");
    assert!(colours.len() > 50, "{} distinct colours", colours.len());
}
