//! The virtual TXL1 lidar over real pseudo-terminals, read with `texel::txl1`'s
//! streaming decoder: intact frames arrive bit-identical and pair with the
//! simulator's EO frames, the decoder's counters equal the injection log, stalls and
//! disconnects are seen by the reader, and the CLI serves a device a reader can open.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use std::io::{BufRead, BufReader, ErrorKind, Read};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serialport::SerialPort;
use sims::serial::{
    DeviceEvent, SerialFaults, StopSignal, StreamEnd, VirtualLidar, VirtualLidarConfig,
    sim_frame_for_seq, spawn_pty,
};
use sims::{SimOptions, Simulator};
use texel::txl1::{Txl1Decoder, Txl1Frame};

/// The wall scene (10 poses) with range noise (every frame differs), lidar 32x32.
fn sim(frames: Option<usize>) -> Arc<Simulator> {
    Arc::new(
        Simulator::with_options(
            common::load("wall"),
            &SimOptions {
                seed: 11,
                effects: Some(common::effects(&["range_noise"])),
                frames,
                lidar_size: Some([32, 32]),
                eo_size: Some([40, 30]),
                ..SimOptions::default()
            },
        )
        .unwrap(),
    )
}

fn open(path: &str, timeout: Duration) -> Box<dyn SerialPort> {
    serialport::new(path, 115_200)
        .timeout(timeout)
        .open()
        .unwrap_or_else(|e| panic!("cannot open {path}: {e}"))
}

/// What one read attempt saw.
#[derive(Debug, PartialEq)]
enum Seen {
    Frames(Vec<Txl1Frame>),
    Timeout,
    /// End of file or an error: the device is gone.
    Gone,
}

fn read_once(port: &mut dyn Read, decoder: &mut Txl1Decoder) -> Seen {
    let mut buf = [0u8; 4096];
    match port.read(&mut buf) {
        Ok(0) => Seen::Gone,
        Ok(n) => {
            decoder.push(&buf[..n]);
            Seen::Frames(std::iter::from_fn(|| decoder.next_frame()).collect())
        }
        Err(e) if e.kind() == ErrorKind::TimedOut => Seen::Timeout,
        Err(_) => Seen::Gone,
    }
}

/// Reads until a frame with `last_seq` arrives (or `limit` passes).
fn read_until(
    port: &mut dyn Read,
    decoder: &mut Txl1Decoder,
    last_seq: u32,
    limit: Duration,
) -> Vec<Txl1Frame> {
    let start = Instant::now();
    let mut frames = Vec::new();
    while start.elapsed() < limit {
        if let Seen::Frames(f) = read_once(port, decoder) {
            let done = f.iter().any(|f| f.seq == last_seq);
            frames.extend(f);
            if done {
                return frames;
            }
        }
    }
    panic!("frame {last_seq} did not arrive; got {:?}", seqs(&frames));
}

fn seqs(frames: &[Txl1Frame]) -> Vec<u32> {
    frames.iter().map(|f| f.seq).collect()
}

/// Every frame equals the simulator's frame for its seq, quantised, and carries the
/// timestamp of the EO frame it pairs with.
fn assert_frames_are_the_simulators(sim: &Simulator, frames: &[Txl1Frame], unit_um: u32) {
    for f in frames {
        let truth = sim_frame_for_seq(sim, f.seq).unwrap();
        let want = Txl1Frame::from_range_frame(&truth.pair.range, unit_um).unwrap();
        assert_eq!(f, &want, "frame {}", f.seq);
        assert_eq!(f.timestamp_ns, truth.pair.eo.timestamp_ns);
    }
}

#[test]
fn garbage_crc_errors_and_drops_match_the_injection_log() {
    let sim = sim(None);
    assert_eq!(sim.frame_count(), 10);
    let config = VirtualLidarConfig {
        range_unit_um: 500,
        rate_hz: Some(100.0),
        faults: SerialFaults {
            garbage_every_frames: 3,
            garbage_bytes: 37,
            crc_error_seqs: vec![4],
            drop_every_frames: 4,
            drop_seqs: vec![6],
            seed: 3,
            ..SerialFaults::default()
        },
        ..VirtualLidarConfig::default()
    };
    let device = spawn_pty(VirtualLidar::new(sim.clone(), config).unwrap(), None).unwrap();
    let mut port = open(&device.path(), Duration::from_millis(200));
    let mut decoder = Txl1Decoder::new();
    let frames = read_until(&mut port, &mut decoder, 9, Duration::from_secs(20));
    let log = device.stop().unwrap();
    assert_eq!(seqs(&frames), [0, 1, 2, 5, 8, 9]);
    assert_frames_are_the_simulators(&sim, &frames, 500);
    assert_eq!(log.dropped_seqs, [3, 6, 7]);
    assert_eq!(log.crc_error_seqs, [4]);
    assert_eq!(log.garbage_before_seqs, [2, 5, 8]);
    let c = decoder.counters();
    assert_eq!(c.bytes_skipped, log.garbage_bytes);
    assert_eq!(log.garbage_bytes, 3 * 37);
    assert_eq!(c.crc_errors, log.crc_errors);
    assert_eq!(c.lost_frames, log.dropped + log.crc_errors);
    assert_eq!(c.frames, log.frames_written - log.crc_errors);
    assert_eq!(c.bad_headers, 0);
    let bad_len = Txl1Frame::from_range_frame(&sim_frame_for_seq(&sim, 4).unwrap().pair.range, 500)
        .unwrap()
        .encode()
        .len();
    assert_eq!(c.bytes_in_bad_frames, bad_len as u64);
    assert_eq!(log.last_seq_written, Some(9));
    assert_eq!(
        log.bytes_written,
        log.garbage_bytes + (log.frames_written as usize * bad_len) as u64
    );
}

