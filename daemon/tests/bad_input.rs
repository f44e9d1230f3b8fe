//! Bad input gets a clear error and no panic: session files with unknown keys or bad
//! values, a missing camera and device nodes that are not cameras, wrong tokens,
//! oversize and garbage protocol frames, too many viewers.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use texel::capture::PoseTopic;
use texel::wire::{Limits, Message, decode_frame};
use texel_client::{Client, ClientError};
use texel_daemon::config::{RegistrationMode, ReplayConfig, SessionConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::source::v4l::{V4lError, V4lSource};
use texel_daemon::source::v4l_convert::PixelFormat;
use texel_daemon::status::Counter;
use texel_e2e::captures;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_util::sync::CancellationToken;

fn parse_error(text: &str) -> String {
    match SessionConfig::from_toml_str(text, "bad.toml") {
        Ok(c) => c.validate("bad.toml").unwrap_err().to_string(),
        Err(e) => e.to_string(),
    }
}

#[test]
fn config_errors_name_the_file_and_the_key_path() {
    let e = parse_error("[[source.replay]]\ncapture = \"x.mcap\"\nsped = 2.0\n");
    assert!(
        e.contains("bad.toml") && e.contains("source.replay[0]") && e.contains("sped"),
        "{e}"
    );
    let e = parse_error("[serve]\nbindd = \"127.0.0.1:1\"\n");
    assert!(e.contains("serve") && e.contains("bindd"), "{e}");
    let e = parse_error("[pipeline.fuse]\nmax_incidence = 3\n");
    assert!(
        e.contains("pipeline.fuse") && e.contains("max_incidence"),
        "{e}"
    );
    let e = parse_error("[serve]\nmax_clients = \"many\"\n");
    assert!(e.contains("serve.max_clients"), "{e}");
    let e = parse_error("[pipeline]\noverload = \"drop-everything\"\n");
    assert!(e.contains("pipeline.overload"), "{e}");
    let e = parse_error("[[source.replay]]\ncapture = \"x.mcap\"\nspeed = -1.0\n");
    assert!(e.contains("source.replay[0].speed"), "{e}");
    let e =
        parse_error("[[source.replay]]\ncapture = \"x.mcap\"\n[serve]\nbind = \"0.0.0.0:7878\"\n");
    assert!(
        e.contains("serve.token") && e.contains("0.0.0.0:7878"),
        "{e}"
    );
    let e = parse_error("[[source.serial]]\npath = \"/dev/ttyACM0\"\n");
    assert!(e.contains("session.sensor"), "{e}");
    let e = parse_error("[[source.v4l]]\nformat = \"H264\"\n[session]\nsensor = \"s.toml\"\n");
    assert!(
        e.contains("source.v4l[0].format") && e.contains("H264"),
        "{e}"
    );
    let e = parse_error("");
    assert!(e.contains("no source"), "{e}");
    let e = parse_error("[record]\nflush_interval_ms = 5000\n[[source.replay]]\ncapture = \"x\"\n");
    assert!(e.contains("record.flush_interval_ms"), "{e}");
    assert!(parse_error("[session\n").contains("bad.toml"));
}

#[test]
fn texeld_run_refuses_a_bad_config_with_exit_code_2() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.toml");
    std::fs::write(&file, "[status]\ninterval_ms = 100\nverbose = true\n").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(["run", "--config"])
        .arg(&file)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("status") && stderr.contains("verbose"),
        "{stderr}"
    );
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(["run", "--config", "/nonexistent/session.toml"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/session.toml"));
}

#[test]
fn the_session_files_in_the_repository_are_valid() {
    let dir = texel_e2e::repo_root().join("configs").join("sessions");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let c = SessionConfig::load(&path).unwrap();
            c.validate(&path.display().to_string()).unwrap();
            seen += 1;
        }
    }
    assert!(seen >= 2, "replay.toml and live.toml");
}

fn camera(device: &str, format: PixelFormat) -> V4lSource {
    V4lSource {
        name: "eo".into(),
        device: device.into(),
        format,
        width: 640,
        height: 480,
        fps: 30,
        dequeue_timeout: Duration::from_millis(500),
        buffers: 4,
    }
}

#[test]
fn cameras_that_are_missing_or_not_cameras_are_named() {
    match camera("/dev/video-texel-missing", PixelFormat::Yuyv).open() {
        Err(e @ V4lError::Missing { .. }) => {
            assert!(e.to_string().contains("/dev/video-texel-missing"), "{e}");
        }
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("a missing device opened"),
    }
    // Real device nodes and files that are not V4L2 devices.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("not-a-camera");
    std::fs::write(&file, b"frames?").unwrap();
    for path in [
        Path::new("/dev/null"),
        Path::new("/dev/zero"),
        file.as_path(),
    ] {
        let p = path.to_str().unwrap();
        match camera(p, PixelFormat::Mjpeg).open() {
            Err(e @ V4lError::NotACamera { .. }) => {
                let text = e.to_string();
                assert!(
                    text.contains(p) && text.contains("not a V4L2 camera"),
                    "{text}"
                );
            }
            Err(e) => panic!("{p}: {e}"),
            Ok(_) => panic!("{p} opened as a camera"),
        }
    }
}

