//! `texel-bench daemon CAPTURE`: what the daemon costs, measured on a capture through the
//! whole pipeline with a real TCP client: `replay --fast` speed against real time,
//! end-to-end latency (a frame is due -> its scan reaches the client) at a paced
//! replay, memory per scan held, and the texture encodings compared.

use std::fmt::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};

use texel::wire::{Message, Texture, TextureFormat};
use tokio_util::sync::CancellationToken;

use texel_client::Client;
use texel_daemon::config::{OverloadPolicy, ReplayConfig, SessionConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::status::percentiles;

fn config(capture: &Path, pace: Option<f64>) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.replay = vec![ReplayConfig {
        name: "replay".into(),
        capture: capture.to_path_buf(),
        speed: pace.unwrap_or(1.0),
        fast: pace.is_none(),
    }];
    c.session.exit_when_sources_end = true;
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.serve.bind = std::net::SocketAddr::from(([127, 0, 0, 1], 0));
    c.status.log = false;
    c
}

/// One run: every scan's timestamp and arrival at the client.
struct Run {
    started: Instant,
    arrivals: Vec<(u64, Instant)>,
    clock_origin: Option<(u64, Instant)>,
    memory: (usize, usize),
    first_scan: Option<std::sync::Arc<texel::TexelScan>>,
    stages: Vec<texel::wire::StageLatency>,
}

async fn run_once(capture: &Path, pace: Option<f64>) -> Result<Run, String> {
    let config = config(capture, pace);
    config.validate("bench").map_err(|e| e.to_string())?;
    let shutdown = CancellationToken::new();
    let started = Instant::now();
    let session = Session::start(config, shutdown.clone())
        .await
        .map_err(|e| e.to_string())?;
    let addr = session.local_addr.ok_or("the session does not serve")?;
    let mut client = Client::connect(addr, "", "bench")
        .await
        .map_err(|e| e.to_string())?;
    let mut arrivals = Vec::new();
    while let Some(message) = client.next_message().await.map_err(|e| e.to_string())? {
        match message {
            Message::ScanAdded(scan) => arrivals.push((scan.timestamp_ns, Instant::now())),
            Message::Goodbye { .. } => break,
            _ => {}
        }
    }
    let hub = std::sync::Arc::clone(&session.hub);
    let metrics = std::sync::Arc::clone(&session.metrics);
    session.wait().await.map_err(|e| e.to_string())?;
    let clock_origin = metrics
        .sources
        .lock()
        .ok()
        .and_then(|s| s.first().and_then(|m| m.clock_origin()));
    let stages = metrics.snapshot().stages;
    Ok(Run {
        started,
        arrivals,
        clock_origin,
        memory: hub.memory_bytes(),
        first_scan: first_scan(&hub),
        stages,
    })
}

/// Scan 0 as the daemon serves it, decoded.
fn first_scan(hub: &texel_daemon::hub::Hub) -> Option<std::sync::Arc<texel::TexelScan>> {
    let frame = hub.fetch_scan(0).ok()?;
    match texel::wire::decode_frame(&frame, &texel::wire::Limits::FROM_SERVER) {
        Ok(Some((texel::wire::Message::ScanAdded(wire), _))) => wire
            .into_scan()
            .ok()
            .map(|(_, scan, _)| std::sync::Arc::new(scan)),
        _ => None,
    }
}

