//! The level-of-detail tree in a running daemon, end to end: a simulated wall through
//! the pipeline, the tree built in the background, its tiles listed to a version 3
//! client, fetched by id and decoded on the far side; the surface they hold lies on
//! the simulator's wall. A scan placed wrongly and later revised to its true pose
//! leaves a ghost wall until the revision, and none after it (the tiles under it are
//! rebuilt), also with the fields paged out to disk after every operation. A version
//! 2 client is served the same model without the tiles.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![cfg(feature = "sim")]

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use texel::model::ModelEvent;
use texel::tile::TileId;
use texel::wire::client::FrameReader;
use texel::wire::{LodStatus, Message, TextureFormat};
use texel::{Pose, TexelScan};
use texel_client::{Client, Replica};
use texel_daemon::config::{LatePolicy, OverloadPolicy, SessionConfig, SimConfig};
use texel_daemon::pipeline::Session;
use texel_e2e::repo_root;
use texel_lod::{LodNode, decode_tile};
use texel_register::placement::{Placement, Registration, ScanInput, StageOutput};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;

const FRAMES: usize = 10;
/// The simulated wall: the plane y = 2 m (`configs/scenes/wall.toml`).
const WALL_Y_M: f64 = 2.0;

/// Places every scan at the simulator's truth, but the first one 0.6 m off towards
/// the camera; with `fix`, the last scan's call revises the first to its truth (as a
/// loop closure would).
struct MisplacedFirst {
    next: u64,
    fix: bool,
    first_truth: Option<Pose>,
}

impl Registration for MisplacedFirst {
    fn name(&self) -> &str {
        "misplaced-first"
    }

    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput {
        let id = self.next;
        self.next += 1;
        let truth = input.truth.expect("the simulator knows the truth");
        let world_from_scan = if id == 0 {
            self.first_truth = Some(truth);
            Pose::translation(0.0, -0.6, 0.0) * truth
        } else {
            truth
        };
        let mut events = vec![ModelEvent::ScanAdded {
            id,
            scan: Arc::clone(scan),
            world_from_scan,
        }];
        if self.fix && id + 1 == FRAMES as u64 {
            events.push(ModelEvent::PoseRevised {
                id: 0,
                world_from_scan: self.first_truth.unwrap(),
            });
        }
        StageOutput {
            placement: Placement::Placed {
                id,
                degenerate: false,
            },
            events,
            recovered: 0,
            anchors: Vec::new(),
        }
    }
}

fn session(field_budget_mb: u64) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.model.lod.field_memory_budget_mb = field_budget_mb;
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
    // Every frame becomes a scan, however loaded the machine: the test counts them.
    c.pipeline.overload = OverloadPolicy::Backpressure;
    // Served until the test has what it needs.
    c.session.exit_when_sources_end = false;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.serve.texture = TextureFormat::Png;
    c.status.interval_ms = 100;
    c.status.log = false;
    c.validate("test").unwrap();
    c
}

/// What a version 3 client saw once the tree caught up with every scan.
struct Outcome {
    status: LodStatus,
    tiles: BTreeMap<TileId, LodNode>,
    unavailable_reason: String,
}

