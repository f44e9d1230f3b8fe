//! The `sim-serial` source end to end: the simulator's virtual TXL1 lidar on a real
//! pseudo-terminal pair, with garbage, CRC errors, a dropped frame, a stall and an
//! unplug-and-reappear injected from the session config, read by the serial source's
//! own code and paired with the simulator's EO frames. The recording holds every
//! intact frame, bit-identical to what the simulator put on the line (computed here
//! independently), each with its EO frame; the status counters equal the device's
//! injection log; and `configs/sessions/sim-serial.toml` is a valid session.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
// The simulated sources are the `sim` feature (on by default).
#![cfg(feature = "sim")]

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use serde_json::Value;
use sims::serial::{
    SerialFaults, VirtualLidar, VirtualLidarConfig, frame_of_seq, sim_frame_for_seq,
};
use texel::capture::{CaptureEvent, CaptureReader, PoseTopic};
use texel_daemon::config::{OverloadPolicy, RegistrationMode, SessionConfig, SimSerialConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::source::sim::build_simulator;
use texel_daemon::status::Counter;
use texel_e2e::repo_root;
use tokio_util::sync::CancellationToken;

const FRAMES: u32 = 14;

/// Faults chosen so every kind shows once or more, none on the last frame (a lost last
/// frame leaves no gap to count). Timing: at 10 Hz with a 300 ms stall timeout and
/// 50 ms backoff, a 400 ms stall is seen exactly once (the reader gives up 300 ms after
/// the last frame, reopens, and the device resumes 500 ms after it, before a second
/// timeout at 650 ms).
fn device() -> VirtualLidarConfig {
    VirtualLidarConfig {
        rate_hz: Some(10.0),
        faults: SerialFaults {
            garbage_every_frames: 4, // before seqs 3, 7, 11
            garbage_bytes: 40,
            crc_error_seqs: vec![2, 10],
            drop_seqs: vec![5],
            stall_at_seq: Some(8),
            stall_s: 0.4,
            disconnect_at_seq: Some(12),
            reappear_after_s: Some(0.3),
            seed: 7,
            ..SerialFaults::default()
        },
        ..VirtualLidarConfig::default()
    }
}

fn sim_serial(dir: &Path) -> SimSerialConfig {
    SimSerialConfig {
        name: "lidar".into(),
        scene: repo_root().join("configs/scenes/lab.toml"),
        seed: 5,
        frames: Some(FRAMES as usize),
        // Small, so rendering keeps up with the line.
        lidar_size: Some([64, 48]),
        eo_size: Some([80, 60]),
        stall_timeout_ms: 300,
        reopen_backoff_min_ms: 50,
        reopen_backoff_max_ms: 200,
        injection_log: Some(dir.join("injections.json")),
        device: device(),
        ..SimSerialConfig::default()
    }
}

fn session(dir: &Path) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.sim_serial = vec![sim_serial(dir)];
    c.session.exit_when_sources_end = true;
    c.pipeline.registration = RegistrationMode::Register;
    c.pipeline.overload = OverloadPolicy::KeepNewest;
    c.serve.enabled = false;
    c.record.path = Some(dir.join("sim-serial.mcap"));
    c.status.log = false;
    c.validate("test").unwrap();
    c
}

