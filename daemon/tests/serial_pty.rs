//! The serial source on real pseudo-terminal pairs: a writer thread sends TXL1 frames
//! with injected garbage, a CRC error, a bad header, dropped sequence numbers, a stall
//! and a disconnect after which the device reappears under another name matched by
//! the configured glob. Every valid frame is received and recorded, and the counters
//! equal what was injected. A hostile flood (a bogus header claiming the largest frame,
//! its span full of false magics) neither loses the frames after it nor keeps the
//! source from reporting a stall or stopping at shutdown.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};
use std::io::{Read, Write};
use texel::capture::{CaptureEvent, CaptureReader, PoseTopic};
use texel::txl1::{HEADER_LEN, MAGIC, MAX_FRAME_LEN, MAX_SIDE, Txl1Frame};
use texel_daemon::config::{SerialConfig, SessionConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::source::{SourceMetrics, SourceState};
use texel_e2e::captures;
use tokio_util::sync::CancellationToken;

const PERIOD_NS: u64 = 33_000_000;

fn frame(seq: u32) -> Txl1Frame {
    Txl1Frame {
        // The size of the session's lidar (captures::sensor()).
        width: 16,
        height: 12,
        seq,
        timestamp_ns: 5_000_000_000 + u64::from(seq) * PERIOD_NS,
        range_unit_um: 1000,
        ranges: (0..192).map(|i| 1500 + i * 10 + seq as u16).collect(),
        intensities: None,
    }
}

/// Polls until `f` holds (the daemon runs concurrently); fails after 10 s.
fn wait_until(what: &str, mut f: impl FnMut() -> bool) {
    let start = Instant::now();
    while !f() {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "timed out: {what}"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

fn received(m: &SourceMetrics) -> u64 {
    m.range_frames.load(std::sync::atomic::Ordering::Relaxed)
}

/// A pty pair whose slave is reachable as `link`.
fn device(link: &Path) -> (TTYPort, TTYPort) {
    let (master, slave) = TTYPort::pair().unwrap();
    let name = slave.name().unwrap();
    std::os::unix::fs::symlink(name, link).unwrap();
    (master, slave)
}

fn session_config(dir: &Path, glob: String, record: PathBuf) -> SessionConfig {
    let sensor = dir.join("sensor.toml");
    std::fs::write(&sensor, captures::sensor().to_toml_string()).unwrap();
    let poses = dir.join("poses.mcap");
    captures::write(&poses, 0, PERIOD_NS, Some(PoseTopic::Truth));
    let mut c = SessionConfig::default();
    c.session.sensor = Some(sensor);
    c.pipeline.pose_capture = Some(poses);
    c.source.serial = vec![SerialConfig {
        name: "lidar".into(),
        path: glob,
        baud: 115_200,
        stall_timeout_ms: 300,
        reopen_backoff_min_ms: 50,
        reopen_backoff_max_ms: 400,
    }];
    c.serve.enabled = false;
    c.record.path = Some(record);
    c.status.log = false;
    c.validate("test").unwrap();
    c
}

/// What the writer injected.
#[derive(Debug, Default)]
struct Injected {
    valid: Vec<u32>,
    garbage_bytes: u64,
    bad_headers: u64,
    crc_errors: u64,
    crc_bytes: u64,
    lost: u64,
}

fn write_all(port: &mut TTYPort, bytes: &[u8]) {
    port.write_all(bytes).unwrap();
    port.flush().unwrap();
}

/// Returns what was injected and the open device, which must outlive the checks
/// (closing it is a disconnect).
fn inject(dir: &Path, metrics: &Arc<SourceMetrics>) -> (Injected, TTYPort, TTYPort) {
    let mut inj = Injected::default();
    let (mut master, slave_a) = device(&dir.join("ttyTEXEL0"));
    wait_until("the device opens", || {
        metrics.state() == SourceState::Running
    });
    let send = |port: &mut TTYPort, seqs: std::ops::Range<u32>, inj: &mut Injected| {
        for seq in seqs {
            write_all(port, &frame(seq).encode());
            inj.valid.push(seq);
        }
    };
    // Garbage before the first frame (no magic in it).
    let garbage: Vec<u8> = (0..100u8).map(|i| b'a' + i % 26).collect();
    write_all(&mut master, &garbage);
    inj.garbage_bytes += 100;
    send(&mut master, 0..5, &mut inj);
    // Seq 5 with a damaged payload: dropped, counted, and its seq lost.
    let mut bad = frame(5).encode();
    bad[30] ^= 0x5A;
    write_all(&mut master, &bad);
    inj.crc_errors += 1;
    inj.crc_bytes += bad.len() as u64;
    inj.lost += 1;
    send(&mut master, 6..10, &mut inj);
    // Seqs 10 and 11 never sent.
    inj.lost += 2;
    send(&mut master, 12..15, &mut inj);
    // A header with an unknown version: refused at once, its bytes skipped.
    let mut header = frame(99).encode()[..28].to_vec();
    header[4] = 9;
    write_all(&mut master, &header);
    inj.bad_headers += 1;
    inj.garbage_bytes += 28;
    let n = inj.valid.len() as u64;
    wait_until("phase 1 frames", || received(metrics) == n);

    // A stall: the line goes silent; the source reports it and reopens.
    wait_until("the stall is reported", || metrics.counter("stalls") >= 1);
    wait_until("the device is reopened", || {
        metrics.counter("reopens") >= 1 && metrics.state() == SourceState::Running
    });
    send(&mut master, 15..20, &mut inj);
    let n = inj.valid.len() as u64;
    wait_until("frames after the stall", || received(metrics) == n);

    // Unplugged: the name disappears, the line closes.
    std::fs::remove_file(dir.join("ttyTEXEL0")).unwrap();
    drop(master);
    drop(slave_a);
    wait_until("the disconnect is reported", || {
        metrics.counter("disconnects") == 1
    });
    std::thread::sleep(Duration::from_millis(200));
    // Plugged in again under another name.
    let (mut master, slave_b) = device(&dir.join("ttyTEXEL1"));
    wait_until("the new device opens", || {
        metrics.state() == SourceState::Running
    });
    send(&mut master, 20..25, &mut inj);
    let n = inj.valid.len() as u64;
    wait_until("frames on the new device", || received(metrics) == n);
    (inj, master, slave_b)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_valid_frame_survives_garbage_crc_errors_gaps_a_stall_and_a_replug() {
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("serial.mcap");
    let glob = format!("{}/ttyTEXEL*", dir.path().display());
    let shutdown = CancellationToken::new();
    let session = Session::start(
        session_config(dir.path(), glob, record.clone()),
        shutdown.clone(),
    )
    .await
    .unwrap();
    let metrics = session.metrics.sources.lock().unwrap()[0].clone();
    // Nothing matches the glob yet: reported, retried.
    wait_until_async(|| metrics.counter("open_failures") >= 1).await;
    assert!(
        metrics.last_error().unwrap().contains("no device matches"),
        "{:?}",
        metrics.last_error()
    );
    let dir_path = dir.path().to_path_buf();
    let m = metrics.clone();
    let (inj, master, slave) = tokio::task::spawn_blocking(move || inject(&dir_path, &m))
        .await
        .unwrap();

    let status = session.metrics.snapshot();
    shutdown.cancel();
    drop((master, slave));
    let summary = session.wait().await.unwrap();

    let c = &status.sources[0].counters;
    assert_eq!(c["range_frames"], inj.valid.len() as u64);
    assert_eq!(c["frames_decoded"], inj.valid.len() as u64);
    assert_eq!(c["crc_errors"], inj.crc_errors);
    assert_eq!(c["bytes_in_bad_frames"], inj.crc_bytes);
    assert_eq!(c["bad_headers"], inj.bad_headers);
    assert_eq!(c["bytes_skipped"], inj.garbage_bytes);
    assert_eq!(c["lost_frames"], inj.lost);
    assert_eq!(c["seq_restarts"], 0);
    assert_eq!(c["disconnects"], 1);
    assert!(c["stalls"] >= 1 && c["reopens"] >= 2, "{c:?}");

    // Every valid frame is in the recording, with its ranges.
    assert_eq!(summary.recording.unwrap().errors, 0);
    let mut recorded = Vec::new();
    for event in CaptureReader::open(&record).unwrap() {
        if let CaptureEvent::Range(f) = event.unwrap() {
            let seq = ((f.timestamp_ns - 5_000_000_000) / PERIOD_NS) as u32;
            let want = frame(seq).to_range_frame();
            assert_eq!(f.ranges_m, want.ranges_m, "seq {seq}");
            recorded.push(seq);
        }
    }
    assert_eq!(recorded, inj.valid);
}

async fn wait_until_async(mut f: impl FnMut() -> bool) {
    tokio::time::timeout(Duration::from_secs(10), async {
        while !f() {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_missing_device_is_reported_by_name_and_retried() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = session_config(
        dir.path(),
        "/dev/ttyTEXELMISSING9".into(),
        dir.path().join("r.mcap"),
    );
    c.record.path = None;
    let shutdown = CancellationToken::new();
    let session = Session::start(c, shutdown.clone()).await.unwrap();
    let metrics = session.metrics.sources.lock().unwrap()[0].clone();
    wait_until_async(|| metrics.counter("open_failures") >= 2).await;
    let status = session.metrics.snapshot();
    assert_eq!(status.sources[0].state, "reopening");
    let e = status.sources[0].last_error.clone().unwrap();
    assert!(
        e.contains("/dev/ttyTEXELMISSING9") && e.contains("cannot open"),
        "{e}"
    );
    shutdown.cancel();
    tokio::time::timeout(Duration::from_secs(2), session.wait())
        .await
        .unwrap()
        .unwrap();
}

/// The hostile stream from the decoder's issue: a header claiming the largest legal
/// frame whose span (CRC field included) is the magic repeated, so its CRC fails and
/// each of the million false magics inside is a bad header. Returns the bytes and the
/// number of false magics.
fn false_magic_flood() -> (Vec<u8>, u64) {
    let mut stream = texel::fuzzing::header(MAX_SIDE, MAX_SIDE, true);
    let magics = (MAX_FRAME_LEN - HEADER_LEN) / MAGIC.len();
    stream.extend(MAGIC.repeat(magics));
    (stream, magics as u64)
}

/// As `wait_until`, with a longer guard for a phase that moves megabytes.
fn wait_long(what: &str, mut f: impl FnMut() -> bool) {
    let start = Instant::now();
    while !f() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "timed out: {what}"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_false_magic_flood_after_a_bogus_large_header_keeps_frames_stalls_and_shutdown_working() {
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("serial.mcap");
    let glob = format!("{}/ttyTEXEL*", dir.path().display());
    let shutdown = CancellationToken::new();
    let session = Session::start(
        session_config(dir.path(), glob, record.clone()),
        shutdown.clone(),
    )
    .await
    .unwrap();
    let metrics = session.metrics.sources.lock().unwrap()[0].clone();
    let (flood, magics) = false_magic_flood();
    let flood_len = flood.len() as u64;
    let dir_path = dir.path().to_path_buf();
    let m = metrics.clone();
    let first_flood = flood.clone();
    let (master, slave) = tokio::task::spawn_blocking(move || {
        let (mut master, slave) = device(&dir_path.join("ttyTEXEL0"));
        // The writer waits as long as the reader needs; the guards are below.
        master.set_timeout(Duration::from_secs(60)).unwrap();
        wait_until("the device opens", || m.state() == SourceState::Running);
        for seq in 0..3 {
            write_all(&mut master, &frame(seq).encode());
        }
        write_all(&mut master, &first_flood);
        for seq in 3..8 {
            write_all(&mut master, &frame(seq).encode());
        }
        wait_long("every frame after the flood", || received(&m) == 8);
        assert_eq!(m.counter("crc_errors"), 1);
        assert_eq!(m.counter("bad_headers"), magics);
        assert_eq!(m.counter("bytes_in_bad_frames"), HEADER_LEN as u64);
        assert_eq!(m.counter("bytes_skipped"), flood_len - HEADER_LEN as u64);
        assert_eq!(m.counter("lost_frames"), 0);
        // The line goes silent: the stall is still reported and the device reopened.
        wait_until("the stall is reported", || m.counter("stalls") >= 1);
        wait_until("the device is reopened", || {
            m.counter("reopens") >= 1 && m.state() == SourceState::Running
        });
        for seq in 8..10 {
            write_all(&mut master, &frame(seq).encode());
        }
        wait_until("frames after the stall", || received(&m) == 10);
        (master, slave)
    })
    .await
    .unwrap();

    // A flood that never ends: shutdown still stops the source.
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let writer = {
        let stop = stop.clone();
        let mut master = master;
        std::thread::spawn(move || {
            master.set_timeout(Duration::from_millis(100)).unwrap();
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                for chunk in flood.chunks(64 * 1024) {
                    match master.write(chunk) {
                        Ok(_) => {}
                        Err(e) if e.kind() == std::io::ErrorKind::TimedOut => break,
                        Err(_) => return,
                    }
                }
            }
        })
    };
    let read_before = metrics.counter("bytes_read");
    wait_until_async(|| metrics.counter("bytes_read") > read_before + 2 * flood_len).await;
    shutdown.cancel();
    let summary = tokio::time::timeout(Duration::from_secs(60), session.wait())
        .await
        .expect("the session stops during a flood")
        .unwrap();
    // Unblock the writer: read what it still writes until it sees the stop.
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let mut slave = slave;
    let mut drain = vec![0u8; 64 * 1024];
    while !writer.is_finished() {
        let _ = slave.read(&mut drain);
    }
    writer.join().unwrap();

    assert_eq!(metrics.counter("frames_decoded"), 10);
    assert_eq!(summary.recording.unwrap().errors, 0);
    let mut recorded = Vec::new();
    for event in CaptureReader::open(&record).unwrap() {
        if let CaptureEvent::Range(f) = event.unwrap() {
            recorded.push(((f.timestamp_ns - 5_000_000_000) / PERIOD_NS) as u32);
        }
    }
    assert_eq!(recorded, (0..10).collect::<Vec<_>>());
}
