//! `texel-bench tradeoffs lod-live`: the level-of-detail tree in a running daemon. The
//! street capture is replayed at its own 30 Hz through the whole pipeline (scans
//! placed at the capture's poses) while a viewer watches the status: how far the tree
//! lags behind ingest. Once it has caught up, a late joiner connects over loopback and
//! is timed to its first overview (the top tiles' data, decoded) against the baseline
//! of the same joiner before level of detail: every served scan's data. Bytes per tile
//! on the wire come from the listings. Writes the "Level of detail in the daemon"
//! section of `docs/tradeoffs.md`.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use texel::wire::{LodStatus, Message};
use texel_client::{Client, Replica};
use texel_daemon::config::{RegistrationMode, ReplayConfig, SessionConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::status::percentiles;
use tokio_util::sync::CancellationToken;

use crate::tradeoffs::lod::StreetArgs;
use crate::tradeoffs::rendering::report::write_tradeoffs_section;

#[derive(Debug, Clone, clap::Args)]
pub struct LodLiveArgs {
    #[command(flatten)]
    pub street: StreetArgs,
}

/// What one run measured.
struct Figures {
    frames: usize,
    ingest_s: f64,
    lag_p50_s: f64,
    lag_p95_s: f64,
    lag_max_s: f64,
    pending_tiles_max: u64,
    catch_up_s: f64,
    final_lod: LodStatus,
    snapshot_s: f64,
    top_tiles: usize,
    top_bytes: u64,
    first_overview_s: f64,
    all_tiles: usize,
    all_tile_bytes: u64,
    all_tiles_s: f64,
    served_scans: usize,
    scan_bytes: u64,
    all_scans_s: f64,
}

pub fn run(args: &LodLiveArgs) -> Result<()> {
    let capture = args.street.capture(args.street.frames)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the runtime")?;
    let f = runtime.block_on(measure(&capture, args.street.frames))?;
    let body = markdown(&f);
    println!("{body}");
    if args.street.no_write {
        return Ok(());
    }
    write_tradeoffs_section(&args.street.repo, "lod-live", &body)
}

fn config(capture: &Path) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.replay = vec![ReplayConfig {
        name: "street".into(),
        capture: capture.to_path_buf(),
        speed: 1.0,
        fast: false,
    }];
    // The capture's poses (its truth): the tree's cost apart from registration's.
    c.pipeline.registration = RegistrationMode::CapturePoses;
    c.session.exit_when_sources_end = false;
    c.serve.bind = std::net::SocketAddr::from(([127, 0, 0, 1], 0));
    c.status.interval_ms = 250;
    c.status.log = false;
    c
}

async fn measure(capture: &Path, frames: usize) -> Result<Figures> {
    let config = config(capture);
    config
        .validate("bench")
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let shutdown = CancellationToken::new();
    let session = Session::start(config, shutdown.clone())
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let addr = session.local_addr.context("the session does not serve")?;
    let sources_done = session.sources_done.clone();

    // 1. A watcher follows the status while the capture plays at 30 Hz.
    let mut watcher = Client::connect(addr, "", "lag watcher").await?;
    watcher.set_max_in_flight(0);
    let started = Instant::now();
    let mut lags = Vec::new();
    let mut pending_tiles_max = 0;
    let mut ingest_s = None;
    let (final_lod, catch_up_s) = loop {
        let message = tokio::time::timeout(Duration::from_secs(600), watcher.next_message())
            .await
            .context("no status for 10 minutes")??
            .context("the stream ended")?;
        let Message::Status(status) = message else {
            continue;
        };
        let Some(lod) = status.lod else {
            bail!("the daemon reports no level-of-detail tree");
        };
        if sources_done.is_cancelled() {
            let ingest = *ingest_s.get_or_insert_with(|| started.elapsed().as_secs_f64());
            let fused = lod.scans_fused + lod.read_errors;
            if lod.pending_scans == 0 && lod.pending_tiles == 0 && fused > 0 {
                break (lod, started.elapsed().as_secs_f64() - ingest);
            }
        } else {
            lags.push(lod.lag_s);
            pending_tiles_max = pending_tiles_max.max(lod.pending_tiles);
        }
    };
    watcher.close().await;
    let (lag_p50_s, lag_p95_s) = percentiles(&lags);
    let lag_max_s = lags.iter().copied().fold(0.0, f64::max);
    eprintln!(
        "ingest {:.1} s, lag p50 {lag_p50_s:.2} p95 {lag_p95_s:.2} max {lag_max_s:.2} s; {} tiles",
        ingest_s.unwrap_or(0.0),
        final_lod.tiles
    );

    // 2. A late joiner: first overview (the top tiles), then every tile.
    let t0 = Instant::now();
    let mut joiner = Client::connect(addr, "", "late joiner").await?;
    joiner.set_max_in_flight(0);
    let mut replica = Replica::new();
    loop {
        let m = joiner.next_message().await?.context("the stream ended")?;
        let done = matches!(m, Message::SnapshotComplete { .. });
        replica.apply(m)?;
        if done {
            break;
        }
    }
    let snapshot_s = t0.elapsed().as_secs_f64();
    let roots = replica.tiles.roots();
    let top_tiles = roots.len();
    let (top_bytes, first_overview_s) = fetch_tiles(&mut joiner, &mut replica, &roots, t0).await?;
    let all: Vec<_> = replica.tiles.listings().map(|(id, _)| id).collect();
    let t1 = Instant::now();
    let (rest_bytes, all_tiles_s) = fetch_tiles(&mut joiner, &mut replica, &all, t1).await?;
    joiner.close().await;

    // 3. The baseline: the same late joiner fetching every served scan's data.
    let t2 = Instant::now();
    let mut baseline = Client::connect(addr, "", "late joiner, scans").await?;
    let mut scans = Replica::new();
    let mut scan_bytes = 0u64;
    while !scans.complete() {
        let m = baseline.next_message().await?.context("the stream ended")?;
        if let Message::ScanAdded(wire) = &m {
            scan_bytes += wire.view().frame_len() as u64;
        }
        scans.apply(m)?;
    }
    let all_scans_s = t2.elapsed().as_secs_f64();
    baseline.close().await;

    shutdown.cancel();
    session.wait().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(Figures {
        frames,
        ingest_s: ingest_s.unwrap_or(0.0),
        lag_p50_s,
        lag_p95_s,
        lag_max_s,
        pending_tiles_max,
        catch_up_s,
        final_lod,
        snapshot_s,
        top_tiles,
        top_bytes,
        first_overview_s,
        all_tiles: all.len(),
        all_tile_bytes: top_bytes + rest_bytes,
        all_tiles_s,
        served_scans: scans.model.len(),
        scan_bytes,
        all_scans_s,
    })
}

