//! Honest exit codes and pacing that data cannot stall, through the real `texeld`:
//! 2 for a bad configuration or a file it names (checked before anything starts), 1
//! for a failure while running, the reason last on stderr; a paced replay goes past a
//! frame dated years ahead.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use texel::capture::{CaptureWriter, EoEncoding, PoseTopic, RangeEncoding, WriterOptions};
use texel_e2e::captures;

const PERIOD_NS: u64 = 50_000_000;

/// Runs `texeld` with a hang guard: a run that outlives `limit` is killed and fails
/// the test.
fn texeld(args: &[&str], limit: Duration) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > limit {
            child.kill().unwrap();
            let out = child.wait_with_output().unwrap();
            panic!(
                "texeld {args:?} still running after {limit:?}:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}

fn last_stderr_line(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr)
        .lines()
        .last()
        .unwrap_or_default()
        .to_string()
}

fn path_str(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn a_paced_replay_does_not_hang_on_a_frame_dated_years_ahead() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("future.mcap");
    let model = captures::sensor();
    let mut w = CaptureWriter::create(&capture, WriterOptions::default()).unwrap();
    w.write_sensor(&model, captures::timestamp(0, PERIOD_NS))
        .unwrap();
    let frames = 10;
    for i in 0..frames {
        let t = captures::timestamp(i, PERIOD_NS);
        let (mut range, eo) = captures::frame(&model, i, t);
        if i == 4 {
            // 32 years ahead: a corrupt clock, not a pause.
            range.timestamp_ns = t + 1_000_000_000 * 3600 * 24 * 365 * 32;
        }
        w.write_range(&range, RangeEncoding::F32Metres).unwrap();
        w.write_eo(&eo, EoEncoding::Rgb8).unwrap();
        w.write_pose(PoseTopic::Truth, t, &captures::pose(i))
            .unwrap();
    }
    w.finish().unwrap();
    let out = texeld(
        &[
            "replay",
            path_str(&capture),
            "--speed",
            "1",
            "--no-serve",
            "--capture-poses",
        ],
        Duration::from_secs(60),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("replayed without waiting"), "{stderr}");
    // Every frame but the one whose halves no longer pair is placed.
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains(&format!("{} scans", frames - 1)),
        "{stdout}{stderr}"
    );

    // The same capture replayed by a session file, paced (not `fast`).
    let session = dir.path().join("paced.toml");
    std::fs::write(
        &session,
        format!(
            "[session]\nexit_when_sources_end = true\n\n\
             [pipeline]\nregistration = \"capture-poses\"\n\n\
             [[source.replay]]\nname = \"paced\"\ncapture = {:?}\nspeed = 1.0\n",
            path_str(&capture)
        ),
    )
    .unwrap();
    let out = texeld(
        &["run", "--config", path_str(&session), "--no-serve"],
        Duration::from_secs(60),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("replayed without waiting"), "{stderr}");
}

#[test]
fn a_replay_that_cannot_read_its_capture_exits_1_saying_why() {
    let dir = tempfile::tempdir().unwrap();
    let not_mcap = dir.path().join("notes.mcap");
    std::fs::write(&not_mcap, "not a capture at all\n").unwrap();
    let empty = dir.path().join("empty.mcap");
    std::fs::write(&empty, "").unwrap();
    // Every chunk damaged: read around, but nothing is left to replay.
    let ruined = dir.path().join("ruined.mcap");
    captures::write_chunked(&ruined, 12, PERIOD_NS, None, 8 << 10);
    let mut bytes = std::fs::read(&ruined).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    for c in &summary.chunk_indexes {
        let at = (c.chunk_start_offset + c.chunk_length / 2) as usize;
        bytes[at] ^= 0x5A;
    }
    std::fs::write(&ruined, bytes).unwrap();
    for (capture, why) in [
        (&not_mcap, "not an MCAP file"),
        (&empty, "truncated"),
        (&ruined, "no range frame could be read"),
    ] {
        let out = texeld(
            &["replay", path_str(capture), "--fast", "--no-serve"],
            Duration::from_secs(60),
        );
        let last = last_stderr_line(&out);
        assert_eq!(
            out.status.code(),
            Some(1),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(
            last.contains(why) && last.contains(path_str(capture)),
            "{last}"
        );
    }
}

#[test]
fn a_missing_capture_or_scene_is_a_configuration_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nowhere.mcap");
    let out = texeld(
        &["replay", path_str(&missing), "--fast", "--no-serve"],
        Duration::from_secs(60),
    );
    let last = last_stderr_line(&out);
    assert_eq!(out.status.code(), Some(2), "{last}");
    assert!(
        last.contains("source.replay[0].capture") && last.contains(path_str(&missing)),
        "{last}"
    );
    assert!(!last.contains("pose capture"), "{last}");

    // A session file naming a scene that is not there, with and without exiting when
    // its sources end: refused before anything starts either way.
    for exit_when_sources_end in [true, false] {
        let session = dir.path().join("session.toml");
        let scene = dir.path().join("no-such-scene.toml");
        std::fs::write(
            &session,
            format!(
                "[session]\nexit_when_sources_end = {exit_when_sources_end}\n\n\
                 [[source.sim]]\nname = \"sim\"\nscene = {:?}\n",
                path_str(&scene)
            ),
        )
        .unwrap();
        let out = texeld(
            &["run", "--config", path_str(&session), "--no-serve"],
            Duration::from_secs(60),
        );
        let last = last_stderr_line(&out);
        assert_eq!(out.status.code(), Some(2), "{last}");
        assert!(
            last.contains("source.sim[0].scene") && last.contains("no-such-scene.toml"),
            "{last}"
        );
    }

    // A recording into a folder that does not exist.
    let capture = dir.path().join("ok.mcap");
    captures::write(&capture, 3, PERIOD_NS, None);
    let out = texeld(
        &[
            "replay",
            path_str(&capture),
            "--fast",
            "--no-serve",
            "--out",
            path_str(&dir.path().join("missing-folder").join("out.mcap")),
        ],
        Duration::from_secs(60),
    );
    let last = last_stderr_line(&out);
    assert_eq!(out.status.code(), Some(2), "{last}");
    assert!(
        last.contains("record.path") && last.contains("missing-folder"),
        "{last}"
    );
}
