//! `texel-bench daemon --scene SCENE`: the daemon on simulator input, with a real TCP
//! client, registration on.
//!
//! 1. How fast the simulator renders here (it decides whether frames are rendered
//!    ahead of the run: the latency measured is the daemon's, not the simulator's).
//! 2. End-to-end latency at `rate_hz` (frame due -> its scan at the client, p50/p99)
//!    in the live configuration (`keep-newest`, recording on), with registration and,
//!    as the same-run baseline, with scans placed at the simulator's true poses.
//! 3. `replay --fast` of that recording, registering every frame, against real time;
//!    the baseline replays the recorded poses.
//! 4. Memory held per scan.
//!
//! Each run reports wall time and the process's CPU time (this machine is shared:
//! ratios to the same-run baseline are the figures to compare).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use texel::TexelScan;
use texel::model::ModelEvent;
use texel::wire::Message;
use tokio_util::sync::CancellationToken;

use texel_client::Client;
use texel_daemon::config::{
    LatePolicy, OverloadPolicy, RegistrationMode, ReplayConfig, SessionConfig, SimConfig,
};
use texel_daemon::pipeline::Session;
use texel_daemon::pipeline::placement::{
    Placement, PlacementFailure, Registration, ScanInput, StageOutput,
};
use texel_daemon::source::sim::build_simulator;
use texel_daemon::status::{Counter, percentiles};

/// What to simulate.
#[derive(Debug, Clone)]
pub struct SimBench {
    pub scene: PathBuf,
    pub frames: usize,
    pub rate_hz: f64,
    /// Where the recording of the latency run goes (kept for a look afterwards).
    pub work_dir: PathBuf,
}

/// CPU seconds of this process so far (all threads, ended ones too), from
/// `/proc/self/stat` (utime + stime, in USER_HZ = 100 ticks per second).
pub fn process_cpu_s() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (which may contain spaces) start at state.
    let rest = &text[text.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}

/// Places each scan at the true pose its source sent: the daemon without
/// registration's cost, for a same-run baseline.
struct TruthPlacement {
    next_id: u64,
}

impl Registration for TruthPlacement {
    fn name(&self) -> &str {
        "truth"
    }

    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput {
        match input.truth {
            Some(world_from_scan) => {
                let id = self.next_id;
                self.next_id += 1;
                StageOutput {
                    placement: Placement::Placed {
                        id,
                        degenerate: false,
                    },
                    events: vec![ModelEvent::ScanAdded {
                        id,
                        scan: Arc::clone(scan),
                        world_from_scan,
                    }],
                    recovered: 0,
                    anchors: Vec::new(),
                }
            }
            None => StageOutput {
                placement: Placement::Failed(PlacementFailure {
                    kind: "no-pose",
                    reason: "no true pose".into(),
                }),
                events: Vec::new(),
                recovered: 0,
                anchors: Vec::new(),
            },
        }
    }
}

/// One session with a client: every scan's timestamp and arrival.
struct Run {
    /// Session start to the last scan at the client.
    wall_s: f64,
    cpu_s: Option<f64>,
    arrivals: Vec<(u64, Instant)>,
    clock_origin: Option<(u64, Instant)>,
    speed: f64,
    status: texel::wire::Status,
    memory: (usize, usize),
    scans: usize,
}

impl Run {
    fn latencies_ms(&self) -> Vec<f64> {
        let Some((t0, origin)) = self.clock_origin else {
            return Vec::new();
        };
        self.arrivals
            .iter()
            .map(|&(t, at)| {
                let due = origin
                    + Duration::from_secs_f64(t.saturating_sub(t0) as f64 * 1e-9 / self.speed);
                at.saturating_duration_since(due).as_secs_f64() * 1e3
            })
            .collect()
    }

    fn counter(&self, name: &str) -> u64 {
        self.status.counters.get(name).copied().unwrap_or(0)
    }

    fn stages(&self) -> String {
        self.status
            .stages
            .iter()
            .map(|s| format!("{} {:.1}/{:.1}", s.stage, s.p50_ms, s.p99_ms))
            .collect::<Vec<_>>()
            .join(", ")
    }

