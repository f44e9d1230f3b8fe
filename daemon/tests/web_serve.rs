//! The browser viewer on the viewer port: its page's files over HTTP (plain names
//! only, the right types, a 503 page naming the build command when it is not built,
//! bounded request heads), and the viewer stream over WebSocket (`/ws`) with the same
//! messages, snapshot and token rule as a native TCP viewer, which is unchanged.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use texel::PinholeCamera;
use texel::capture::PoseTopic;
use texel::wire::{Limits, Message, TextureFormat, decode_frame};
use texel_client::{Client, FrameReader, hello, request};
use texel_daemon::config::{OverloadPolicy, RegistrationMode, ReplayConfig, SessionConfig};
use texel_daemon::hub::Hub;
use texel_daemon::pipeline::Session;
use texel_daemon::server::{self, ServeOptions};
use texel_daemon::status::{Counter, Metrics};
use texel_e2e::captures;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::{Error as WsError, Message as WsMessage};
use tokio_util::sync::CancellationToken;

/// Only a hang guard: nothing here is expected to take this long.
const HANG_GUARD: Duration = Duration::from_secs(60);
const TOKEN: &str = "a token of sixteen bytes or more";
const INDEX: &str = "<!doctype html><title>texel</title><script src=app.js></script>";
const WASM: &[u8] = b"\0asm\x01\0\0\0 not really a module";

/// A server on a bare hub (no pipeline): enough for HTTP.
async fn start_server(web_dir: Option<PathBuf>, web: bool) -> (SocketAddr, CancellationToken) {
    let serve = SessionConfig::default().serve;
    let mut options = ServeOptions::from_config(&serve, "test");
    options.web = web;
    options.web_dir = web_dir;
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let shutdown = CancellationToken::new();
    tokio::spawn(server::run(
        listener,
        Hub::new(16),
        options,
        Metrics::new(),
        shutdown.clone(),
    ));
    (addr, shutdown)
}

/// A web directory with the page, its script and a wasm file.
fn web_dir(root: &Path) -> PathBuf {
    let dir = root.join("web");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("index.html"), INDEX).unwrap();
    std::fs::write(dir.join("app.js"), "export default 1;").unwrap();
    std::fs::write(dir.join("viewer_bg.wasm"), WASM).unwrap();
    dir
}

/// An HTTP answer: status, head (lowercased) and body.
struct Answer {
    status: u16,
    head: String,
    body: Vec<u8>,
}

impl Answer {
    fn header(&self, name: &str) -> Option<&str> {
        self.head.lines().find_map(|l| {
            let (n, v) = l.split_once(':')?;
            (n.trim() == name).then(|| v.trim())
        })
    }
}

/// Sends `raw` and reads the answer to the end: the server closes after each one.
async fn exchange(addr: SocketAddr, raw: &[u8]) -> Answer {
    tokio::time::timeout(HANG_GUARD, async {
        let mut s = TcpStream::connect(addr).await.unwrap();
        s.write_all(raw).await.unwrap();
        let mut all = Vec::new();
        s.read_to_end(&mut all).await.unwrap();
        let at = all
            .windows(4)
            .position(|w| w == b"\r\n\r\n")
            .unwrap_or_else(|| panic!("no head in {:?}", String::from_utf8_lossy(&all)));
        let head = String::from_utf8_lossy(&all[..at]).to_lowercase();
        let status = head.split(' ').nth(1).unwrap().parse().unwrap();
        Answer {
            status,
            head,
            body: all[at + 4..].to_vec(),
        }
    })
    .await
    .expect("the server did not close after its answer")
}