async fn run(fix: bool, field_budget_mb: u64) -> Outcome {
    let stop = CancellationToken::new();
    let stage = MisplacedFirst {
        next: 0,
        fix,
        first_truth: None,
    };
    let session =
        Session::start_with_registration(session(field_budget_mb), Box::new(stage), stop.clone())
            .await
            .unwrap();
    let addr = session.local_addr.unwrap();
    let mut client = Client::connect(addr, "", "lod-test").await.unwrap();
    assert_eq!(client.server.version, texel::wire::PROTOCOL_VERSION);
    // Tiles only: the scans' data is not needed here.
    client.set_max_in_flight(0);
    let mut replica = Replica::new();
    let revisions = u64::from(fix);
    let outcome = tokio::time::timeout(Duration::from_secs(120), async {
        // 1. Until the tree reflects every scan (and the revision).
        let status = loop {
            let m = client.next_message().await.unwrap().expect("stream ended");
            replica.apply(m).unwrap();
            let Some(status) = replica.status.as_ref().and_then(|s| s.lod.clone()) else {
                continue;
            };
            let settled = status.scans_fused == FRAMES as u64
                && status.revisions_applied == revisions
                && status.pending_scans == 0
                && status.pending_tiles == 0
                && status.tiles > 0
                && replica.tiles.len() as u64 == status.tiles;
            if settled {
                break status;
            }
        };
        // 2. Every listed tile's data, and one tile that does not exist.
        let ids: Vec<TileId> = replica.tiles.listings().map(|(id, _)| id).collect();
        for id in replica.tiles.request(ids.iter().copied(), usize::MAX) {
            client.request_tile(id).await.unwrap();
        }
        let nowhere = TileId {
            lod: 0,
            x: 1 << 40,
            y: 0,
        };
        client.request_tile(nowhere).await.unwrap();
        let mut unavailable_reason = String::new();
        while replica.tiles.in_flight() > 0 || unavailable_reason.is_empty() {
            let m = client.next_message().await.unwrap().expect("stream ended");
            if let Message::TileUnavailable { id, reason } = &m {
                assert_eq!(*id, nowhere);
                unavailable_reason = reason.clone();
            }
            replica.apply(m).unwrap();
        }
        let mut tiles = BTreeMap::new();
        for id in ids {
            assert!(replica.tiles.is_current(id), "tile {} is stale", id.path());
            let data = replica.tiles.data(id).unwrap();
            let node = decode_tile(&data.data).unwrap();
            assert_eq!(node.id, id);
            let listing = replica.tiles.listing(id).unwrap();
            assert_eq!(
                listing.encoded_bytes as usize,
                data.data.len() + 4 + 1 + 17 + 8 + 4
            );
            // The listing's box (nested over the children) holds the tile's own.
            for a in 0..3 {
                assert!(listing.bounds_min_m[a] <= node.bounds_min_m[a] + 1e-9);
                assert!(listing.bounds_max_m[a] >= node.bounds_max_m[a] - 1e-9);
            }
            assert!(listing.geometric_error_m >= node.geometric_error_m - 1e-12);
            tiles.insert(id, node);
        }
        Outcome {
            status,
            tiles,
            unavailable_reason,
        }
    })
    .await
    .expect("the tree never caught up");
    // A version 2 viewer is served the same scans, without a single tile message.
    let v2 = v2_snapshot(addr).await;
    assert_eq!(v2.0, replica.model.len());
    assert_eq!(v2.1, 0, "a version 2 client was sent tile messages");
    client.close().await;
    stop.cancel();
    session.wait().await.unwrap();
    outcome
}

/// Connects with protocol version 2 and reads the snapshot: scans listed, tile
/// messages seen. Then asks for a tile, which version 2 does not have: the server
/// ends the connection saying why.
async fn v2_snapshot(addr: std::net::SocketAddr) -> (usize, usize) {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let hello = Message::ClientHello {
        version: 2,
        token: String::new(),
        client_name: "old viewer".into(),
    };
    stream.write_all(&hello.encode().unwrap()).await.unwrap();
    let mut frames = FrameReader::default();
    let (mut scans, mut tiles) = (0, 0);
    loop {
        let m = loop {
            if let Some(m) = frames.take_message().unwrap() {
                break m;
            }
            assert!(stream.read_buf(&mut frames.buf).await.unwrap() > 0);
        };
        match m {
            Message::ServerHello { version, .. } => assert_eq!(version, 2),
            Message::ScanListed { .. } => scans += 1,
            Message::TileListed { .. } | Message::TileWithdrawn { .. } => tiles += 1,
            Message::SnapshotComplete { .. } => break,
            _ => {}
        }
    }
    let ask = Message::RequestTile {
        id: TileId { lod: 0, x: 0, y: 0 },
    };
    stream.write_all(&ask.encode().unwrap()).await.unwrap();
    let reason = loop {
        if let Some(m) = frames.take_message().unwrap() {
            if let Message::Goodbye { reason } = m {
                break reason;
            }
            continue;
        }
        assert!(
            stream.read_buf(&mut frames.buf).await.unwrap() > 0,
            "closed without a goodbye"
        );
    };
    assert!(reason.contains("unexpected RequestTile"), "{reason}");
    (scans, tiles)
}