fn seqs(log: &Value, key: &str) -> Vec<u32> {
    log[key]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as u32)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_intact_frame_is_recorded_bit_identical_and_counters_equal_the_injections() {
    let dir = tempfile::tempdir().unwrap();
    let config = session(dir.path());
    let record = config.record.path.clone().unwrap();
    let session = Session::start(config, CancellationToken::new())
        .await
        .unwrap();
    let metrics = session.metrics.clone();
    let summary = tokio::time::timeout(Duration::from_secs(60), session.wait())
        .await
        .expect("the session did not end")
        .unwrap();

    // 1. The device did what the config asked, and says so in its log.
    let log: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("injections.json")).unwrap())
            .unwrap();
    assert_eq!(seqs(&log, "garbage_before_seqs"), [3, 7, 11]);
    assert_eq!(log["garbage_bytes"], 120);
    assert_eq!(seqs(&log, "crc_error_seqs"), [2, 10]);
    assert_eq!(seqs(&log, "dropped_seqs"), [5]);
    assert_eq!(log["frames_written"], u64::from(FRAMES) - 1);
    assert_eq!(log["stalls"].as_array().unwrap().len(), 1);
    let disconnects = log["disconnects"].as_array().unwrap();
    assert_eq!(disconnects.len(), 1);
    assert_eq!(disconnects[0]["before_seq"], 12);
    assert!(disconnects[0]["reappeared_as"].is_string(), "{log}");
    // Timing preconditions of the counts below: the reader never closed the port
    // while the device was writing.
    assert_eq!(log["reader_disconnects"], 0, "{log}");

    // 2. The serial source's counters equal the injection log.
    let sim = Arc::new(build_simulator(&sim_serial(dir.path()).setup()).unwrap());
    let lidar = VirtualLidar::new(sim.clone(), device()).unwrap();
    let source = &summary.status.sources[0];
    assert_eq!(
        (source.kind.as_str(), source.state.as_str()),
        ("sim-serial", "ended")
    );
    let c = &source.counters;
    eprintln!("counters: {c:?}");
    let crc_seqs = seqs(&log, "crc_error_seqs");
    let dropped = seqs(&log, "dropped_seqs");
    let n = |v: &Value| v.as_u64().unwrap();
    for (counter, key) in [
        ("injected_frames_written", "frames_written"),
        ("injected_bytes_written", "bytes_written"),
        ("injected_garbage_bytes", "garbage_bytes"),
        ("injected_crc_errors", "crc_errors"),
        ("injected_dropped", "dropped"),
    ] {
        assert_eq!(c[counter], n(&log[key]), "{counter}");
    }
    assert_eq!(c["injected_stalls"], 1);
    assert_eq!(c["injected_disconnects"], 1);
    assert_eq!(c["bytes_read"], n(&log["bytes_written"]));
    assert_eq!(c["bytes_skipped"], n(&log["garbage_bytes"]));
    assert_eq!(c["bad_headers"], 0);
    assert_eq!(c["crc_errors"], n(&log["crc_errors"]));
    let bad_bytes: usize = crc_seqs
        .iter()
        .map(|&s| lidar.wire_frame(s).unwrap().encode().len())
        .sum();
    assert_eq!(c["bytes_in_bad_frames"], bad_bytes as u64);
    // A frame with a bad CRC is refused, so its seq is a gap like a dropped one.
    assert_eq!(c["lost_frames"], (crc_seqs.len() + dropped.len()) as u64);
    assert_eq!(c["seq_restarts"], 0);
    let intact = n(&log["frames_written"]) - n(&log["crc_errors"]);
    assert_eq!(c["frames_decoded"], intact);
    assert_eq!(c["range_frames"], intact);
    // Each lidar frame's EO frame was rendered and sent, or skipped (counted) when
    // rendering fell behind the line (`late = skip`).
    let eo_skipped = c.get("eo_skipped").copied().unwrap_or(0);
    assert_eq!(c["eo_frames"] + eo_skipped, intact);
    assert!(eo_skipped <= 2, "rendering fell far behind: {c:?}");
    assert!(!c.contains_key("eo_render_failures"), "{c:?}");
    // The unplug was seen and survived; the injected stall was seen, and the end of
    // the stream shows as one more.
    assert_eq!(c["disconnects"], 1);
    assert_eq!(c["stalls"], 2);
    assert!(c["reopens"] >= 2, "{c:?}");
    assert!(
        c["open_failures"] >= 1,
        "the unplugged device was retried: {c:?}"
    );

    // 3. Every intact lidar frame met its EO frame and went down the pipeline.
    assert_eq!(metrics.get(Counter::Paired), c["eo_frames"]);
    assert_eq!(metrics.get(Counter::UnpairedRange), eo_skipped);
    assert_eq!(metrics.get(Counter::UnpairedEo), 0);
    assert!(summary.scans > 0, "no scan reached the model");
    assert_eq!(summary.recording.unwrap().errors, 0);

    // 4. The recording: every intact frame, in order (before and after the unplug),
    // ranges bit-identical to the simulator's frame on the wire, EO bit-identical to
    // the simulator's, each with its truth.
    let want: Vec<u32> = (0..FRAMES)
        .filter(|s| !crc_seqs.contains(s) && !dropped.contains(s))
        .collect();
    let seq_at: BTreeMap<u64, u32> = (0..FRAMES).map(|s| (frame_of_seq(&sim, s).1, s)).collect();
    let (mut ranges, mut eos, mut truths) = (Vec::new(), Vec::new(), Vec::new());
    for event in CaptureReader::open(&record).unwrap() {
        match event.unwrap() {
            CaptureEvent::Range(f) => {
                let seq = seq_at[&f.timestamp_ns];
                let expected = lidar.wire_frame(seq).unwrap().to_range_frame();
                assert_eq!((f.width, f.height), (64, 48));
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&f.ranges_m), bits(&expected.ranges_m), "seq {seq}");
                ranges.push(seq);
            }
            CaptureEvent::Eo(f) => {
                let seq = seq_at[&f.timestamp_ns];
                let expected = sim_frame_for_seq(&sim, seq).unwrap().pair.eo;
                assert!(f.rgb == expected.rgb, "EO of seq {seq} differs");
                eos.push(seq);
            }
            CaptureEvent::Pose {
                topic: PoseTopic::Truth,
                timestamp_ns,
                world_from_eo,
            } => {
                let seq = seq_at[&timestamp_ns];
                let truth = sim.true_pose(seq as usize);
                let (angle, dist) = texel::pose::pose_difference(&world_from_eo, &truth);
                assert!(angle < 1e-12 && dist < 1e-12, "truth of seq {seq}");
                truths.push(seq);
            }
            _ => {}
        }
    }
    assert_eq!(ranges, want);
    assert_eq!(truths, want);
    assert_eq!(eos.len() as u64, c["eo_frames"]);
    assert!(eos.iter().all(|s| want.contains(s)), "{eos:?}");
}