#[test]
fn a_stall_and_a_disconnect_are_seen_by_the_reader() {
    let sim = sim(None);
    let config = VirtualLidarConfig {
        rate_hz: Some(50.0),
        loop_trajectory: true,
        max_frames: Some(12),
        faults: SerialFaults {
            stall_at_seq: Some(3),
            stall_s: 1.0,
            disconnect_at_seq: Some(6),
            reappear_after_s: Some(0.3),
            ..SerialFaults::default()
        },
        ..VirtualLidarConfig::default()
    };
    let device = spawn_pty(VirtualLidar::new(sim.clone(), config).unwrap(), None).unwrap();
    let first_path = device.path();
    let mut port = open(&first_path, Duration::from_millis(300));
    let mut decoder = Txl1Decoder::new();
    let before = read_until(&mut port, &mut decoder, 2, Duration::from_secs(10));
    assert_eq!(seqs(&before), [0, 1, 2]);
    // The stall: the line is silent longer than the read timeout.
    let silent = Instant::now();
    assert_eq!(read_once(&mut port, &mut decoder), Seen::Timeout);
    let after = read_until(&mut port, &mut decoder, 5, Duration::from_secs(10));
    assert!(silent.elapsed() > Duration::from_millis(600));
    assert_eq!(seqs(&after), [3, 4, 5]);
    // The disconnect: the port reads end of file or fails.
    let gone = Instant::now();
    loop {
        match read_once(&mut port, &mut decoder) {
            Seen::Gone => break,
            Seen::Timeout => assert!(gone.elapsed() < Duration::from_secs(5)),
            Seen::Frames(f) => panic!("frames after the disconnect: {:?}", seqs(&f)),
        }
    }
    drop(port);
    // It reappears under a new name and continues with frame 6.
    let new_path = loop {
        match device
            .events()
            .recv_timeout(Duration::from_secs(5))
            .unwrap()
        {
            DeviceEvent::Reappeared { path } => break path,
            _ => continue,
        }
    };
    assert_ne!(new_path, first_path);
    assert_eq!(device.path(), new_path);
    let mut port = open(&new_path, Duration::from_millis(300));
    let rest = read_until(&mut port, &mut decoder, 11, Duration::from_secs(10));
    assert_eq!(seqs(&rest), [6, 7, 8, 9, 10, 11]);
    assert_frames_are_the_simulators(&sim, &rest, 1000);
    let log = device.stop().unwrap();
    assert_eq!(log.stalls.len(), 1);
    assert_eq!(log.stalls[0].before_seq, 3);
    assert!(log.stalls[0].duration_s >= 1.0);
    assert_eq!(log.disconnects.len(), 1);
    assert_eq!(log.disconnects[0].before_seq, 6);
    assert_eq!(
        log.disconnects[0].reappeared_as.as_deref(),
        Some(new_path.as_str())
    );
    let c = decoder.counters();
    assert_eq!((c.lost_frames, c.bytes_skipped, c.crc_errors), (0, 0, 0));
}

#[test]
fn a_reader_may_close_the_port_and_open_it_again() {
    let sim = sim(None);
    let config = VirtualLidarConfig {
        rate_hz: Some(100.0),
        loop_trajectory: true,
        ..VirtualLidarConfig::default()
    };
    let device = spawn_pty(VirtualLidar::new(sim.clone(), config).unwrap(), None).unwrap();
    let path = device.path();
    let mut decoder = Txl1Decoder::new();
    {
        let mut port = open(&path, Duration::from_millis(200));
        read_until(&mut port, &mut decoder, 1, Duration::from_secs(10));
    }
    // The device notices when it next writes, and waits for the next reader.
    let start = Instant::now();
    loop {
        match device
            .events()
            .recv_timeout(Duration::from_secs(10))
            .unwrap()
        {
            DeviceEvent::ReaderGone => break,
            _ => assert!(start.elapsed() < Duration::from_secs(10)),
        }
    }
    std::thread::sleep(Duration::from_millis(100));
    let waiting = device.log();
    assert_eq!(waiting.reader_disconnects, 1);
    let mut port = open(&path, Duration::from_millis(200));
    let mut fresh = Txl1Decoder::new();
    let start = Instant::now();
    let frames = loop {
        if let Seen::Frames(f) = read_once(&mut port, &mut fresh)
            && !f.is_empty()
        {
            break f;
        }
        assert!(start.elapsed() < Duration::from_secs(10));
    };
    // Nothing was written while no reader had the port open: the stream resumes
    // right after the frame that found the reader gone.
    assert_eq!(waiting.undelivered_seqs.len(), 1);
    assert_eq!(
        waiting.last_seq_written,
        Some(waiting.undelivered_seqs[0] - 1)
    );
    assert_eq!(frames[0].seq, waiting.undelivered_seqs[0] + 1);
    assert_frames_are_the_simulators(&sim, &frames, 1000);
    drop(port);
    let log = device.stop().unwrap();
    assert_eq!(log.reader_disconnects, 1, "{log:?}");
}