    fn cpu(&self) -> String {
        self.cpu_s.map_or("n/a".into(), |c| format!("{c:.2} s CPU"))
    }
}

async fn run_session(
    config: SessionConfig,
    registration: Option<Box<dyn Registration>>,
    speed: f64,
) -> Result<Run, String> {
    config.validate("bench").map_err(|e| e.to_string())?;
    let cpu0 = process_cpu_s();
    let started = Instant::now();
    let shutdown = CancellationToken::new();
    let session = match registration {
        Some(r) => Session::start_with_registration(config, r, shutdown.clone()).await,
        None => Session::start(config, shutdown.clone()).await,
    }
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
    let hub = Arc::clone(&session.hub);
    let metrics = Arc::clone(&session.metrics);
    let summary = session.wait().await.map_err(|e| e.to_string())?;
    let wall_s = arrivals
        .last()
        .map_or(0.0, |a| a.1.duration_since(started).as_secs_f64());
    let cpu_s = match (cpu0, process_cpu_s()) {
        (Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    let clock_origin = metrics
        .sources
        .lock()
        .ok()
        .and_then(|s| s.first().and_then(|m| m.clock_origin()));
    Ok(Run {
        wall_s,
        cpu_s,
        arrivals,
        clock_origin,
        speed,
        status: summary.status,
        memory: hub.memory_bytes(),
        scans: summary.scans,
    })
}

fn sim_session(bench: &SimBench, speed: f64, record: &Path) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.sim = vec![SimConfig {
        scene: bench.scene.clone(),
        frames: Some(bench.frames),
        speed,
        prerender: true,
        late: LatePolicy::Wait,
        ..SimConfig::default()
    }];
    c.session.exit_when_sources_end = true;
    c.pipeline.registration = RegistrationMode::Register;
    c.pipeline.overload = OverloadPolicy::KeepNewest;
    c.record.path = Some(record.to_path_buf());
    c.serve.bind = std::net::SocketAddr::from(([127, 0, 0, 1], 0));
    c.status.log = false;
    c
}

fn replay_session(capture: &Path, mode: RegistrationMode) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.replay = vec![ReplayConfig {
        name: "replay".into(),
        capture: capture.to_path_buf(),
        speed: 1.0,
        fast: true,
    }];
    c.session.exit_when_sources_end = true;
    c.pipeline.registration = mode;
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.serve.bind = std::net::SocketAddr::from(([127, 0, 0, 1], 0));
    c.status.log = false;
    c
}

