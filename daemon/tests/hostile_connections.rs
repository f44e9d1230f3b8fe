//! Hostile connections against a real server: silent connections and clients that
//! never read cannot hold viewer slots, pending handshakes are bounded per address
//! and in total, and the serve limits are configured and validated like every other
//! setting.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use texel::PinholeCamera;
use texel::capture::PoseTopic;
use texel::wire::{Limits, Message, TextureFormat, decode_frame};
use texel_client::{Client, ClientError};
use texel_daemon::config::{
    OverloadPolicy, RegistrationMode, ReplayConfig, SessionConfig, SlowClientPolicy,
};
use texel_daemon::hub::Hub;
use texel_daemon::pipeline::Session;
use texel_daemon::server::{self, ServeOptions};
use texel_daemon::status::{Counter, Metrics};
use texel_e2e::captures;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;

/// Only a hang guard: nothing here is expected to take this long.
const HANG_GUARD: Duration = Duration::from_secs(60);
const TOKEN: &str = "correct horse battery staple";

fn replay_config(capture: &Path, fast: bool) -> SessionConfig {
    let mut c = SessionConfig::default();
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
    c
}

/// What a flood of connections saw.
#[derive(Default)]
struct FloodStats {
    connections: AtomicU64,
    wrong_token_refusals: AtomicU64,
    /// Flood connections that were welcomed as viewers (there must be none).
    admitted: AtomicU64,
}

/// `n` connections from 127.0.0.1, each reopened as soon as the server closes it:
/// the first `wrong_token` of them send a hello with a wrong token, the others send
/// nothing.
struct Flood {
    stats: Arc<FloodStats>,
    stop: CancellationToken,
    tasks: JoinSet<()>,
}

impl Flood {
    fn start(addr: SocketAddr, n: usize, wrong_token: usize) -> Self {
        let stats = Arc::new(FloodStats::default());
        let stop = CancellationToken::new();
        let mut tasks = JoinSet::new();
        let bad_hello = Message::ClientHello {
            version: texel::wire::PROTOCOL_VERSION,
            token: "not the token, but as long as one".into(),
            client_name: "flood".into(),
        }
        .encode()
        .unwrap();
        for i in 0..n {
            let (stats, stop) = (Arc::clone(&stats), stop.clone());
            let hello = (i < wrong_token).then(|| bad_hello.clone());
            tasks.spawn(async move {
                while !stop.is_cancelled() {
                    let Ok(mut s) = TcpStream::connect(addr).await else {
                        // Out of ports or descriptors for a moment.
                        tokio::time::sleep(Duration::from_millis(10)).await;
                        continue;
                    };
                    stats.connections.fetch_add(1, Ordering::Relaxed);
                    if let Some(hello) = &hello {
                        let _ = s.write_all(hello).await;
                    }
                    let mut answer = Vec::new();
                    tokio::select! {
                        _ = s.read_to_end(&mut answer) => {}
                        () = stop.cancelled() => return,
                    }
                    match decode_frame(&answer, &Limits::FROM_SERVER) {
                        Ok(Some((Message::Refused { reason }, _))) if reason == "wrong token" => {
                            stats.wrong_token_refusals.fetch_add(1, Ordering::Relaxed);
                        }
                        Ok(Some((Message::ServerHello { .. }, _))) => {
                            stats.admitted.fetch_add(1, Ordering::Relaxed);
                        }
                        _ => {}
                    }
                }
            });
        }
        Self { stats, stop, tasks }
    }

    fn connections(&self) -> u64 {
        self.stats.connections.load(Ordering::Relaxed)
    }

    async fn stop(mut self) {
        self.stop.cancel();
        while self.tasks.join_next().await.is_some() {}
    }
}

/// Connects, retrying while the server answers that its pending places are taken;
/// returns the client and the number of attempts.
async fn connect_through(addr: SocketAddr, token: &str) -> (Client, u32) {
    tokio::time::timeout(HANG_GUARD, async {
        let mut attempts = 0;
        loop {
            attempts += 1;
            match Client::connect(addr, token, "viewer").await {
                Ok(c) => return (c, attempts),
                Err(ClientError::Refused(r)) if r.contains("pending handshakes") => {}
                Err(e) => panic!("the viewer was refused: {e}"),
            }
        }
    })
    .await
    .expect("the viewer never got in")
}

/// Reads until the snapshot is complete; returns its scan count.
async fn read_snapshot(client: &mut Client) -> u64 {
    tokio::time::timeout(HANG_GUARD, async {
        loop {
            match client.next_message().await.unwrap() {
                Some(Message::SnapshotComplete { scan_count }) => return scan_count,
                Some(_) => {}
                None => panic!("the stream ended before the snapshot was complete"),
            }
        }
    })
    .await
    .expect("the snapshot stalled")
}