#[test]
fn the_session_file_is_valid_and_faults_are_checked_by_key() {
    let path = repo_root().join("configs/sessions/sim-serial.toml");
    let c = SessionConfig::load(&path).unwrap();
    c.validate("sim-serial.toml").unwrap();
    let s = &c.source.sim_serial[0];
    assert_eq!(s.device.faults.disconnect_at_seq, Some(28));
    assert!(s.device.faults.stall_s * 1000.0 > s.stall_timeout_ms as f64);

    let text = std::fs::read_to_string(&path).unwrap();
    let bad = text.replace("stall_s = 1.5", "stall_s = 1.5\nstal_s = 2.0");
    let e = SessionConfig::from_toml_str(&bad, "s.toml")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("source.sim_serial[0].device.faults.stal_s"),
        "{e}"
    );
    let mut c2 = SessionConfig::from_toml_str(&text, "s.toml").unwrap();
    c2.source.sim_serial[0].device.faults.stall_s = -1.0;
    let e = c2.validate("s.toml").unwrap_err().to_string();
    assert!(
        e.contains("source.sim_serial[0].device") && e.contains("stall_s"),
        "{e}"
    );
    let mut c3 = SessionConfig::from_toml_str(&text, "s.toml").unwrap();
    c3.source.sim_serial[0].lidar_size = Some([2048, 16]);
    let e = c3.validate("s.toml").unwrap_err().to_string();
    assert!(e.contains("source.sim_serial[0].lidar_size"), "{e}");
    let mut c4 = SessionConfig::from_toml_str(&text, "s.toml").unwrap();
    c4.source.sim.push(Default::default());
    c4.source.sim[0].scene = "x.toml".into();
    let e = c4.validate("s.toml").unwrap_err().to_string();
    assert!(e.contains("at most one simulator"), "{e}");
}