async fn serving_session(token: Option<&str>, max_clients: usize) -> (Session, CancellationToken) {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("c.mcap");
    captures::write(&capture, 2, 10_000_000, Some(PoseTopic::Truth));
    let mut c = SessionConfig::default();
    // Every scan served: what this test follows is the stream, not retirement
    // (the synthetic frames overlap so much that most would retire).
    c.model.retirement.enabled = false;
    c.source.replay = vec![ReplayConfig {
        name: "replay".into(),
        capture,
        speed: 1.0,
        fast: true,
    }];
    c.pipeline.registration = RegistrationMode::CapturePoses;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.serve.token = token.map(str::to_string);
    c.serve.max_clients = max_clients;
    c.serve.handshake_timeout_ms = 500;
    c.status.log = false;
    c.validate("test").unwrap();
    let shutdown = CancellationToken::new();
    let session = Session::start(c, shutdown.clone()).await.unwrap();
    // The capture was read at start; the directory may go.
    tokio::time::timeout(Duration::from_secs(5), session.sources_done.cancelled())
        .await
        .unwrap();
    (session, shutdown)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_token_is_refused_and_the_right_one_admitted() {
    let token = "correct horse battery staple";
    let (session, shutdown) = serving_session(Some(token), 4).await;
    let addr = session.local_addr.unwrap();
    for wrong in [
        "",
        "correct horse battery stapl",
        "correct horse battery staplf",
    ] {
        match Client::connect(addr, wrong, "intruder").await {
            Err(ClientError::Refused(reason)) => assert_eq!(reason, "wrong token"),
            Err(e) => panic!("{e}"),
            Ok(_) => panic!("token {wrong:?} admitted"),
        }
    }
    assert_eq!(session.metrics.get(Counter::ClientsRefused), 3);
    let ok = Client::connect(addr, token, "viewer").await.unwrap();
    assert_eq!(ok.server.version, texel::wire::PROTOCOL_VERSION);
    shutdown.cancel();
    session.wait().await.unwrap();
}

/// Sends raw bytes as a client and returns what the server answers before closing.
async fn raw_exchange(addr: std::net::SocketAddr, bytes: &[u8]) -> Option<Message> {
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(bytes).await.unwrap();
    let mut buf = Vec::new();
    tokio::time::timeout(Duration::from_secs(3), s.read_to_end(&mut buf))
        .await
        .expect("the server kept a hostile connection open")
        .ok()?;
    decode_frame(&buf, &Limits::FROM_SERVER)
        .unwrap()
        .map(|(m, _)| m)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_clients_are_refused_with_a_reason_and_the_server_carries_on() {
    let (session, shutdown) = serving_session(None, 2).await;
    let addr = session.local_addr.unwrap();
    let refused = |m: Option<Message>| match m {
        Some(Message::Refused { reason }) => reason,
        other => panic!("expected a refusal, got {other:?}"),
    };
    // A frame claiming 4 GB.
    let r = refused(raw_exchange(addr, &u32::MAX.to_le_bytes()).await);
    assert!(r.contains("frame length 4294967295"), "{r}");
    // Another protocol (HTTP is the browser viewer's: `web_serve`).
    let r = refused(raw_exchange(addr, b"SSH-2.0-OpenSSH_9.6\r\n").await);
    assert!(r.contains("frame length"), "{r}");
    // A hello whose token length claims far more than the frame holds.
    let mut hello = vec![0u8; 4];
    hello.push(0x01);
    hello.extend_from_slice(b"TXLV");
    hello.extend_from_slice(&1u16.to_le_bytes());
    hello.extend_from_slice(&0x4000_0000u32.to_le_bytes());
    let len = (hello.len() - 4) as u32;
    hello[..4].copy_from_slice(&len.to_le_bytes());
    let r = refused(raw_exchange(addr, &hello).await);
    assert!(r.contains("token"), "{r}");
    // A newer protocol version.
    let v9 = Message::ClientHello {
        version: 9,
        token: String::new(),
        client_name: "future".into(),
    }
    .encode()
    .unwrap();
    let r = refused(raw_exchange(addr, &v9).await);
    assert!(r.contains("version 9"), "{r}");
    // Silence: refused when the handshake times out.
    let r = refused(raw_exchange(addr, b"").await);
    assert!(r.contains("no hello"), "{r}");
    // Too many viewers: the third is refused while two are connected.
    let a = Client::connect(addr, "", "a").await.unwrap();
    let b = Client::connect(addr, "", "b").await.unwrap();
    match Client::connect(addr, "", "c").await {
        Err(ClientError::Refused(reason)) => assert!(reason.contains("server full"), "{reason}"),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("a third client was admitted"),
    }
    drop((a, b));
    // The server still serves.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let mut c = Client::connect(addr, "", "after").await.unwrap();
    assert!(matches!(
        c.next_message().await.unwrap(),
        Some(Message::ModelReset { scan_count: 2 })
    ));
    shutdown.cancel();
    session.wait().await.unwrap();
}
