//! A late joiner's overview from a running daemon: a simulated wall through the
//! daemon's pipeline and level-of-detail stage, then the viewer's tile renderer over
//! its own connection (`texel_viewer::tiles::net`), selecting, fetching, decoding and
//! drawing the tiles on the GPU. The wall shows, textured, in a view facing it; a
//! view away from it shows nothing.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::time::{Duration, Instant};

use texel::wire::TextureFormat;
use texel_client::Client;
use texel_daemon::config::{LatePolicy, SessionConfig, SimConfig};
use texel_daemon::pipeline::Session;
use texel_e2e::repo_root;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::gpu::GpuContext;
use texel_viewer::tiles::net::NetTileSource;
use texel_viewer::tiles::{TileRenderer, TileSettings, look_at};
use tokio_util::sync::CancellationToken;

const FRAMES: usize = 10;
const BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];

fn session() -> SessionConfig {
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
    c.session.exit_when_sources_end = false;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.serve.texture = TextureFormat::Png;
    c.status.interval_ms = 100;
    c.status.log = false;
    c.validate("test").unwrap();
    c
}

/// Waits until the daemon's tree reflects every scan.
async fn tree_settled(addr: std::net::SocketAddr) {
    let mut watcher = Client::connect(addr, "", "watcher").await.unwrap();
    watcher.set_max_in_flight(0);
    loop {
        let m = watcher.next_message().await.unwrap().expect("stream ended");
        // Every scan the model holds (registration may refuse a few) is in the tree.
        if let texel::wire::Message::Status(s) = m
            && let (Some(l), Some(model)) = (s.lod, s.model)
            && model.scans > 0
            && l.scans_fused == model.scans
            && l.pending_scans == 0
            && l.pending_tiles == 0
            && l.tiles > 0
        {
            break;
        }
    }
    watcher.close().await;
}

fn covered_fraction(img: &image::RgbaImage) -> f64 {
    let covered = img
        .pixels()
        .filter(|p| [p[0], p[1], p[2]] != [255, 0, 255])
        .count();
    covered as f64 / f64::from(img.width() * img.height()).max(1.0)
}

#[test]
fn a_late_joiner_draws_the_daemons_tiles() {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let stop = CancellationToken::new();
    let session = runtime
        .block_on(Session::start(session(), stop.clone()))
        .unwrap();
    let addr = session.local_addr.unwrap();
    runtime.block_on(async {
        tokio::time::timeout(Duration::from_secs(120), tree_settled(addr))
            .await
            .expect("the tree never settled");
    });

    let gpu = GpuContext::headless().unwrap();
    let joined = Instant::now();
    let source = NetTileSource::connect(addr, "", Duration::from_secs(5)).unwrap();
    let settings = TileSettings {
        background: BACKGROUND,
        fade_s: 0.0,
        ..TileSettings::default()
    };
    let mut tiles = TileRenderer::new(&gpu, source, settings).unwrap();
    // Facing the wall (y = 2 m) from 3 m, where the walk was.
    let facing = VirtualCamera::new(
        look_at([0.0, -1.0, 1.5], [0.0, 2.0, 1.5], [0.0, 0.0, 1.0]).unwrap(),
        50.0,
        160,
        120,
    )
    .unwrap();
    let mut frame = 0u32;
    let (image, stats) = loop {
        let (image, stats) = tiles
            .render_to_image(&facing, f64::from(frame) / 30.0)
            .unwrap();
        frame += 1;
        if stats.tiles_drawn > 0 && stats.loads_in_flight == 0 && stats.tiles_wanted == 0 {
            break (image, stats);
        }
        assert!(
            joined.elapsed() < Duration::from_secs(30),
            "no overview after {frame} frames: {stats:?}, errors {:?}",
            tiles.take_errors()
        );
        tiles.finish_loads(Duration::from_millis(200));
    };
    let first_overview = joined.elapsed();
    let covered = covered_fraction(&image);
    eprintln!(
        "first overview after {:.0} ms and {frame} frames: {} tiles, {} triangles, {:.1} % of the view covered",
        first_overview.as_secs_f64() * 1e3,
        stats.tiles_drawn,
        stats.triangles_drawn,
        covered * 100.0
    );
    assert!(tiles.take_errors().is_empty());
    // The patch of wall the walk saw (its lidar's field at 2 m) covers a good part
    // of the view.
    assert!(covered > 0.2, "{covered}");
    // The wall is textured (the mural), not a flat colour.
    let lum: Vec<f64> = image
        .pixels()
        .filter(|p| [p[0], p[1], p[2]] != [255, 0, 255])
        .map(|p| f64::from(p[0]) + f64::from(p[1]) + f64::from(p[2]))
        .collect();
    let mean = lum.iter().sum::<f64>() / lum.len() as f64;
    let sd = (lum.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / lum.len() as f64).sqrt();
    assert!(sd > 10.0, "flat colour: sd {sd}");

    // Facing away from the wall: nothing.
    let away = VirtualCamera::new(
        look_at([0.0, -1.0, 1.5], [0.0, -4.0, 1.5], [0.0, 0.0, 1.0]).unwrap(),
        50.0,
        160,
        120,
    )
    .unwrap();
    let (image, stats) = tiles.render_to_image(&away, 10.0).unwrap();
    assert_eq!(stats.tiles_drawn, 0);
    assert_eq!(covered_fraction(&image), 0.0);

    drop(tiles);
    stop.cancel();
    runtime.block_on(session.wait()).unwrap();
}