/// Requests `ids` not yet current and waits for their data, decoding every tile;
/// returns the bytes received and the seconds since `since`.
async fn fetch_tiles(
    client: &mut Client,
    replica: &mut Replica,
    ids: &[texel::tile::TileId],
    since: Instant,
) -> Result<(u64, f64)> {
    let before = replica.tiles.bytes_received();
    for id in replica.tiles.request(ids.iter().copied(), usize::MAX) {
        client.request_tile(id).await?;
    }
    while replica.tiles.in_flight() > 0 {
        let m = client.next_message().await?.context("the stream ended")?;
        if let Message::TileData(tile) = &m {
            texel_lod::decode_tile(&tile.data)
                .with_context(|| format!("tile {}", tile.id.path()))?;
        }
        replica.apply(m)?;
    }
    Ok((
        replica.tiles.bytes_received() - before,
        since.elapsed().as_secs_f64(),
    ))
}

fn mb(bytes: u64) -> f64 {
    bytes as f64 / 1e6
}

fn markdown(f: &Figures) -> String {
    let l = &f.final_lod;
    let ratio = if f.first_overview_s > 0.0 {
        f.all_scans_s / f.first_overview_s
    } else {
        0.0
    };
    format!(
        "## Level of detail in the daemon\n\n\
         The street capture ({frames} frames) replayed at its own 30 Hz through `texeld` \
         (scans at the capture's poses, retirement on, `[model.lod]` defaults), then a late \
         joiner over loopback. Measured with `cargo run --release -p texel-bench -- \
         tradeoffs lod-live` on the shared 2-core machine.\n\n\
         | figure | value |\n|---|---|\n\
         | ingest (replay at 30 Hz) | {ingest:.1} s |\n\
         | tree lag behind ingest, p50 / p95 / max | {p50:.2} / {p95:.2} / {max:.2} s |\n\
         | tiles waiting to be rebuilt, at most | {ptmax} |\n\
         | catch-up after the last frame | {catch:.1} s |\n\
         | scans fused, tiles rebuilt | {fused}, {rebuilds} |\n\
         | tiles served, top level | {tiles}, {top} |\n\
         | bytes per tile on the wire, mean / largest | {mean:.0} / {largest} |\n\
         | late joiner: snapshot (listings) | {snap:.3} s |\n\
         | late joiner: first overview ({ntop} top tiles, {topmb:.2} MB, decoded) | {first:.3} s |\n\
         | late joiner: every tile ({nall}, {allmb:.1} MB) | {alls:.2} s more |\n\
         | baseline: every served scan ({nscans}, {scanmb:.1} MB) | {scans_s:.2} s |\n\
         | first overview against the baseline | {ratio:.0} times sooner |\n",
        frames = f.frames,
        ingest = f.ingest_s,
        p50 = f.lag_p50_s,
        p95 = f.lag_p95_s,
        max = f.lag_max_s,
        ptmax = f.pending_tiles_max,
        catch = f.catch_up_s,
        fused = l.scans_fused,
        rebuilds = l.rebuilds,
        tiles = l.tiles,
        top = l.top_lod,
        mean = l.mean_tile_bytes,
        largest = l.largest_tile_bytes,
        snap = f.snapshot_s,
        ntop = f.top_tiles,
        topmb = mb(f.top_bytes),
        first = f.first_overview_s,
        nall = f.all_tiles,
        allmb = mb(f.all_tile_bytes),
        alls = f.all_tiles_s,
        nscans = f.served_scans,
        scanmb = mb(f.scan_bytes),
        scans_s = f.all_scans_s,
    )
}
