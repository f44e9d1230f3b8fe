//! Scans listed, then fetched by id (protocol version 2) against a real server on a
//! hub: a late joiner gets listings first and fetches the same model an early client
//! has; unknown and withdrawn scans are unavailable and the connection stays usable;
//! a request flood beyond the limit is told the limit and disconnected; a version 1
//! hello is refused with its reason; a fetched scan whose pose was revised lands with
//! its newest pose.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use texel::model::ScanId;
use texel::wire::{Limits, Message, TextureFormat, decode_frame};
use texel::{FuseConfig, Pose, Sensor, TexelScan, fuse};
use texel_client::{Applied, Client, Replica};
use texel_daemon::config::SessionConfig;
use texel_daemon::hub::Hub;
use texel_daemon::pipeline::encode::encode_scan;
use texel_daemon::server::{self, ServeOptions};
use texel_daemon::status::Metrics;
use texel_e2e::captures;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;

/// Only a hang guard: nothing here is expected to take this long.
const HANG_GUARD: Duration = Duration::from_secs(60);

struct Server {
    addr: SocketAddr,
    hub: Arc<Hub>,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<()>,
}

async fn start_server(tune: impl FnOnce(&mut ServeOptions)) -> Server {
    let serve = SessionConfig::default().serve;
    let mut options = ServeOptions::from_config(&serve, "test");
    tune(&mut options);
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let hub = Hub::new(256);
    let shutdown = CancellationToken::new();
    let task = tokio::spawn(server::run(
        listener,
        Arc::clone(&hub),
        options,
        Metrics::new(),
        shutdown.clone(),
    ));
    Server {
        addr,
        hub,
        shutdown,
        task,
    }
}

impl Server {
    async fn stop(self) {
        self.hub.close("test over");
        self.shutdown.cancel();
        tokio::time::timeout(HANG_GUARD, self.task)
            .await
            .unwrap()
            .unwrap();
    }
}

fn scan(i: u32) -> Arc<TexelScan> {
    let m = captures::sensor();
    let (r, eo) = captures::frame(&m, i, 1_000 * u64::from(i));
    Arc::new(fuse(&r, eo, &Sensor::new(m), &FuseConfig::default()).unwrap())
}

/// Adds scan `id` at its capture pose, encoded as the pipeline does.
fn add(hub: &Hub, id: ScanId) {
    let scan = scan(id as u32);
    let pose = captures::pose(id as u32);
    let frame = encode_scan(id, &scan, pose, TextureFormat::Png, 90).unwrap();
    let listing = texel::model::ScanListing::of_scan(&scan, frame.len() as u64, 0.0);
    hub.add_scan(id, listing, pose, frame, false, None).unwrap();
}