/// Distances of every vertex of the finest tiles from the wall.
fn off_wall_m(tiles: &BTreeMap<TileId, LodNode>) -> Vec<f64> {
    let mut d: Vec<f64> = tiles
        .values()
        .filter(|n| n.id.lod == 0)
        .flat_map(|n| (0..n.mesh.vertex_count()).filter_map(|v| n.mesh.world(v)))
        .map(|p| (p[1] - WALL_Y_M).abs())
        .collect();
    d.sort_by(f64::total_cmp);
    d
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_serves_tiles_on_the_wall_and_rebuilds_them_after_a_revision() {
    let fixed = run(true, 256).await;
    let status = &fixed.status;
    eprintln!("{status:?}");
    assert!(status.mean_tile_bytes > 0.0 && status.largest_tile_bytes > 0);
    assert_eq!(status.lag_s, 0.0);
    assert!(
        fixed.unavailable_reason.contains("not in the served tree"),
        "{}",
        fixed.unavailable_reason
    );
    let d = off_wall_m(&fixed.tiles);
    assert!(d.len() > 100, "{} vertices", d.len());
    let p99 = d[d.len() * 99 / 100];
    let worst = d[d.len() - 1];
    eprintln!(
        "revised: {} finest-level vertices, p99 {:.1} mm, worst {:.1} mm off the wall",
        d.len(),
        p99 * 1e3,
        worst * 1e3
    );
    assert!(p99 < 0.02, "p99 {p99} m");
    assert!(worst < 0.1, "worst {worst} m");

    // The same session without the revision keeps the first scan's ghost wall 0.6 m
    // in front of the real one: what the rebuild removed.
    let ghost = run(false, 256).await;
    let d = off_wall_m(&ghost.tiles);
    let ghosts = d.iter().filter(|&&x| x > 0.3).count();
    eprintln!(
        "unrevised: {ghosts} of {} vertices on the ghost wall",
        d.len()
    );
    assert!(ghosts > 50, "{ghosts}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fields_paged_to_disk_after_every_operation_give_the_same_tiles() {
    let whole = run(true, 256).await;
    assert_eq!(whole.status.field_paged_bytes, 0);
    // A budget of 0 keeps no block in memory between operations: every fusion, the
    // revision's removal and every rebuild reads its blocks back from the page file.
    let paged = run(true, 0).await;
    let status = &paged.status;
    eprintln!("{status:?}");
    assert_eq!(status.field_bytes, 0);
    assert!(status.field_paged_bytes > 0);
    assert_eq!(status.field_page_errors, 0);
    assert_eq!(
        paged.tiles.keys().collect::<Vec<_>>(),
        whole.tiles.keys().collect::<Vec<_>>()
    );
    // The revision reached the paged blocks: no ghost wall, the wall where it was.
    let d = off_wall_m(&paged.tiles);
    assert!(d.len() > 100, "{} vertices", d.len());
    let p99 = d[d.len() * 99 / 100];
    assert!(p99 < 0.02, "p99 {p99} m");
    assert!(d[d.len() - 1] < 0.1, "worst {} m", d[d.len() - 1]);
    // Fusion order aside (the stage's rounds follow the clock), the surface is the
    // same: as many vertices within a few percent.
    let n = off_wall_m(&whole.tiles).len() as f64;
    assert!(
        (d.len() as f64 - n).abs() <= 0.05 * n,
        "{} against {n}",
        d.len()
    );
}