#[test]
fn a_device_written_to_memory_loops_with_paired_timestamps() {
    let sim = sim(Some(4));
    let config = VirtualLidarConfig {
        range_unit_um: 250,
        rate_hz: Some(1000.0),
        loop_trajectory: true,
        max_frames: Some(7),
        faults: SerialFaults {
            garbage_every_frames: 2,
            garbage_bytes: 5,
            crc_error_every_frames: 5,
            ..SerialFaults::default()
        },
    };
    let mut lidar = VirtualLidar::new(sim.clone(), config).unwrap();
    let mut bytes = Vec::new();
    let end = lidar.run(&mut bytes, &StopSignal::new()).unwrap();
    assert_eq!(end, StreamEnd::Finished);
    let log = lidar.log();
    let mut decoder = Txl1Decoder::new();
    decoder.push(&bytes);
    let frames: Vec<Txl1Frame> = std::iter::from_fn(|| decoder.next_frame()).collect();
    assert_eq!(seqs(&frames), [0, 1, 2, 3, 5, 6]);
    assert_frames_are_the_simulators(&sim, &frames, 250);
    // Lap 1 repeats the trajectory one period (4 frames at 10 Hz) later.
    let (f1, f5) = (&frames[1], &frames[4]);
    assert_eq!(f5.ranges, f1.ranges);
    assert_eq!(f5.timestamp_ns - f1.timestamp_ns, 400_000_000);
    assert_eq!(f1, &lidar.wire_frame(1).unwrap());
    let c = decoder.counters();
    assert_eq!(log.crc_error_seqs, [4]);
    assert_eq!(log.garbage_before_seqs, [1, 3, 5]);
    assert_eq!(c.bytes_skipped, log.garbage_bytes);
    assert_eq!((c.crc_errors, c.lost_frames), (1, 1));
    assert_eq!(bytes.len() as u64, log.bytes_written);
}

#[test]
fn the_configuration_is_strict_toml() {
    let config: VirtualLidarConfig = toml::from_str(
        "range_unit_um = 500\nloop_trajectory = true\n[faults]\ndrop_every_frames = 3\nstall_at_seq = 9\n",
    )
    .unwrap();
    assert_eq!(config.range_unit_um, 500);
    assert_eq!(config.faults.drop_every_frames, 3);
    assert_eq!(config.faults.stall_at_seq, Some(9));
    assert_eq!(config.faults.stall_s, 2.0);
    let e = toml::from_str::<VirtualLidarConfig>("[faults]\ndrop_evry = 3\n").unwrap_err();
    assert!(e.to_string().contains("drop_evry"), "{e}");
    let bad = VirtualLidarConfig {
        rate_hz: Some(0.0),
        ..VirtualLidarConfig::default()
    };
    let e = VirtualLidar::new(sim(Some(1)), bad).err().unwrap();
    assert!(e.to_string().contains("rate_hz"), "{e}");
}

#[test]
fn the_cli_serves_a_device_a_reader_can_open() {
    let scene = common::configs().join("scenes/plane.toml");
    let mut child = Command::new(env!("CARGO_BIN_EXE_texel-sims"))
        .args(["serve-serial", "--scene"])
        .arg(&scene)
        .args(["--loop", "--rate-hz", "20", "--drop-every", "2"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut path = String::new();
    stdout.read_line(&mut path).unwrap();
    let path = path.trim();
    assert!(path.starts_with("/dev/"), "{path:?}");
    let mut port = open(path, Duration::from_millis(500));
    let mut decoder = Txl1Decoder::new();
    let start = Instant::now();
    let mut frames = Vec::new();
    while frames.len() < 2 {
        if let Seen::Frames(f) = read_once(&mut port, &mut decoder) {
            frames.extend(f);
        }
        assert!(start.elapsed() < Duration::from_secs(20), "no frame");
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert_eq!((frames[0].width, frames[0].height), (128, 128));
    // Every second frame is dropped: even seqs only.
    assert!(frames.iter().all(|f| f.seq % 2 == 0), "{:?}", seqs(&frames));
}