/// Runs the measurements and returns the report.
pub async fn run(capture: &Path, speed: f64) -> Result<String, String> {
    let mut out = String::new();
    let w = |out: &mut String, s: String| {
        let _ = writeln!(out, "{s}");
    };
    w(&mut out, format!("capture: {}", capture.display()));

    // 1. As fast as possible.
    let fast = run_once(capture, None).await?;
    let scans = fast.arrivals.len();
    if scans < 2 {
        return Err(format!(
            "{scans} scans reached the client; the capture needs at least two posed frames"
        ));
    }
    let first_t = fast.arrivals.iter().map(|a| a.0).min().unwrap_or(0);
    let last_t = fast.arrivals.iter().map(|a| a.0).max().unwrap_or(0);
    let capture_s = (last_t - first_t) as f64 * 1e-9;
    let wall_s = fast
        .arrivals
        .last()
        .map_or(0.0, |a| a.1.duration_since(fast.started).as_secs_f64());
    w(
        &mut out,
        format!(
            "replay --fast: {scans} scans spanning {capture_s:.3} s of capture in {wall_s:.3} s \
             (session start to last scan at the client) = {:.2}x real time",
            if wall_s > 0.0 {
                capture_s / wall_s
            } else {
                0.0
            }
        ),
    );
    for s in &fast.stages {
        w(
            &mut out,
            format!(
                "  stage {:<10} p50 {:>7.2} ms  p99 {:>7.2} ms  ({} samples)",
                s.stage, s.p50_ms, s.p99_ms, s.samples
            ),
        );
    }
    let (index_bytes, frame_bytes) = fast.memory;
    w(
        &mut out,
        format!(
            "memory per scan held: {:.0} KiB (model index {:.0} KiB + encoded frame {:.0} KiB; the daemon holds no scan arrays)",
            (index_bytes + frame_bytes) as f64 / scans as f64 / 1024.0,
            index_bytes as f64 / scans as f64 / 1024.0,
            frame_bytes as f64 / scans as f64 / 1024.0
        ),
    );

    // 2. Paced: latency from when a frame is due to its scan at the client.
    let paced = run_once(capture, Some(speed)).await?;
    let Some((t0, origin)) = paced.clock_origin else {
        return Err("the paced replay reported no clock origin".into());
    };
    let latencies_ms: Vec<f64> = paced
        .arrivals
        .iter()
        .map(|&(t, at)| {
            let due = origin + Duration::from_secs_f64(t.saturating_sub(t0) as f64 * 1e-9 / speed);
            at.saturating_duration_since(due).as_secs_f64() * 1e3
        })
        .collect();
    let (p50, p99) = percentiles(&latencies_ms);
    w(
        &mut out,
        format!(
            "end-to-end latency at x{speed} ({} scans; frame due -> scan at the client): \
             p50 {p50:.2} ms, p99 {p99:.2} ms",
            latencies_ms.len()
        ),
    );

    // 3. Texture encodings, on the first scan's texture.
    if let Some(scan) = fast.first_scan {
        let raw = scan.texture.rgb.len();
        // The daemon's encoders, and the `image` crate's JPEG encoder as the baseline.
        let mut baseline_ms = None;
        for (name, format, daemon_encoder) in [
            ("rgb8", TextureFormat::Rgb8, true),
            ("png", TextureFormat::Png, true),
            (
                "jpeg q90 (image crate, baseline)",
                TextureFormat::Jpeg,
                false,
            ),
            ("jpeg q90 (jpeg-encoder, used)", TextureFormat::Jpeg, true),
        ] {
            let t = Instant::now();
            let reps = 5;
            let mut size = 0;
            for _ in 0..reps {
                let texture = if daemon_encoder {
                    texel_daemon::texture::encode(&scan.texture, format, 90)
                } else {
                    Texture::encode(&scan.texture, format, 90)
                };
                size = texture.map_err(|e| e.to_string())?.data.len();
            }
            let ms = t.elapsed().as_secs_f64() * 1e3 / f64::from(reps);
            let ratio = match baseline_ms {
                Some(b) if format == TextureFormat::Jpeg => {
                    format!(" ({:.2}x the baseline's speed)", b / ms)
                }
                _ => String::new(),
            };
            if !daemon_encoder {
                baseline_ms = Some(ms);
            }
            w(
                &mut out,
                format!(
                    "texture {}x{} as {name}: {size} bytes ({:.3} of raw), encode {ms:.2} ms{ratio}",
                    scan.texture.width,
                    scan.texture.height,
                    size as f64 / raw as f64
                ),
            );
        }
    }
    Ok(out)
}