/// Runs the measurements and returns the report.
pub async fn run(bench: &SimBench) -> Result<String, String> {
    let mut out = String::new();
    let mut w = |s: String| {
        let _ = writeln!(out, "{s}");
    };
    let setup = SimConfig {
        scene: bench.scene.clone(),
        frames: Some(bench.frames),
        ..SimConfig::default()
    }
    .setup();
    let sim = build_simulator(&setup)?;
    let m = sim.sensor_model();
    w(format!(
        "scene {} ({} frames at {} Hz on the trajectory; lidar {}x{}, EO {}x{}); {} cores",
        bench.scene.display(),
        sim.frame_count(),
        sim.frame_rate_hz(),
        m.lidar.width,
        m.lidar.height,
        m.eo.width,
        m.eo.height,
        std::thread::available_parallelism().map_or(0, |n| n.get())
    ));

    // 1. The simulator's own speed, one frame per thread at a time as the source does.
    let sample = sim.frame_count().min(6);
    let cpu0 = process_cpu_s();
    let t = Instant::now();
    std::thread::scope(|s| {
        let sim = &sim;
        let handles: Vec<_> = (0..2)
            .map(|k| s.spawn(move || (k..sample).step_by(2).all(|i| sim.frame(i).is_ok())))
            .collect();
        handles.into_iter().all(|h| h.join().unwrap_or(false))
    });
    let render_s = t.elapsed().as_secs_f64();
    let render_fps = sample as f64 / render_s.max(1e-9);
    w(format!(
        "simulator: {sample} frames in {render_s:.2} s on 2 threads = {render_fps:.1} frames/s \
         ({:.2} s CPU); {} for {} Hz, so frames are rendered before each run (prerender) and \
         the latency below is the daemon's alone",
        cpu0.zip(process_cpu_s()).map_or(0.0, |(a, b)| b - a),
        if render_fps >= bench.rate_hz {
            "enough"
        } else {
            "not enough"
        },
        bench.rate_hz
    ));
    drop(sim);

    // 2. Latency at the rate, live configuration, registration vs truth placement.
    std::fs::create_dir_all(&bench.work_dir)
        .map_err(|e| format!("{}: {e}", bench.work_dir.display()))?;
    let speed = bench.rate_hz / setup_rate(&bench.scene)?;
    let recording = bench.work_dir.join("bench-sim.mcap");
    let baseline_recording = bench.work_dir.join("bench-sim-truth.mcap");
    let registered = run_session(sim_session(bench, speed, &recording), None, speed).await?;
    let baseline = run_session(
        sim_session(bench, speed, &baseline_recording),
        Some(Box::new(TruthPlacement { next_id: 0 })),
        speed,
    )
    .await?;
    for (name, r) in [
        ("registration", &registered),
        ("baseline: true poses, no registration", &baseline),
    ] {
        let (p50, p99) = percentiles(&r.latencies_ms());
        w(format!(
            "latency at {} Hz, {name}: p50 {p50:.1} ms, p99 {p99:.1} ms (frame due -> scan at \
             the client; {} scans of {} frames, {} skipped by overload, {} failed); run {:.2} s \
             wall, {}",
            bench.rate_hz,
            r.arrivals.len(),
            r.counter(Counter::Paired.name()),
            r.counter(Counter::SkippedByOverload.name()),
            r.counter(Counter::RegistrationFailures.name()),
            r.wall_s,
            r.cpu()
        ));
        w(format!("  stages p50/p99 ms: {}", r.stages()));
    }

    // 3. replay --fast of the recording, registering every frame; baseline: the
    // recorded poses.
    let fast = run_session(
        replay_session(&recording, RegistrationMode::Register),
        None,
        1.0,
    )
    .await?;
    let fast_base = run_session(
        replay_session(&recording, RegistrationMode::CapturePoses),
        None,
        1.0,
    )
    .await?;
    for (name, r) in [
        ("registering every frame", &fast),
        ("baseline: recorded poses", &fast_base),
    ] {
        let span_s = span_s(&r.arrivals);
        w(format!(
            "replay --fast, {name}: {} scans spanning {span_s:.2} s of capture in {:.2} s wall \
             ({}) = {:.2}x real time",
            r.arrivals.len(),
            r.wall_s,
            r.cpu(),
            span_s / r.wall_s.max(1e-9)
        ));
        w(format!("  stages p50/p99 ms: {}", r.stages()));
    }

    // 4. Memory per scan held.
    let (index_bytes, frame_bytes) = fast.memory;
    let n = fast.scans.max(1) as f64;
    w(format!(
        "memory per scan held: {:.0} KiB (model index {:.0} KiB + encoded frame \
         {:.0} KiB; the daemon holds no scan arrays)",
        (index_bytes + frame_bytes) as f64 / n / 1024.0,
        index_bytes as f64 / n / 1024.0,
        frame_bytes as f64 / n / 1024.0
    ));
    w(format!("recording kept: {}", recording.display()));
    let _ = std::fs::remove_file(&baseline_recording);
    Ok(out)
}

fn setup_rate(scene: &Path) -> Result<f64, String> {
    let scene = sims::Scene::load(scene).map_err(|e| e.to_string())?;
    Ok(scene.frame_rate_hz())
}

fn span_s(arrivals: &[(u64, Instant)]) -> f64 {
    let first = arrivals.iter().map(|a| a.0).min().unwrap_or(0);
    let last = arrivals.iter().map(|a| a.0).max().unwrap_or(0);
    (last - first) as f64 * 1e-9
}