async fn wait_for(what: &str, mut done: impl FnMut() -> bool) {
    tokio::time::timeout(HANG_GUARD, async {
        while !done() {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await
    .unwrap_or_else(|_| panic!("never happened: {what}"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_connections_do_not_lock_out_a_viewer() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("c.mcap");
    captures::write(&capture, 2, 10_000_000, Some(PoseTopic::Truth));
    for token in [None, Some(TOKEN)] {
        let mut c = replay_config(&capture, true);
        c.serve.token = token.map(str::to_string);
        c.status.interval_ms = 50;
        c.validate("test").unwrap();
        let max_clients = c.serve.max_clients as u64;
        let shutdown = CancellationToken::new();
        let session = Session::start(c, shutdown.clone()).await.unwrap();
        let addr = session.local_addr.unwrap();
        tokio::time::timeout(HANG_GUARD, session.sources_done.cancelled())
            .await
            .unwrap();

        // More silent connections than there are slots, refilled as they close; with
        // a token, some send a hello with a wrong one.
        let flooders = 24;
        let flood = Flood::start(addr, flooders, if token.is_some() { 4 } else { 0 });
        let m = &session.metrics;
        wait_for("the flood outnumbers the slots and is being fought", || {
            flood.connections() > 2 * max_clients && m.get(Counter::HandshakesEvicted) > 0
        })
        .await;

        let started = Instant::now();
        let before = flood.connections();
        let (mut viewer, attempts) = connect_through(addr, token.unwrap_or("")).await;
        assert_eq!(read_snapshot(&mut viewer).await, 2);
        let took = started.elapsed();
        let during = flood.connections() - before;
        // Not one flood connection holds a slot.
        assert_eq!(m.clients.load(Ordering::Relaxed), 1);
        // The flood goes on, and the admitted viewer keeps its slot and its stream.
        let (after, evicted) = (flood.connections(), m.get(Counter::HandshakesEvicted));
        wait_for("the flood goes on", || {
            flood.connections() > after + 2 * max_clients
                && m.get(Counter::HandshakesEvicted) > evicted
        })
        .await;
        tokio::time::timeout(HANG_GUARD, async {
            loop {
                match viewer.next_message().await.unwrap() {
                    Some(Message::Status(_)) => return,
                    Some(_) => {}
                    None => panic!("the viewer was closed during the flood"),
                }
            }
        })
        .await
        .expect("the viewer's stream stalled during the flood");
        assert_eq!(m.clients.load(Ordering::Relaxed), 1);
        // A viewer on another address is untouched by the flood: in at the first
        // attempt.
        let mut elsewhere = connect_from("127.0.0.2", addr).await;
        complete_handshake_with(&mut elsewhere, token.unwrap_or("")).await;
        assert_eq!(m.clients.load(Ordering::Relaxed), 2);
        if token.is_some() {
            wait_for("a wrong-token flooder is refused", || {
                flood.stats.wrong_token_refusals.load(Ordering::Relaxed) > 0
            })
            .await;
        }
        eprintln!(
            "token {}: the viewer got in after {attempt} attempt(s) in {took:?}, \
             while the flood opened {during} connections ({} in all); evicted {}, \
             timed out {}, wrong tokens refused {}",
            token.is_some(),
            flood.connections(),
            m.get(Counter::HandshakesEvicted),
            m.get(Counter::HandshakeTimeouts),
            flood.stats.wrong_token_refusals.load(Ordering::Relaxed),
            attempt = attempts,
        );
        let admitted = flood.stats.admitted.load(Ordering::Relaxed);
        flood.stop().await;
        assert_eq!(admitted, 0, "a flood connection was admitted as a viewer");
        shutdown.cancel();
        session.wait().await.unwrap();
    }
}

/// 60 frames with a 320x240 texture sent raw: about 14 MB of stream, more than the
/// socket buffers of a client that reads nothing.
fn big_capture(path: &Path) {
    let mut m = captures::sensor();
    m.eo = PinholeCamera::from_vertical_fov(320, 240, 40.0).unwrap();
    captures::write_with(path, &m, 60, 10_000_000, Some(PoseTopic::Truth));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_says_hello_and_never_reads_is_dropped() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("big.mcap");
    big_capture(&capture);
    let mut c = replay_config(&capture, false);
    c.serve.texture = TextureFormat::Rgb8;
    c.serve.max_clients = 1;
    // Room for the whole stream: the queue never overflows, so only the write
    // timeout can drop the stalled client.
    c.serve.client_queue = 256;
    c.serve.slow_client = SlowClientPolicy::Resync;
    c.serve.write_timeout_ms = 500;
    c.validate("test").unwrap();
    let shutdown = CancellationToken::new();
    let session = Session::start(c, shutdown.clone()).await.unwrap();
    let addr = session.local_addr.unwrap();
    let metrics = Arc::clone(&session.metrics);

    let mut stalled = Client::connect(addr, "", "stalled").await.unwrap();
    // While it holds the only slot, a newcomer is refused (unless the stalled one was
    // dropped already, which is what comes next).
    match Client::connect(addr, "", "early").await {
        Err(ClientError::Refused(r)) => assert!(r.contains("server full"), "{r}"),
        Err(e) => panic!("{e}"),
        Ok(_) => assert_eq!(metrics.get(Counter::ClientsWriteTimeouts), 1),
    }
    wait_for("the stalled client is dropped", || {
        metrics.get(Counter::ClientsWriteTimeouts) == 1
    })
    .await;
    assert_eq!(metrics.get(Counter::ClientsDropped), 1);
    assert_eq!(metrics.get(Counter::ClientsResynced), 0);
    // Its stream ends: what the socket buffers held, then the end.
    tokio::time::timeout(HANG_GUARD, async {
        while let Ok(Some(_)) = stalled.next_message().await {}
    })
    .await
    .expect("the stalled client's connection stayed open");

    // Its slot went to the next viewer, which gets the model.
    wait_for("the slot is returned", || {
        metrics.clients.load(Ordering::Relaxed) == 0
    })
    .await;
    tokio::time::timeout(HANG_GUARD, session.sources_done.cancelled())
        .await
        .unwrap();
    let mut next = Client::connect(addr, "", "next").await.unwrap();
    assert_eq!(read_snapshot(&mut next).await, 60);
    assert_eq!(metrics.get(Counter::ClientsWriteTimeouts), 1);
    shutdown.cancel();
    session.wait().await.unwrap();
}

/// A server on 127.0.0.1:0 with an empty model.
struct Server {
    addr: SocketAddr,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<()>,
    hub: Arc<Hub>,
}

async fn start_server(tune: impl FnOnce(&mut ServeOptions)) -> Server {
    let mut serve = SessionConfig::default().serve;
    serve.handshake_timeout_ms = 60_000;
    let mut options = ServeOptions::from_config(&serve, "test");
    tune(&mut options);
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let hub = Hub::new(16);
    let metrics = Metrics::new();
    let shutdown = CancellationToken::new();
    let task = tokio::spawn(server::run(
        listener,
        Arc::clone(&hub),
        options,
        Arc::clone(&metrics),
        shutdown.clone(),
    ));
    Server {
        addr,
        metrics,
        shutdown,
        task,
        hub,
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

    fn pending(&self) -> u64 {
        self.metrics
            .snapshot()
            .queues
            .iter()
            .find(|q| q.name == "pending_handshakes")
            .map(|q| q.depth)
            .unwrap()
    }
}

/// A silent connection from `from` (any 127.x.y.z address is loopback on Linux).
async fn connect_from(from: &str, to: SocketAddr) -> TcpStream {
    let socket = TcpSocket::new_v4().unwrap();
    socket.bind(format!("{from}:0").parse().unwrap()).unwrap();
    socket.connect(to).await.unwrap()
}

/// What the server says before closing a connection.
async fn refusal(stream: &mut TcpStream) -> String {
    let mut answer = Vec::new();
    tokio::time::timeout(HANG_GUARD, stream.read_to_end(&mut answer))
        .await
        .expect("the server kept the connection open")
        .unwrap();
    match decode_frame(&answer, &Limits::FROM_SERVER).unwrap() {
        Some((Message::Refused { reason }, _)) => reason,
        other => panic!("expected a refusal, got {other:?}"),
    }
}

/// Sends a hello on a pending connection and expects the welcome and a snapshot.
async fn complete_handshake(stream: &mut TcpStream) {
    complete_handshake_with(stream, "").await;
}

async fn complete_handshake_with(stream: &mut TcpStream, token: &str) {
    let hello = texel_client::hello(token, "late").unwrap();
    stream.write_all(&hello).await.unwrap();
    let mut buf = Vec::new();
    let mut kinds = Vec::new();
    tokio::time::timeout(HANG_GUARD, async {
        while !matches!(kinds.last(), Some(Message::SnapshotComplete { .. })) {
            let mut chunk = [0u8; 4096];
            let n = stream.read(&mut chunk).await.unwrap();
            assert!(n > 0, "closed after {kinds:?}");
            buf.extend_from_slice(&chunk[..n]);
            while let Some((m, used)) = decode_frame(&buf, &Limits::FROM_SERVER).unwrap() {
                buf.drain(..used);
                kinds.push(m);
            }
        }
    })
    .await
    .expect("no snapshot");
    assert!(matches!(kinds.first(), Some(Message::ServerHello { .. })));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pending_handshakes_are_bounded_per_address_and_in_total() {
    let server = start_server(|o| {
        o.max_pending_handshakes = 3;
        o.max_pending_handshakes_per_address = 2;
    })
    .await;
    let addr = server.addr;
    let m = &server.metrics;

    // A third connection from one address evicts that address's oldest.
    let mut a = connect_from("127.0.0.1", addr).await;
    let mut b = connect_from("127.0.0.1", addr).await;
    let mut c = connect_from("127.0.0.1", addr).await;
    let r = refusal(&mut a).await;
    assert!(
        r.contains("too many pending handshakes from your address"),
        "{r}"
    );
    assert_eq!(m.get(Counter::HandshakesEvicted), 1);
    wait_for("two pending", || server.pending() == 2).await;

    // Another address still gets a place, and takes nobody's.
    let mut x = connect_from("127.0.0.2", addr).await;
    wait_for("three pending", || server.pending() == 3).await;
    assert_eq!(m.get(Counter::HandshakesEvicted), 1);

    // With every place taken, a newcomer from a third address evicts the oldest
    // handshake of the most crowded address (b), not x.
    let mut y = connect_from("127.0.0.3", addr).await;
    let r = refusal(&mut b).await;
    assert!(r.contains("pending handshakes"), "{r}");
    assert_eq!(m.get(Counter::HandshakesEvicted), 2);
    assert_eq!(server.pending(), 3);

    // The survivors were left alone: each completes its handshake.
    for s in [&mut c, &mut x, &mut y] {
        complete_handshake(s).await;
    }
    assert_eq!(server.metrics.clients.load(Ordering::Relaxed), 3);
    assert_eq!(server.pending(), 0);
    assert_eq!(m.get(Counter::HandshakeTimeouts), 0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_connection_is_closed_after_the_handshake_timeout() {
    let server = start_server(|o| o.handshake_timeout = Duration::from_millis(200)).await;
    let mut silent = connect_from("127.0.0.1", server.addr).await;
    let r = refusal(&mut silent).await;
    assert_eq!(r, "no hello within 200 ms");
    assert_eq!(server.metrics.get(Counter::HandshakeTimeouts), 1);
    assert_eq!(server.metrics.get(Counter::ClientsRefused), 0);
    assert_eq!(server.pending(), 0);
    server.stop().await;
}

fn config_error(text: &str) -> String {
    let base = "[[source.replay]]\ncapture = \"c.mcap\"\n";
    let text = format!("{base}{text}");
    match SessionConfig::from_toml_str(&text, "s.toml").and_then(|c| c.validate("s.toml")) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn serve_limits_have_defaults_and_bad_values_are_named() {
    let d = SessionConfig::default().serve;
    assert_eq!(d.handshake_timeout_ms, 2000);
    assert_eq!(d.max_pending_handshakes, 64);
    assert_eq!(d.max_pending_handshakes_per_address, 8);
    assert_eq!(d.write_timeout_ms, 10_000);
    assert_eq!(d.max_requests_in_flight, 64);

    let c = SessionConfig::from_toml_str(
        "[serve]\nhandshake_timeout_ms = 700\nmax_pending_handshakes = 10\n\
         max_pending_handshakes_per_address = 3\nwrite_timeout_ms = 1500\n",
        "s.toml",
    )
    .unwrap();
    assert_eq!(
        (
            c.serve.handshake_timeout_ms,
            c.serve.max_pending_handshakes,
            c.serve.max_pending_handshakes_per_address,
            c.serve.write_timeout_ms
        ),
        (700, 10, 3, 1500)
    );

    let e = config_error("[serve]\nmax_pending = 3\n");
    assert!(e.contains("serve") && e.contains("max_pending"), "{e}");
    for (text, key) in [
        ("handshake_timeout_ms = 0", "serve.handshake_timeout_ms"),
        (
            "handshake_timeout_ms = 600000",
            "serve.handshake_timeout_ms",
        ),
        ("write_timeout_ms = 0", "serve.write_timeout_ms"),
        ("max_requests_in_flight = 0", "serve.max_requests_in_flight"),
        (
            "max_requests_in_flight = 5000",
            "serve.max_requests_in_flight",
        ),
        ("max_pending_handshakes = 0", "serve.max_pending_handshakes"),
        (
            "max_pending_handshakes_per_address = 0",
            "serve.max_pending_handshakes_per_address",
        ),
        (
            "max_pending_handshakes = 4\nmax_pending_handshakes_per_address = 5",
            "serve.max_pending_handshakes_per_address",
        ),
    ] {
        let e = config_error(&format!("[serve]\n{text}\n"));
        assert!(e.contains(&format!("{key}:")), "{text}: {e}");
    }
}