/// Reads into `replica` until `done`.
async fn follow(
    client: &mut Client,
    replica: &mut Replica,
    mut done: impl FnMut(&Replica, &Applied) -> bool,
) {
    tokio::time::timeout(HANG_GUARD, async {
        while let Some(m) = client.next_message().await.unwrap() {
            let applied = replica.apply(m).unwrap();
            if done(replica, &applied) {
                return;
            }
        }
        panic!("the stream ended");
    })
    .await
    .expect("the stream stalled");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_joiner_gets_listings_first_and_fetches_the_early_clients_model() {
    let server = start_server(|_| {}).await;
    let mut early = Client::connect(server.addr, "", "early").await.unwrap();
    let mut early_model = Replica::new();
    follow(&mut early, &mut early_model, |_, a| {
        *a == Applied::SnapshotComplete
    })
    .await;
    for id in 0..6 {
        add(&server.hub, id);
    }
    server
        .hub
        .revise_pose(2, Pose::translation(0.5, 0.25, 1.0))
        .unwrap();
    follow(&mut early, &mut early_model, |_, a| {
        *a == Applied::PoseRevised(2)
    })
    .await;

    // The late joiner reads the raw stream: every listing comes before any data.
    let mut late = Client::connect(server.addr, "", "late").await.unwrap();
    let mut late_model = Replica::new();
    let mut kinds = Vec::new();
    tokio::time::timeout(HANG_GUARD, async {
        while !late_model.complete() {
            let m = late.next_message().await.unwrap().unwrap();
            kinds.push(m.kind_name());
            late_model.apply(m).unwrap();
        }
    })
    .await
    .expect("the late joiner never got the whole model");
    let first_data = kinds.iter().position(|k| *k == "ScanAdded").unwrap();
    let listed_before = kinds[..first_data]
        .iter()
        .filter(|k| **k == "ScanListed")
        .count();
    assert_eq!(kinds[0], "ModelReset");
    assert_eq!(listed_before, 6, "{kinds:?}");
    assert_eq!(kinds.iter().filter(|k| **k == "ScanAdded").count(), 6);

    let ids = |r: &Replica| r.model.scans().iter().map(|s| s.id).collect::<Vec<_>>();
    assert_eq!(ids(&late_model), ids(&early_model));
    for (a, b) in early_model
        .model
        .scans()
        .iter()
        .zip(late_model.model.scans())
    {
        assert_eq!(a.world_from_scan, b.world_from_scan, "scan {}", a.id);
        assert_eq!(a.scan, b.scan, "scan {}: PNG textures are exact", a.id);
        assert!(b.is_resident());
        assert_eq!(b.listing.bounds_min_m, a.listing.bounds_min_m);
        assert_eq!(b.listing.bounds_max_m, a.listing.bounds_max_m);
        assert!(
            b.listing.encoded_bytes > 0,
            "the listing gives the frame's size"
        );
    }
    assert_eq!(late_model.in_flight(), 0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_and_withdrawn_scans_are_unavailable_and_the_connection_stays_usable() {
    let server = start_server(|_| {}).await;
    for id in 0..3 {
        add(&server.hub, id);
    }
    let mut client = Client::connect(server.addr, "", "viewer").await.unwrap();
    client.set_max_in_flight(0);
    let mut replica = Replica::new();
    follow(&mut client, &mut replica, |_, a| {
        *a == Applied::SnapshotComplete
    })
    .await;
    assert_eq!((replica.model.len(), replica.model.resident_len()), (3, 0));

    client.request_scan(77).await.unwrap();
    let mut answer = None;
    follow(&mut client, &mut replica, |_, a| {
        answer = Some(a.clone());
        matches!(a, Applied::Unavailable { .. })
    })
    .await;
    let Some(Applied::Unavailable { id, reason }) = answer else {
        unreachable!()
    };
    assert_eq!(id, 77);
    assert!(reason.contains("77"), "{reason}");

    // Still usable: a withdrawn scan is gone, then unavailable; a served one arrives.
    server.hub.withdraw(1).unwrap();
    follow(&mut client, &mut replica, |_, a| {
        *a == Applied::ScanWithdrawn(1)
    })
    .await;
    client.request_scan(1).await.unwrap();
    client.request_scan(2).await.unwrap();
    let mut answers = Vec::new();
    follow(&mut client, &mut replica, |_, a| {
        if matches!(a, Applied::Unavailable { .. } | Applied::ScanAdded(_)) {
            answers.push(a.clone());
        }
        answers.len() == 2
    })
    .await;
    match &answers[0] {
        Applied::Unavailable { id: 1, reason } => {
            assert!(
                reason.contains("scan 1") && reason.contains("retired"),
                "{reason}"
            );
        }
        other => panic!("expected scan 1 unavailable, got {other:?}"),
    }
    assert_eq!(answers[1], Applied::ScanAdded(2));
    assert!(replica.model.get(1).is_none());

    // Listed again, it can be fetched again.
    server.hub.relist(1).unwrap();
    follow(&mut client, &mut replica, |_, a| {
        *a == Applied::ScanListed(1)
    })
    .await;
    client.request_scan(1).await.unwrap();
    follow(&mut client, &mut replica, |_, a| {
        *a == Applied::ScanAdded(1)
    })
    .await;
    assert!(replica.model.get(1).unwrap().is_resident());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fetched_scan_revised_since_it_was_encoded_lands_with_its_newest_pose() {
    let server = start_server(|_| {}).await;
    add(&server.hub, 0);
    let first = Pose::translation(1.0, 2.0, 3.0);
    let newest = Pose::translation(-4.0, 5.0, 0.5);
    server.hub.revise_pose(0, first).unwrap();
    let mut client = Client::connect(server.addr, "", "viewer").await.unwrap();
    client.set_max_in_flight(0);
    let mut replica = Replica::new();
    follow(&mut client, &mut replica, |_, a| {
        *a == Applied::SnapshotComplete
    })
    .await;
    assert_eq!(replica.model.get(0).unwrap().world_from_scan, first);
    server.hub.revise_pose(0, newest).unwrap();
    client.request_scan(0).await.unwrap();
    // Whatever order the live revision and the answer take, the stream ends on the
    // newest pose once the scan's data has landed.
    follow(&mut client, &mut replica, |r, _| {
        r.model
            .get(0)
            .is_some_and(|s| s.is_resident() && s.world_from_scan == newest)
    })
    .await;
    // The frame was encoded with the capture pose: a revision had to follow it.
    assert_ne!(captures::pose(0), newest);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_flood_beyond_the_limit_gets_a_goodbye_naming_the_limit() {
    let server = start_server(|o| o.max_requests_in_flight = 5).await;
    let mut client = Client::connect(server.addr, "", "flood").await.unwrap();
    client.set_max_in_flight(0);
    let mut flood = Vec::new();
    for id in 0..1000 {
        flood.extend(texel_client::request(id).unwrap());
    }
    client.send_raw(&flood).await.unwrap();
    let reason = tokio::time::timeout(HANG_GUARD, async {
        loop {
            match client.next_message().await {
                Ok(Some(Message::Goodbye { reason })) => return reason,
                Ok(Some(_)) => {}
                other => panic!("closed without a goodbye: {other:?}"),
            }
        }
    })
    .await
    .unwrap();
    assert!(reason.contains("5 in flight"), "{reason}");
    assert!(reason.contains("max_requests_in_flight"), "{reason}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_version_1_hello_is_refused_with_the_reason() {
    let server = start_server(|_| {}).await;
    let mut stream = TcpStream::connect(server.addr).await.unwrap();
    let hello = Message::ClientHello {
        version: 1,
        token: String::new(),
        client_name: "old viewer".into(),
    };
    stream.write_all(&hello.encode().unwrap()).await.unwrap();
    let mut answer = Vec::new();
    tokio::time::timeout(HANG_GUARD, stream.read_to_end(&mut answer))
        .await
        .unwrap()
        .unwrap();
    match decode_frame(&answer, &Limits::FROM_SERVER).unwrap() {
        Some((Message::Refused { reason }, _)) => assert_eq!(
            reason,
            "protocol version 1 is not served; this daemon speaks version 4: update the viewer"
        ),
        other => panic!("expected a refusal, got {other:?}"),
    }
    server.stop().await;
}
