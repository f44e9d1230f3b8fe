//! The daemon as a real child process: `kill -9` during recording loses at most a
//! second and the file replays; SIGTERM stops sources, drains, finalises the
//! recording, tells clients and exits 0 within 2 s; wrong tokens are logged.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use texel::capture::{CaptureError, CaptureEvent, CaptureReader, PoseTopic};
use texel::wire::Message;
use texel_client::{BlockingClient, ClientError};
use texel_e2e::captures;

const PERIOD_NS: u64 = 50_000_000;

/// Starts `texeld` with stderr forwarded line by line to a channel.
fn spawn(args: &[&std::ffi::OsStr]) -> (Child, mpsc::Receiver<String>) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(args)
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    (child, rx)
}

/// Waits for a stderr line containing `needle`; returns it.
fn wait_line(rx: &mpsc::Receiver<String>, needle: &str, log: &mut Vec<String>) -> String {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let line = rx
            .recv_timeout(left)
            .unwrap_or_else(|_| panic!("no line with {needle:?}; got:\n{}", log.join("\n")));
        log.push(line.clone());
        if line.contains(needle) {
            return line;
        }
    }
}

/// Range frame timestamps in a capture, and the error it ends with, if any.
fn recorded_ranges(path: &Path) -> (Vec<u64>, Option<CaptureError>) {
    let mut times = Vec::new();
    for event in CaptureReader::open(path).unwrap() {
        match event {
            Ok(CaptureEvent::Range(f)) => times.push(f.timestamp_ns),
            Ok(_) => {}
            Err(e) => return (times, Some(e)),
        }
    }
    (times, None)
}

#[test]
fn kill_9_while_recording_loses_at_most_a_second_and_the_file_replays() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("walk.mcap");
    let out = dir.path().join("recorded.mcap");
    // 8 s of frames at 20 Hz, replayed at real time; killed after about 2.5 s.
    captures::write(&capture, 160, PERIOD_NS, Some(PoseTopic::Truth));
    let (mut child, rx) = spawn(&[
        "replay".as_ref(),
        capture.as_os_str(),
        "--speed".as_ref(),
        "1".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
        "--no-serve".as_ref(),
        "--capture-poses".as_ref(),
    ]);
    let mut log = Vec::new();
    // The replay clock starts at this line (the first frame is due right after).
    wait_line(&rx, "replay started", &mut log);
    let started = Instant::now();
    std::thread::sleep(Duration::from_millis(2500));
    child.kill().unwrap(); // SIGKILL
    let alive_s = started.elapsed().as_secs_f64();
    child.wait().unwrap();

    let (times, error) = recorded_ranges(&out);
    // Everything due more than a second before the kill is in the file.
    let t0 = captures::timestamp(0, PERIOD_NS);
    let must_have = ((alive_s - 1.0) / (PERIOD_NS as f64 * 1e-9)).floor() as usize;
    assert!(
        times.len() >= must_have,
        "{} frames recorded, {must_have} were due more than 1 s before the kill",
        times.len()
    );
    // And nothing from the future.
    let could_have = (alive_s / (PERIOD_NS as f64 * 1e-9)).ceil() as usize + 1;
    assert!(times.len() <= could_have, "{} > {could_have}", times.len());
    for (i, t) in times.iter().enumerate() {
        assert_eq!(*t, t0 + i as u64 * PERIOD_NS, "frame {i}");
    }
    // The file ends without its summary: a truncated recording (not a corrupt one),
    // said after the frames.
    if let Some(e) = &error {
        assert!(
            matches!(e, CaptureError::Truncated { .. }) && e.to_string().contains("recorded.mcap"),
            "{e}"
        );
    }

    // The cut file replays: every recorded frame with its recorded pose is placed.
    let replayed = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .arg("replay")
        .arg(&out)
        .args(["--fast", "--no-serve", "--capture-poses"])
        .output()
        .unwrap();
    assert!(
        replayed.status.success(),
        "{}",
        String::from_utf8_lossy(&replayed.stderr)
    );
    let stdout = String::from_utf8_lossy(&replayed.stdout);
    let scans: usize = stdout
        .split_whitespace()
        .nth(1)
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{stdout}"));
    // The pose of the last frame or two may have been cut with the file.
    assert!(
        scans + 2 >= times.len() && scans <= times.len(),
        "{scans} scans from {} frames",
        times.len()
    );
}

