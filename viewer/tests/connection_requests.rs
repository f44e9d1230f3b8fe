//! The connection thread against a scripted daemon: listings and unavailability are
//! forwarded, the window's requests reach the daemon as `RequestScan`, the answer
//! comes back as the scan's data, and a reconnect drops requests made for the lost
//! connection.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::mpsc::{Receiver, sync_channel};
use std::time::Duration;

use texel::Pose;
use texel::model::{ModelEvent, ScanListing};
use texel::wire::{Limits, Message, PROTOCOL_VERSION, TextureFormat, WireScan, decode_frame};
use texel_viewer::live::connection::{ConnectOptions, spawn};
use texel_viewer::live::{SourceCommand, ViewerEvent};
use texel_viewer::scenes;

/// Reads one client message (blocking).
fn read_message(stream: &mut TcpStream, buf: &mut Vec<u8>) -> Message {
    loop {
        if let Some((m, used)) = decode_frame(buf, &Limits::FROM_CLIENT).unwrap() {
            buf.drain(..used);
            return m;
        }
        let mut chunk = [0u8; 4096];
        let n = stream.read(&mut chunk).unwrap();
        assert!(n > 0, "the viewer closed the connection");
        buf.extend_from_slice(&chunk[..n]);
    }
}

fn write(stream: &mut TcpStream, m: &Message) {
    stream.write_all(&m.encode().unwrap()).unwrap();
}

/// Answers the hello and sends a snapshot of two listed scans.
fn greet(stream: &mut TcpStream, buf: &mut Vec<u8>, listing: ScanListing) {
    assert!(matches!(
        read_message(stream, buf),
        Message::ClientHello { .. }
    ));
    write(
        stream,
        &Message::ServerHello {
            version: PROTOCOL_VERSION,
            server_name: "script".into(),
            session_name: "s".into(),
        },
    );
    write(stream, &Message::ModelReset { scan_count: 2 });
    for id in [0, 1] {
        write(
            stream,
            &Message::ScanListed {
                id,
                listing,
                world_from_scan: Pose::identity(),
            },
        );
    }
    write(stream, &Message::SnapshotComplete { scan_count: 2 });
}

/// The next event that is not about the connection or the status.
fn next_model_event(rx: &Receiver<ViewerEvent>) -> ViewerEvent {
    loop {
        let e = rx.recv_timeout(Duration::from_secs(30)).unwrap();
        if !matches!(e, ViewerEvent::Connection(_) | ViewerEvent::Status { .. }) {
            return e;
        }
    }
}

#[test]
fn requests_reach_the_daemon_and_answers_come_back() {
    let sensor = scenes::test_sensor();
    let pose = scenes::box_scene_poses()[0];
    let scan = scenes::scan(&scenes::box_scene(), &sensor, &pose, [1.0; 3], 0);
    let listing = ScanListing::of_scan(&scan, 1000, 2.0);
    let scan_copy = scan.clone();
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    let daemon = std::thread::spawn(move || {
        // First connection: answer a request for scan 1 with its data and one for
        // scan 0 with "unavailable", then drop the connection.
        let (mut stream, _) = listener.accept().unwrap();
        let mut buf = Vec::new();
        greet(&mut stream, &mut buf, listing);
        let mut asked = Vec::new();
        for _ in 0..2 {
            match read_message(&mut stream, &mut buf) {
                Message::RequestScan { id } => asked.push(id),
                other => panic!("not a request: {other:?}"),
            }
        }
        for &id in &asked {
            let m = if id == 1 {
                Message::ScanAdded(Box::new(
                    WireScan::from_scan(id, &scan, Pose::identity(), TextureFormat::Rgb8, 90)
                        .unwrap(),
                ))
            } else {
                Message::ScanUnavailable {
                    id,
                    reason: "withdrawn".into(),
                }
            };
            write(&mut stream, &m);
        }
        drop(stream);
        // Second connection: the first request it sees is one made after the reset.
        let (mut stream, _) = listener.accept().unwrap();
        let mut buf = Vec::new();
        greet(&mut stream, &mut buf, listing);
        let first = read_message(&mut stream, &mut buf);
        (asked, first)
    });
    let (tx, rx) = sync_channel(64);
    let (requests, request_rx) = sync_channel(4);
    let mut options = ConnectOptions::new(addr.to_string(), "");
    options.backoff_min = Duration::from_millis(20);
    let mut handle = spawn(options, tx, request_rx);
    assert!(matches!(next_model_event(&rx), ViewerEvent::Reset));
    for want in [0, 1] {
        match next_model_event(&rx) {
            ViewerEvent::Model {
                event: ModelEvent::ScanListed { id, listing: l, .. },
                ..
            } => assert_eq!((id, l), (want, listing)),
            other => panic!("not a listing: {other:?}"),
        }
    }
    assert!(matches!(
        next_model_event(&rx),
        ViewerEvent::SnapshotComplete { scans: 2 }
    ));
    let ask = |id, generation| {
        requests
            .send(SourceCommand::RequestScan { id, generation })
            .unwrap()
    };
    ask(1, 1);
    ask(0, 1);
    match next_model_event(&rx) {
        ViewerEvent::Model {
            event: ModelEvent::ScanAdded { id: 1, scan: s, .. },
            ..
        } => assert_eq!(*s, scan_copy),
        other => panic!("not scan 1's data: {other:?}"),
    }
    match next_model_event(&rx) {
        ViewerEvent::ScanUnavailable { id, reason } => {
            assert_eq!((id, reason.as_str()), (0, "withdrawn"));
        }
        other => panic!("not unavailable: {other:?}"),
    }
    // The connection drops. A request made before the new snapshot's reset is for
    // the lost model: it is not sent; one made after it is.
    ask(0, 1);
    assert!(matches!(next_model_event(&rx), ViewerEvent::Reset));
    ask(1, 2);
    let (asked, first) = daemon.join().unwrap();
    assert_eq!(asked, vec![1, 0]);
    assert!(matches!(first, Message::RequestScan { id: 1 }), "{first:?}");
    handle.stop();
}