async fn get(addr: SocketAddr, path: &str) -> Answer {
    let raw = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nUser-Agent: test\r\n\r\n");
    exchange(addr, raw.as_bytes()).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_and_its_files_are_served_with_their_types() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = web_dir(tmp.path());
    // A file outside the directory, and a link to it inside.
    std::fs::write(tmp.path().join("secret.txt"), "secret").unwrap();
    std::os::unix::fs::symlink(tmp.path().join("secret.txt"), dir.join("link.txt")).unwrap();
    std::fs::create_dir(dir.join("assets")).unwrap();
    std::fs::write(dir.join("assets").join("style.css"), "body{}").unwrap();
    let (addr, _stop) = start_server(Some(dir.clone()), true).await;

    for path in ["/", "/index.html", "/?mode=blended&pose=1,2,3"] {
        let a = get(addr, path).await;
        assert_eq!(a.status, 200, "{path}");
        assert_eq!(a.body, INDEX.as_bytes(), "{path}");
        assert_eq!(a.header("content-type"), Some("text/html; charset=utf-8"));
        assert_eq!(a.header("cache-control"), Some("no-cache"));
        assert_eq!(a.header("connection"), Some("close"));
        assert_eq!(a.header("content-length"), Some(&*INDEX.len().to_string()));
    }
    let wasm = get(addr, "/viewer_bg.wasm").await;
    assert_eq!((wasm.status, wasm.body.as_slice()), (200, WASM));
    assert_eq!(wasm.header("content-type"), Some("application/wasm"));
    let js = get(addr, "/app.js").await;
    assert_eq!(
        js.header("content-type"),
        Some("text/javascript; charset=utf-8")
    );
    let css = get(addr, "/assets/style.css").await;
    assert_eq!(
        (css.status, css.header("content-type")),
        (200, Some("text/css; charset=utf-8"))
    );

    // A browser holding the file asks with its entity tag and is sent no body; a
    // changed file has a new tag and is sent again.
    let tag = wasm.header("etag").unwrap().to_string();
    let revalidate = |tag: &str| {
        format!("GET /viewer_bg.wasm HTTP/1.1\r\nHost: x\r\nIf-None-Match: {tag}\r\n\r\n")
    };
    let again = exchange(addr, revalidate(&tag).as_bytes()).await;
    assert_eq!((again.status, again.body.len()), (304, 0));
    assert_eq!(again.header("etag"), Some(&*tag));
    let other = exchange(addr, revalidate("\"0-0\"").as_bytes()).await;
    assert_eq!((other.status, other.body.as_slice()), (200, WASM));
    let mut rebuilt = WASM.to_vec();
    rebuilt.push(0);
    std::fs::write(dir.join("viewer_bg.wasm"), &rebuilt).unwrap();
    let changed = exchange(addr, revalidate(&tag).as_bytes()).await;
    assert_eq!((changed.status, &changed.body), (200, &rebuilt));
    assert_ne!(changed.header("etag"), Some(&*tag));
    std::fs::write(dir.join("viewer_bg.wasm"), WASM).unwrap();

    // HEAD: the head alone.
    let head = exchange(addr, b"HEAD /viewer_bg.wasm HTTP/1.1\r\nHost: x\r\n\r\n").await;
    assert_eq!(head.status, 200);
    assert_eq!(
        head.header("content-length"),
        Some(&*WASM.len().to_string())
    );
    assert!(head.body.is_empty());

    // Nothing outside the directory, nothing but plain names.
    for path in [
        "/nope",
        "/../Cargo.toml",
        "/%2e%2e/Cargo.toml",
        "/assets/../index.html",
        "/link.txt",
        "/assets",
        "/assets/",
        "/.hidden",
        "//etc/passwd",
    ] {
        let a = get(addr, path).await;
        assert_eq!(a.status, 404, "{path}");
        assert!(!a.body.windows(6).any(|w| w == b"secret"), "{path}");
    }

    // Other methods, and /ws without an upgrade.
    let post = exchange(addr, b"POST / HTTP/1.1\r\nContent-Length: 0\r\n\r\n").await;
    assert_eq!(
        (post.status, post.header("allow")),
        (405, Some("get, head"))
    );
    let ws = get(addr, "/ws").await;
    assert_eq!(ws.status, 426);
    assert!(String::from_utf8_lossy(&ws.body).contains("WebSocket"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unbuilt_viewer_is_a_503_page_naming_the_build_command() {
    let tmp = tempfile::tempdir().unwrap();
    for dir in [
        Some(tmp.path().join("missing")),
        Some(tmp.path().to_path_buf()),
        None,
    ] {
        let (addr, _stop) = start_server(dir.clone(), true).await;
        let a = get(addr, "/").await;
        assert_eq!(a.status, 503, "{dir:?}");
        assert_eq!(a.header("content-type"), Some("text/html; charset=utf-8"));
        let page = String::from_utf8(a.body).unwrap();
        assert!(page.contains("not built"), "{page}");
        assert!(page.contains("bash scripts/build-web.sh"), "{page}");
        assert_eq!(get(addr, "/texel_viewer_web.js").await.status, 404);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_request_heads_are_refused_and_closed_and_tcp_viewers_are_unchanged() {
    let tmp = tempfile::tempdir().unwrap();
    let (addr, _stop) = start_server(Some(web_dir(tmp.path())), true).await;

    // A head over the bound: refused, and closed without reading it all.
    let huge = format!("GET / HTTP/1.1\r\nX-Big: {}\r\n\r\n", "a".repeat(20 * 1024));
    let a = exchange(addr, huge.as_bytes()).await;
    assert_eq!(a.status, 431);
    let many = format!("GET / HTTP/1.1\r\n{}\r\n", "A: b\r\n".repeat(200));
    assert_eq!(exchange(addr, many.as_bytes()).await.status, 431);
    // Malformed heads.
    for raw in [
        &b"GET / HTTP/1.1\r\nBad Header\r\n\r\n"[..],
        b"GET http://elsewhere/ HTTP/1.1\r\n\r\n",
        b"GET \x01\x02 HTTP/1.1\r\n\r\n",
    ] {
        assert_eq!(exchange(addr, raw).await.status, 400, "{raw:?}");
    }
    // A head that never ends is closed at the handshake timeout, like a silent hello.
    let mut silent = TcpStream::connect(addr).await.unwrap();
    silent
        .write_all(b"GET / HTTP/1.1\r\nHost: x\r\n")
        .await
        .unwrap();
    let mut rest = Vec::new();
    tokio::time::timeout(HANG_GUARD, silent.read_to_end(&mut rest))
        .await
        .expect("a partial head held its connection")
        .unwrap();
    assert!(
        rest.starts_with(b"HTTP/1.1 408"),
        "{:?}",
        String::from_utf8_lossy(&rest)
    );

    // A native viewer on the same port, unchanged.
    let mut client = Client::connect(addr, "", "native").await.unwrap();
    assert_eq!(client.server.session_name, "test");
    match client.next_message().await.unwrap() {
        Some(Message::ModelReset { .. }) => {}
        m => panic!("expected the snapshot, got {m:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_web_off_http_is_refused_as_an_invalid_hello() {
    let tmp = tempfile::tempdir().unwrap();
    let (addr, _stop) = start_server(Some(web_dir(tmp.path())), false).await;
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .unwrap();
    let mut answer = Vec::new();
    tokio::time::timeout(HANG_GUARD, s.read_to_end(&mut answer))
        .await
        .unwrap()
        .unwrap();
    match decode_frame(&answer, &Limits::FROM_SERVER) {
        Ok(Some((Message::Refused { reason }, _))) => {
            assert!(reason.contains("frame length"), "{reason}");
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
}

type Ws = WebSocketStream<TcpStream>;

/// Opens `/ws` with a real WebSocket client (`origin`: what a browser would send).
async fn ws_connect(addr: SocketAddr, origin: Option<&str>) -> Result<Ws, WsError> {
    let stream = TcpStream::connect(addr).await.unwrap();
    let mut request = format!("ws://{addr}/ws").into_client_request().unwrap();
    if let Some(origin) = origin {
        request
            .headers_mut()
            .insert("Origin", origin.parse().unwrap());
    }
    let (ws, response) = tokio_tungstenite::client_async(request, stream).await?;
    assert_eq!(response.status(), 101);
    Ok(ws)
}

/// The wire messages arriving over a WebSocket, whatever its message boundaries.
struct WsViewer {
    ws: Ws,
    frames: FrameReader,
}

impl WsViewer {
    async fn open(addr: SocketAddr, token: &str) -> Self {
        Self::hello(ws_connect(addr, None).await.unwrap(), token).await
    }

    /// Sends the wire hello over an open WebSocket, as the first message.
    async fn hello(mut ws: Ws, token: &str) -> Self {
        ws.send(WsMessage::Binary(hello(token, "browser").unwrap().into()))
            .await
            .unwrap();
        Self {
            ws,
            frames: FrameReader::default(),
        }
    }

    /// The next message; `None` once the server closed the WebSocket.
    async fn next(&mut self) -> Option<Message> {
        tokio::time::timeout(HANG_GUARD, async {
            loop {
                if let Some(m) = self.frames.take_message().unwrap() {
                    return Some(m);
                }
                match self.ws.next().await {
                    Some(Ok(WsMessage::Binary(b))) => self.frames.buf.extend_from_slice(&b),
                    Some(Ok(WsMessage::Close(_))) | None => return None,
                    Some(Ok(m)) => panic!("a non-binary message: {m:?}"),
                    Some(Err(e)) => panic!("websocket: {e}"),
                }
            }
        })
        .await
        .expect("the websocket stream stalled")
    }
}

/// A message reduced to what both transports must agree on: its kind and id.
fn summary(m: &Message) -> String {
    match m {
        Message::ScanListed { id, .. } => format!("ScanListed {id}"),
        Message::ScanAdded(scan) => format!("ScanAdded {}", scan.id),
        Message::ServerHello { version, .. } => format!("ServerHello {version}"),
        m => m.kind_name().to_string(),
    }
}

/// The messages up to the end of the snapshot, statuses aside (they are periodic).
async fn snapshot(mut next: impl AsyncFnMut() -> Option<Message>) -> Vec<String> {
    let mut seen = Vec::new();
    loop {
        match next().await {
            Some(Message::Status(_)) => {}
            Some(m) => {
                let done = matches!(m, Message::SnapshotComplete { .. });
                seen.push(summary(&m));
                if done {
                    return seen;
                }
            }
            None => panic!("closed before the snapshot was complete: {seen:?}"),
        }
    }
}

fn replay_session(capture: &Path) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.model.retirement.enabled = false;
    c.source.replay = vec![ReplayConfig {
        name: "replay".into(),
        capture: capture.to_path_buf(),
        speed: 1.0,
        fast: true,
    }];
    c.pipeline.registration = RegistrationMode::CapturePoses;
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.status.log = false;
    c
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_websocket_viewer_gets_the_same_stream_as_a_tcp_viewer() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("c.mcap");
    captures::write(&capture, 3, 10_000_000, Some(PoseTopic::Truth));
    let mut config = replay_session(&capture);
    config.serve.web_dir = Some(tmp.path().join("no-page"));
    let session = Session::start(config, CancellationToken::new())
        .await
        .unwrap();
    let addr = session.local_addr.unwrap();
    tokio::time::timeout(HANG_GUARD, session.sources_done.cancelled())
        .await
        .unwrap();
    // The model is stable once every listed scan has been placed.
    let deadline = Instant::now() + HANG_GUARD;
    while session.hub.status().scans < 3 {
        assert!(
            Instant::now() < deadline,
            "the replay never placed its scans"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    let mut tcp = Client::connect(addr, "", "native").await.unwrap();
    tcp.set_max_in_flight(0);
    let mut from_tcp = vec![format!("ServerHello {}", tcp.server.version)];
    from_tcp.extend(snapshot(async || tcp.next_message().await.unwrap()).await);

    let mut browser = WsViewer::open(addr, "").await;
    let from_ws = snapshot(async || browser.next().await).await;
    eprintln!("over WebSocket as over TCP: {from_ws:?}");
    assert_eq!(from_ws, from_tcp);
    let listed: Vec<u64> = from_ws
        .iter()
        .filter_map(|s| s.strip_prefix("ScanListed ")?.parse().ok())
        .collect();
    assert_eq!(listed.len(), 3, "{from_ws:?}");
    // Both count as viewers.
    assert_eq!(session.metrics.clients.load(Ordering::Relaxed), 2);

    // Requests travel the other way: the scan's data comes back as over TCP.
    let id = listed[0];
    let ask = request(id).unwrap();
    browser
        .ws
        .send(WsMessage::Binary(ask.into()))
        .await
        .unwrap();
    loop {
        match browser.next().await {
            Some(Message::ScanAdded(scan)) => {
                assert_eq!(scan.id, id);
                break;
            }
            Some(Message::ScanUnavailable { reason, .. }) => panic!("unavailable: {reason}"),
            Some(_) => {}
            None => panic!("closed before the scan arrived"),
        }
    }

    // A text message is not the protocol: the connection is closed and its slot freed.
    browser
        .ws
        .send(WsMessage::Text("hello?".into()))
        .await
        .unwrap();
    let close = tokio::time::timeout(HANG_GUARD, async {
        loop {
            match browser.ws.next().await {
                Some(Ok(WsMessage::Close(frame))) => return frame,
                Some(Ok(_)) => {}
                other => panic!("no close frame: {other:?}"),
            }
        }
    })
    .await
    .expect("the connection stayed open after a text message");
    assert_eq!(close.map(|f| f.code), Some(CloseCode::Unsupported));
    tcp.close().await;
    let deadline = Instant::now() + HANG_GUARD;
    while session.metrics.clients.load(Ordering::Relaxed) != 0 {
        assert!(Instant::now() < deadline, "a viewer slot was never freed");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
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
async fn a_websocket_viewer_that_never_reads_is_dropped_and_its_slot_returns() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("big.mcap");
    // 60 frames with raw 320x240 textures: about 14 MB of live scans, more than the
    // bridge's pipe and the socket buffers hold.
    let mut sensor = captures::sensor();
    sensor.eo = PinholeCamera::from_vertical_fov(320, 240, 40.0).unwrap();
    captures::write_with(&capture, &sensor, 60, 10_000_000, Some(PoseTopic::Truth));
    let mut config = replay_session(&capture);
    config.source.replay[0].fast = false;
    config.serve.texture = TextureFormat::Rgb8;
    config.serve.max_clients = 1;
    // Room for the whole stream: only the write timeout can drop the stalled viewer.
    config.serve.client_queue = 256;
    config.serve.write_timeout_ms = 500;
    config.validate("test").unwrap();
    let session = Session::start(config, CancellationToken::new())
        .await
        .unwrap();
    let addr = session.local_addr.unwrap();
    let metrics = Arc::clone(&session.metrics);

    // Says hello, then reads nothing.
    let stalled = WsViewer::open(addr, "").await;
    wait_for("the stalled viewer is dropped", || {
        metrics.get(Counter::ClientsWriteTimeouts) == 1
    })
    .await;
    assert_eq!(metrics.get(Counter::ClientsDropped), 1);
    wait_for("its slot returns", || {
        metrics.clients.load(Ordering::Relaxed) == 0
    })
    .await;
    drop(stalled);
    tokio::time::timeout(HANG_GUARD, session.sources_done.cancelled())
        .await
        .unwrap();
    let mut next = WsViewer::open(addr, "").await;
    let seen = snapshot(async || next.next().await).await;
    let listed = seen.iter().filter(|s| s.starts_with("ScanListed")).count();
    assert_eq!(listed, 60);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_token_rule_is_the_same_over_websocket() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("c.mcap");
    captures::write(&capture, 2, 10_000_000, Some(PoseTopic::Truth));
    let mut config = replay_session(&capture);
    config.serve.bind = "0.0.0.0:0".parse().unwrap();
    config.serve.token = Some(TOKEN.into());
    config.validate("test").unwrap();
    let session = Session::start(config, CancellationToken::new())
        .await
        .unwrap();
    let port = session.local_addr.unwrap().port();
    let addr = SocketAddr::from(([127, 0, 0, 1], port));
    tokio::time::timeout(HANG_GUARD, session.sources_done.cancelled())
        .await
        .unwrap();

    // A wrong token, or none: refused by name, no snapshot, and no slot.
    for wrong in ["guess", ""] {
        let mut intruder = WsViewer::open(addr, wrong).await;
        match intruder.next().await {
            Some(Message::Refused { reason }) => assert_eq!(reason, "wrong token"),
            m => panic!("expected a refusal, got {m:?}"),
        }
        assert!(intruder.next().await.is_none(), "more after the refusal");
    }
    assert_eq!(session.metrics.clients.load(Ordering::Relaxed), 0);

    // The token in the URL counts for nothing: only the hello carries it.
    let stream = TcpStream::connect(addr).await.unwrap();
    let url = format!("ws://{addr}/ws?token={}", TOKEN.replace(' ', "%20"));
    let (ws, _) = tokio_tungstenite::client_async(url, stream).await.unwrap();
    let mut by_url = WsViewer::hello(ws, "").await;
    assert!(matches!(by_url.next().await, Some(Message::Refused { .. })));

    // With the token, from any page (the token decides): admitted, with the snapshot.
    let ws = ws_connect(addr, Some("http://elsewhere.example"))
        .await
        .unwrap();
    let mut viewer = WsViewer::hello(ws, TOKEN).await;
    match viewer.next().await {
        Some(Message::ServerHello { .. }) => {}
        m => panic!("expected the welcome, got {m:?}"),
    }
    let seen = snapshot(async || viewer.next().await).await;
    assert_eq!(seen.first().map(String::as_str), Some("ModelReset"));
    assert_eq!(session.metrics.clients.load(Ordering::Relaxed), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_token_only_the_daemons_own_page_opens_the_stream() {
    let (addr, _stop) = start_server(None, true).await;
    let own = format!("http://{addr}");
    let ws = ws_connect(addr, Some(&own)).await.unwrap();
    let mut own_page = WsViewer::hello(ws, "").await;
    assert!(matches!(
        own_page.next().await,
        Some(Message::ServerHello { .. })
    ));
    match ws_connect(addr, Some("http://elsewhere.example")).await {
        Err(WsError::Http(response)) => assert_eq!(response.status(), 403),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("another site's page opened the stream"),
    }
}

/// `texeld` logs the page's address with its real port, and warns when the page is
/// not built; `TEXEL_WEB_DIR` says where it is.
#[test]
fn the_daemon_logs_the_page_address_and_serves_the_built_page() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("c.mcap");
    captures::write(&capture, 2, 10_000_000, Some(PoseTopic::Truth));
    let built = web_dir(tmp.path());
    for (dir, is_built) in [(built, true), (tmp.path().join("unbuilt"), false)] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_texeld"))
            .args(["replay".as_ref(), capture.as_os_str()])
            .args(["--bind", "127.0.0.1:0", "--stay"])
            .env("RUST_LOG", "info")
            .env("TEXEL_WEB_DIR", &dir)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let stderr = child.stderr.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut log = Vec::new();
        let mut wait_line = |needle: &str| -> String {
            let deadline = Instant::now() + HANG_GUARD;
            loop {
                let left = deadline.saturating_duration_since(Instant::now());
                let Ok(line) = rx.recv_timeout(left) else {
                    panic!("no line with {needle:?}:\n{}", log.join("\n"));
                };
                log.push(line.clone());
                if line.contains(needle) {
                    return line;
                }
            }
        };
        let serving = wait_line("serving viewers on ");
        let serving = serving.rsplit("serving viewers on ").next().unwrap().trim();
        let url = wait_line("field display: ");
        let url = url.rsplit("field display: ").next().unwrap().trim();
        assert_eq!(url, format!("http://{serving}/"));
        if !is_built {
            let warning = wait_line("browser viewer is not built");
            assert!(warning.contains("bash scripts/build-web.sh"), "{warning}");
            assert!(warning.contains(&*dir.display().to_string()), "{warning}");
        }
        let addr: SocketAddr = serving.parse().unwrap();
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let answer = rt.block_on(get(addr, "/"));
        assert_eq!(answer.status, if is_built { 200 } else { 503 });
        child.kill().unwrap();
        child.wait().unwrap();
    }
}
