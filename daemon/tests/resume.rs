//! A real `texeld` killed with SIGKILL in the middle of a simulated session comes back
//! with `--resume`: the model is rebuilt from the recording (ids and poses as
//! recorded, nothing registered again), the simulator goes on after the last
//! recorded frame, a viewer that connects gets the whole model, and the final model
//! matches an uninterrupted run of the same frames.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use texel::Pose;
use texel::capture::RegisteredPoses;
use texel_client::{BlockingClient, Replica};

const FRAMES: usize = 50;

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn session_file(dir: &Path, name: &str, stay: bool) -> (PathBuf, PathBuf) {
    let recording = dir.join(format!("{name}.mcap"));
    let session = dir.join(format!("{name}.toml"));
    let scene = repo_root().join("configs/scenes/lab-walk.toml");
    std::fs::write(
        &session,
        format!(
            "[session]\nname = \"{name}\"\nexit_when_sources_end = {}\n\
             [[source.sim]]\nscene = \"{}\"\nframes = {FRAMES}\nlidar_size = [64, 64]\n\
             eo_size = [160, 120]\nspeed = 1.0\nlate = \"wait\"\nrender_threads = 1\n\
             [pipeline]\noverload = \"backpressure\"\n\
             [record]\npath = \"{}\"\nflush_interval_ms = 200\n\
             [serve]\nbind = \"127.0.0.1:0\"\n\
             [status]\ninterval_ms = 200\n\
             [model.retirement]\nenabled = false\n",
            !stay,
            scene.display(),
            recording.display()
        ),
    )
    .unwrap();
    (session, recording)
}

/// Starts `texeld` with stderr forwarded line by line to a channel.
fn spawn(args: &[&std::ffi::OsStr]) -> (Child, mpsc::Receiver<String>) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(args)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines() {
            let Ok(line) = line else { break };
            if tx.send(strip_ansi(&line)).is_err() {
                break;
            }
        }
    });
    (child, rx)
}

/// The line without its terminal colour codes (`ESC [ ... m`).
fn strip_ansi(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut chars = line.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            for d in chars.by_ref() {
                if d == 'm' {
                    break;
                }
            }
        } else {
            out.push(c);
        }
    }
    out
}