fn wait_exit(child: &mut Child, within: Duration) -> Option<std::process::ExitStatus> {
    let start = Instant::now();
    while start.elapsed() < within {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    None
}

#[test]
fn sigterm_drains_finalises_the_recording_tells_clients_and_exits_0_within_2_s() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("walk.mcap");
    let out = dir.path().join("session.mcap");
    captures::write(&capture, 400, PERIOD_NS, Some(PoseTopic::Texel));
    let session = dir.path().join("session.toml");
    let token = "sixteen-plus-bytes-of-token";
    std::fs::write(
        &session,
        format!(
            "[session]\nname = \"signal test\"\n\
             [[source.replay]]\ncapture = \"{}\"\nspeed = 1.0\n\
             [record]\npath = \"{}\"\n\
             [serve]\nbind = \"127.0.0.1:0\"\ntoken = \"{token}\"\n\
             [status]\ninterval_ms = 200\n",
            capture.display(),
            out.display()
        ),
    )
    .unwrap();
    let (mut child, rx) = spawn(&["run".as_ref(), "--config".as_ref(), session.as_os_str()]);
    let mut log = Vec::new();
    let line = wait_line(&rx, "serving viewers on ", &mut log);
    let addr: SocketAddr = line
        .rsplit("serving viewers on ")
        .next()
        .unwrap()
        .trim()
        .parse()
        .unwrap();

    // A wrong token is refused and logged.
    match BlockingClient::connect(addr, "guess", "intruder", Duration::from_secs(5)) {
        Err(ClientError::Refused(reason)) => assert_eq!(reason, "wrong token"),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("a wrong token was admitted"),
    }
    wait_line(&rx, "refused: wrong token", &mut log);

    let mut client =
        BlockingClient::connect(addr, token, "viewer", Duration::from_secs(5)).unwrap();
    assert_eq!(client.server.session_name, "signal test");
    let mut scans = 0;
    while scans < 5 {
        if let Some(Message::ScanAdded(_)) = client.next_message().unwrap() {
            scans += 1;
        }
    }

    let sent = Instant::now();
    let kill = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let status = wait_exit(&mut child, Duration::from_secs(2));
    let took = sent.elapsed();
    let Some(status) = status else {
        child.kill().unwrap();
        panic!("texeld did not exit within 2 s of SIGTERM");
    };
    assert!(status.success(), "exit status {status} after {took:?}");

    // The client was told why the stream ended.
    let reason = loop {
        match client.next_message().unwrap() {
            Some(Message::Goodbye { reason }) => break reason,
            Some(_) => {}
            None => panic!("closed without a goodbye"),
        }
    };
    assert!(reason.contains("shutting down"), "{reason}");

    // The recording is complete: it reads to its end without an error, and holds a
    // pose for every frame it recorded (the last range frame may have lost its EO
    // partner to the stop, and so have no pose).
    let (times, error) = recorded_ranges(&out);
    assert!(error.is_none(), "{error:?}");
    assert!(times.len() >= 5, "{} frames", times.len());
    let mut poses = 0;
    for event in CaptureReader::open(&out).unwrap() {
        if let Ok(CaptureEvent::Pose {
            topic: PoseTopic::Texel,
            ..
        }) = event
        {
            poses += 1;
        }
    }
    assert!(
        poses + 1 >= times.len() && poses <= times.len(),
        "{poses} poses for {} frames: the queued frames were drained and placed",
        times.len()
    );
}
