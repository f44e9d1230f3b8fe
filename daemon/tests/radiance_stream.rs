//! Radiance on the wire (protocol version 4) against a real server on a hub: a
//! version 4 client gets the session's response curve in its snapshot and every
//! exposed scan's exposure with its data, whether the scan is broadcast as it arrives
//! or fetched later; scans without one arrive without one; a version 3 client is sent
//! neither message and still gets every scan.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::sync::Arc;
use std::time::Duration;

use texel::model::ScanId;
use texel::radiance::EoResponse;
use texel::wire::{Limits, Message, TextureFormat, decode_frame};
use texel::{EoExposure, FuseConfig, Sensor, TexelScan, fuse};
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

const HANG_GUARD: Duration = Duration::from_secs(60);

fn exposure(id: ScanId) -> Option<EoExposure> {
    // Even ids were exposed (and say so), odd ones did not record it.
    id.is_multiple_of(2).then(|| EoExposure {
        exposure_time_s: 0.01 * (1 + id) as f64,
        gain: 2.0,
    })
}

fn scan(id: ScanId) -> Arc<TexelScan> {
    let m = captures::sensor();
    let (r, mut eo) = captures::frame(&m, id as u32, 1_000 * id);
    eo.exposure = exposure(id);
    Arc::new(fuse(&r, eo, &Sensor::new(m), &FuseConfig::default()).unwrap())
}

/// Adds scan `id` as the encode stage does: its exposure noted first.
fn add(hub: &Hub, id: ScanId) {
    let scan = scan(id);
    let pose = captures::pose(id as u32);
    if let Some(e) = &scan.texture.exposure {
        hub.note_exposure(id, e).unwrap();
    }
    let frame = encode_scan(id, &scan, pose, TextureFormat::Png, 90).unwrap();
    let listing = texel::model::ScanListing::of_scan(&scan, frame.len() as u64, 0.0);
    hub.add_scan(id, listing, pose, frame, false, None).unwrap();
}

/// Reads into `replica`, fetching what it lacks, until it is live and complete with
/// at least `until` scans.
async fn follow(client: &mut Client, replica: &mut Replica, until: usize) {
    let fut = async {
        while !(replica.complete() && replica.model.resident_len() >= until) {
            let m = client
                .next_message()
                .await
                .unwrap()
                .expect("the stream ended");
            if let Applied::Goodbye(r) = replica.apply(m).unwrap() {
                panic!("goodbye: {r}");
            }
            for id in replica.wanted(4) {
                client.request_scan(id).await.unwrap();
            }
        }
    };
    tokio::time::timeout(HANG_GUARD, fut)
        .await
        .expect("the stream stalled");
}

fn assert_exposures(replica: &Replica, ids: std::ops::Range<ScanId>) {
    for id in ids {
        let scan = replica.model.get(id).unwrap().scan.as_ref().unwrap();
        assert_eq!(scan.texture.exposure, exposure(id), "scan {id}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn version_4_clients_get_the_response_and_every_exposure_version_3_neither() {
    let serve = SessionConfig::default().serve;
    let options = ServeOptions::from_config(&serve, "test");
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let hub = Hub::new(256);
    let response = EoResponse::from_linear(|x| x * x);
    hub.set_eo_response(Some(&response)).unwrap();
    let shutdown = CancellationToken::new();
    let task = tokio::spawn(server::run(
        listener,
        Arc::clone(&hub),
        options,
        Metrics::new(),
        shutdown.clone(),
    ));

    // Early: connected before any scan, so scans 0..4 are broadcast to it.
    let mut early = Client::connect(addr, "", "early").await.unwrap();
    let mut early_model = Replica::new();
    follow(&mut early, &mut early_model, 0).await;
    assert_eq!(early_model.eo_response.as_ref(), Some(&response));
    for id in 0..4 {
        add(&hub, id);
    }
    follow(&mut early, &mut early_model, 4).await;
    assert_exposures(&early_model, 0..4);

    // Late: every scan fetched by id.
    let mut late = Client::connect(addr, "", "late").await.unwrap();
    let mut late_model = Replica::new();
    follow(&mut late, &mut late_model, 4).await;
    assert_eq!(late_model.eo_response.as_ref(), Some(&response));
    assert_exposures(&late_model, 0..4);

    // Version 3: the raw stream holds neither message, and every scan's data.
    let mut v3 = TcpStream::connect(addr).await.unwrap();
    let hello = Message::ClientHello {
        version: 3,
        token: String::new(),
        client_name: "version 3 viewer".into(),
    };
    v3.write_all(&hello.encode().unwrap()).await.unwrap();
    let mut buf = Vec::new();
    let mut kinds = Vec::new();
    let mut requested = false;
    tokio::time::timeout(HANG_GUARD, async {
        while kinds.iter().filter(|k| **k == "ScanAdded").count() < 4 {
            let mut chunk = [0u8; 65536];
            let n = v3.read(&mut chunk).await.unwrap();
            assert!(n > 0, "the stream ended: {kinds:?}");
            buf.extend_from_slice(&chunk[..n]);
            while let Some((m, used)) = decode_frame(&buf, &Limits::FROM_SERVER).unwrap() {
                buf.drain(..used);
                kinds.push(m.kind_name());
                if let Message::ScanAdded(wire) = &m {
                    let (_, scan, _) = wire.as_ref().clone().into_scan().unwrap();
                    assert_eq!(scan.texture.exposure, None);
                }
            }
            if !requested && kinds.contains(&"SnapshotComplete") {
                for id in 0..4 {
                    let request = Message::RequestScan { id }.encode().unwrap();
                    v3.write_all(&request).await.unwrap();
                }
                requested = true;
            }
        }
    })
    .await
    .expect("the version 3 client never got its scans");
    assert!(
        !kinds.contains(&"ScanExposure") && !kinds.contains(&"EoResponse"),
        "{kinds:?}"
    );

    hub.close("test over");
    shutdown.cancel();
    tokio::time::timeout(HANG_GUARD, task)
        .await
        .unwrap()
        .unwrap();
}