fn wait_line(rx: &mpsc::Receiver<String>, needle: &str, log: &mut Vec<String>) -> String {
    let deadline = Instant::now() + Duration::from_secs(120);
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

/// Every frame's registered pose over a recording's segments (its last `/texel/pose`,
/// or its keyframe's composed with its `/texel/anchor`), and the order of their
/// first `/texel/pose` (the ids).
fn recorded_poses(segments: &[PathBuf]) -> (Vec<u64>, BTreeMap<u64, Pose>) {
    let mut poses = RegisteredPoses::default();
    for path in segments {
        poses.read_capture(path).unwrap();
    }
    (poses.timestamps().to_vec(), poses.iter().collect())
}

fn distance_m(a: &Pose, b: &Pose) -> f64 {
    (a.translation.vector - b.translation.vector).norm()
}

#[test]
fn a_killed_session_resumes_from_its_recording_and_ends_like_an_uninterrupted_one() {
    let dir = tempfile::tempdir().unwrap();

    // 1. The uninterrupted run.
    let (session_a, recording_a) = session_file(dir.path(), "whole", false);
    let status = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(["run", "--config"])
        .arg(&session_a)
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    let (order_a, poses_a) = recorded_poses(std::slice::from_ref(&recording_a));
    assert!(order_a.len() >= FRAMES - 2, "{} scans", order_a.len());

    // 2. The same session, killed part-way.
    let (session_b, recording_b) = session_file(dir.path(), "killed", true);
    let (mut child, rx) = spawn(&["run".as_ref(), "--config".as_ref(), session_b.as_os_str()]);
    let mut log = Vec::new();
    wait_line(&rx, "simulator started", &mut log);
    std::thread::sleep(Duration::from_millis(2600));
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    let (order_killed, _) = recorded_poses(std::slice::from_ref(&recording_b));
    assert!(
        order_killed.len() >= 5 && order_killed.len() < FRAMES - 5,
        "{} scans recorded before the kill",
        order_killed.len()
    );

    // 3. Resumed: it rebuilds the model, goes on, and a viewer gets all of it.
    let (mut child, rx) = spawn(&[
        "run".as_ref(),
        "--config".as_ref(),
        session_b.as_os_str(),
        "--resume".as_ref(),
    ]);
    let mut log = Vec::new();
    let line = wait_line(&rx, "resumed", &mut log);
    assert!(
        line.contains(&format!("restored={}", order_killed.len())),
        "{line}"
    );
    let line = wait_line(&rx, "serving viewers on ", &mut log);
    let addr: SocketAddr = line
        .rsplit("serving viewers on ")
        .next()
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    wait_line(&rx, "simulation ended", &mut log);
    // Let the last frames through the pipeline.
    std::thread::sleep(Duration::from_millis(1500));
    let mut client = BlockingClient::connect(addr, "", "resume-test", Duration::from_secs(20))
        .expect("the resumed daemon serves viewers");
    let mut replica = Replica::new();
    while !(replica.live && replica.complete()) {
        let message = client.next_message().unwrap().expect("stream open");
        replica.apply(message).unwrap();
        for id in replica.wanted(16) {
            client.request_scan(id).unwrap();
        }
    }
    // The level-of-detail tree took in the restored scans as well as the new ones.
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    loop {
        assert!(
            std::time::Instant::now() < deadline,
            "the tree never took in the restored scans: {:?}",
            replica.status.as_ref().and_then(|s| s.lod.clone())
        );
        let message = client.next_message().unwrap().expect("stream open");
        replica.apply(message).unwrap();
        let lod = replica.status.as_ref().and_then(|s| s.lod.clone());
        if let Some(l) = lod
            && l.pending_scans == 0
            && l.pending_tiles == 0
            && l.scans_fused as usize >= replica.model.len()
        {
            assert!(l.tiles > 0 && l.read_errors == 0, "{l:?}");
            break;
        }
    }
    Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(child.wait().unwrap().success());

    let segments = vec![
        recording_b.clone(),
        texel_daemon::resume::segment_path(&recording_b, 1),
    ];
    assert!(
        segments[1].exists(),
        "the resumed session records a new segment"
    );
    let (order_b, poses_b) = recorded_poses(&segments);

    // Nothing placed before the kill is lost, and the session went on to the end.
    assert_eq!(&order_b[..order_killed.len()], &order_killed[..]);
    let last_a = *order_a.iter().max().unwrap();
    assert_eq!(
        order_b.iter().max(),
        Some(&last_a),
        "the resumed run reached the end"
    );
    // At most the frames in flight at the kill (sent, not yet registered) are missing.
    let missing = order_a.iter().filter(|t| !poses_b.contains_key(t)).count();
    assert!(missing <= 6, "{missing} frames missing after the resume");

    // The viewer got the whole model: every recorded scan under its id, at its pose.
    assert_eq!(replica.model.len(), order_b.len());
    for (id, t) in order_b.iter().enumerate() {
        let s = replica
            .model
            .get(id as u64)
            .unwrap_or_else(|| panic!("scan {id} missing"));
        assert_eq!(s.listing.timestamp_ns, *t, "scan {id}");
        // Within the revision thresholds: a frame hanging from a keyframe is recorded
        // at the keyframe's last recorded pose (2 mm behind at most, as the frame's
        // own pose in the model may be), times the frame's pose relative to it.
        let d = distance_m(&s.world_from_scan, &poses_b[t]);
        assert!(
            d < 0.006,
            "scan {id}: the viewer's pose is {:.2} mm from the recorded one",
            d * 1e3
        );
    }

    // And it ends like the uninterrupted run: the same frames at nearly the same poses.
    let mut worst = 0.0f64;
    for (t, a) in &poses_a {
        if let Some(b) = poses_b.get(t) {
            worst = worst.max(distance_m(a, b));
        }
    }
    eprintln!(
        "resume: {} scans before the kill, {} after; {missing} missing; worst position difference \
         against the uninterrupted run {:.1} mm",
        order_killed.len(),
        order_b.len(),
        worst * 1e3
    );
    assert!(worst < 0.02, "poses differ by up to {:.1} mm", worst * 1e3);
}
