//! `texel-bench replay-memory`: the peak resident memory of a `texeld` binary
//! replaying captures as fast as it goes (`texeld replay CAPTURE --fast
//! --no-serve`). The binary is any build of the daemon, so a build of an older
//! commit can be measured on the same captures, in the same run, as this one: the
//! comparison the long-session figures are quoted against.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// A daemon binary to measure, as `LABEL=PATH` (repeatable; each replays every
    /// capture).
    #[arg(long = "texeld", required = true)]
    pub daemons: Vec<String>,
    /// A capture (MCAP) to replay (repeatable).
    #[arg(long = "capture", required = true)]
    pub captures: Vec<PathBuf>,
    /// Extra arguments for every replay (for example `--register`).
    #[arg(long, allow_hyphen_values = true)]
    pub replay_args: Vec<String>,
}

/// What one replay measured.
#[derive(Debug, Clone, Copy, Default)]
struct Run {
    wall_s: f64,
    peak_mb: f64,
    final_mb: f64,
    exit_ok: bool,
}

pub fn run(args: &Args) -> Result<()> {
    let daemons: Vec<(String, PathBuf)> = args
        .daemons
        .iter()
        .map(|d| match d.split_once('=') {
            Some((label, path)) => Ok((label.to_string(), PathBuf::from(path))),
            None => bail!("--texeld {d}: expected LABEL=PATH"),
        })
        .collect::<Result<_>>()?;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "| capture | texel frames | daemon | peak resident (MiB) | resident at the end (MiB) | wall (s) | exit |"
    );
    let _ = writeln!(out, "|---|---|---|---|---|---|---|");
    for capture in &args.captures {
        let frames = count_frames(capture)?;
        for (label, binary) in &daemons {
            let r = replay(binary, capture, &args.replay_args)?;
            let _ = writeln!(
                out,
                "| {} | {frames} | {label} | {:.0} | {:.0} | {:.1} | {} |",
                capture.file_name().map_or_else(
                    || capture.display().to_string(),
                    |n| n.to_string_lossy().into()
                ),
                r.peak_mb,
                r.final_mb,
                r.wall_s,
                if r.exit_ok { "0" } else { "failed" }
            );
            eprintln!(
                "{label} on {}: peak {:.0} MiB",
                capture.display(),
                r.peak_mb
            );
        }
    }
    print!("{out}");
    Ok(())
}

/// Replays `capture` with `binary`, sampling its memory every 100 ms until it exits.
fn replay(binary: &Path, capture: &Path, extra: &[String]) -> Result<Run> {
    let started = Instant::now();
    let mut child = Command::new(binary)
        .arg("replay")
        .arg(capture)
        .arg("--fast")
        .arg("--no-serve")
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .with_context(|| format!("starting {}", binary.display()))?;
    let status_path = format!("/proc/{}/status", child.id());
    let mut run = Run::default();
    loop {
        if let Some((rss, hwm)) = memory_mb(&status_path) {
            run.final_mb = rss;
            run.peak_mb = run.peak_mb.max(hwm).max(rss);
        }
        if let Some(status) = child.try_wait()? {
            run.exit_ok = status.success();
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    run.wall_s = started.elapsed().as_secs_f64();
    Ok(run)
}

/// `VmRSS` and `VmHWM` (the peak) of a process in MiB, from its status file.
fn memory_mb(status_path: &str) -> Option<(f64, f64)> {
    let status = std::fs::read_to_string(status_path).ok()?;
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|kb| kb.parse::<f64>().ok())
            .map(|kb| kb / 1024.0)
    };
    Some((field("VmRSS:")?, field("VmHWM:")?))
}

/// Range frames in a capture.
fn count_frames(path: &Path) -> Result<u64> {
    let mut reader = texel::capture::CaptureReader::open(path)
        .with_context(|| format!("opening {}", path.display()))?;
    let mut frames = 0u64;
    while let Some(next) = reader.next_message() {
        if let Ok(message) = next
            && message.channel.topic == texel::capture::topics::LIDAR_RANGE
        {
            frames += 1;
        }
    }
    Ok(frames)
}
