//! `texel-bench long-session`: the daemon over a session of any length. The
//! simulator walks a scene's trajectory again and again (`loops`, as fast as the
//! pipeline goes) through the whole pipeline in this process; every second the
//! process's resident memory, the model's status and the registration stage's
//! latency are sampled. Printed: a row per `--every` frames (resident memory, model
//! memory against its budget, scans served / retired / on disk, registration p50 and
//! p99 over its recent window); written: the samples as CSV and a plot of resident
//! memory over frames. At the end, a late joiner connects over loopback and the
//! time until it has the coarse view (one scan per region) and the whole served
//! model is measured; with `--viewer-budget-mb`, a viewer under that GPU budget
//! fetches the served model and renders it (`live_viewer`). With `--record`, the
//! recording's `/texel/pose` and `/texel/anchor` messages per frame are counted.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use texel_daemon::config::{SessionConfig, SimConfig};
use texel_daemon::pipeline::Session;
use tokio_util::sync::CancellationToken;

#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// The scene whose trajectory is walked again and again.
    #[arg(long, default_value = "configs/scenes/lab-walk.toml")]
    pub scene: PathBuf,
    /// Frames to run (the trajectory is looped as often as needed).
    #[arg(long, default_value_t = 20_000)]
    pub frames: u64,
    /// A row of the table every this many frames.
    #[arg(long, default_value_t = 1000)]
    pub every: u64,
    /// `model.memory_budget_mb`.
    #[arg(long, default_value_t = 1024)]
    pub budget_mb: u64,
    /// Keep every scan served (`model.retirement.enabled = false`): the baseline.
    #[arg(long)]
    pub no_retirement: bool,
    /// Retirement settings overriding the defaults, as TOML (`docs/model.md`,
    /// "Settings"), for example `--retirement 'max_checks_per_call = 256'`.
    #[arg(long, value_name = "TOML")]
    pub retirement: Option<String>,
    /// Record the session here (to count `/texel/pose` messages per frame).
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// At the end, a viewer with this GPU budget fetches the served model and renders
    /// it (an overview and the newest scan's view): frame time and GPU memory.
    #[arg(long, value_name = "MB")]
    pub viewer_budget_mb: Option<u64>,
    /// Timed frames per view of `--viewer-budget-mb` (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub viewer_frames: u32,
    /// Where the CSV and the plot go.
    #[arg(long, default_value = "target/long-session")]
    pub out: PathBuf,
}

/// One sample.
#[derive(Debug, Clone, Copy, Default)]
struct Sample {
    elapsed_s: f64,
    frames: u64,
    rss_mb: f64,
    model_mb: f64,
    index_mb: f64,
    scans: u64,
    served: u64,
    retired: u64,
    on_disk: u64,
    register_p50_ms: f64,
    register_p99_ms: f64,
    skipped: u64,
}

/// The process's resident memory in MiB (`VmRSS`), 0 where unknown.
fn rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

fn config(args: &Args, loops: u32) -> Result<SessionConfig> {
    let mut c = SessionConfig::default();
    c.session.name = "long-session".into();
    // Kept serving after the last frame, for the late joiner; the run stops it.
    c.session.exit_when_sources_end = false;
    c.source.sim = vec![SimConfig {
        name: "sim".into(),
        scene: args.scene.clone(),
        fast: true,
        loops,
        ..SimConfig::default()
    }];
    // Every frame registered: the session waits for registration rather than skip.
    c.pipeline.overload = texel_daemon::config::OverloadPolicy::Backpressure;
    c.serve.bind = "127.0.0.1:0".parse().unwrap_or(c.serve.bind);
    c.record.path = args.record.clone();
    c.status.log = false;
    c.model.memory_budget_mb = args.budget_mb;
    if let Some(text) = &args.retirement {
        c.model.retirement = toml::from_str(text).context("--retirement")?;
    }
    c.model.retirement.enabled = !args.no_retirement;
    Ok(c)
}

fn sample(session: &Session, started: Instant) -> Sample {
    let status = session.metrics.snapshot();
    let model = session.hub.status();
    let register = status.stages.iter().find(|s| s.stage == "register");
    Sample {
        elapsed_s: started.elapsed().as_secs_f64(),
        frames: status.counters.get("paired").copied().unwrap_or(0),
        rss_mb: rss_mb(),
        model_mb: model.memory_bytes as f64 / 1048576.0,
        index_mb: session.hub.memory_bytes().0 as f64 / 1048576.0,
        scans: model.scans,
        served: model.served,
        retired: model.retired,
        on_disk: model.on_disk,
        register_p50_ms: register.map_or(0.0, |s| s.p50_ms),
        register_p99_ms: register.map_or(0.0, |s| s.p99_ms),
        skipped: status
            .counters
            .get("skipped_by_overload")
            .copied()
            .unwrap_or(0),
    }
}

/// Runs the session and prints the report.
pub fn run(args: &Args) -> Result<()> {
    if args.frames == 0 || args.every == 0 {
        bail!("--frames and --every must be positive");
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let walk = sims::Scene::load(&args.scene)
        .with_context(|| format!("loading {}", args.scene.display()))?
        .frame_count()
        .max(1) as u64;
    let loops = u32::try_from(args.frames.div_ceil(walk)).unwrap_or(u32::MAX);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let (samples, joiner, viewer) = runtime.block_on(drive(args, loops))?;
    report(args, walk, &samples, &joiner, &viewer)
}

/// What a late joiner measured.
#[derive(Debug, Clone, Default)]
struct Joiner {
    served: u64,
    coarse_scans: u64,
    to_listing_s: f64,
    to_coarse_s: f64,
    to_all_s: f64,
}

async fn drive(
    args: &Args,
    loops: u32,
) -> Result<(Vec<Sample>, Joiner, Vec<crate::live_viewer::ViewFigures>)> {
    let shutdown = CancellationToken::new();
    let session = Session::start(config(args, loops)?, shutdown.clone())
        .await
        .context("starting the session")?;
    let addr = session
        .local_addr
        .context("the session serves no viewers")?;
    let started = Instant::now();
    let mut samples = Vec::new();
    let mut interval = tokio::time::interval(Duration::from_secs(1));
    loop {
        interval.tick().await;
        let s = sample(&session, started);
        samples.push(s);
        if s.frames / args.every
            > samples
                .len()
                .checked_sub(2)
                .and_then(|i| samples.get(i))
                .map_or(0, |p| p.frames / args.every)
        {
            eprintln!(
                "{} frames, {:.0} s: resident {:.0} MiB, model {:.1} MiB",
                s.frames, s.elapsed_s, s.rss_mb, s.model_mb
            );
        }
        if s.frames >= args.frames || session.sources_done.is_cancelled() {
            break;
        }
    }
    if let Some(c) = session.hub.retirement_counts() {
        eprintln!(
            "retirement: {} new scans served, {} retired on arrival, {} retired later; \
             served again: {} after a test, {} untested (budget spent), {} on approximate offers; \
             {} kept by their own witnesses after a revision",
            c.added_served,
            c.added_retired,
            c.retired_later,
            c.restored_tested,
            c.restored_unexamined,
            c.restored_approximate,
            c.revalidated
        );
        let w = session.hub.retirement_work();
        eprintln!(
            "retirement work: {} calls, mean {:.1} us, longest {:.1} ms",
            w.calls,
            w.mean_s() * 1.0e6,
            w.max_s * 1.0e3
        );
    }
    let joiner = late_joiner(addr).await.unwrap_or_else(|e| {
        eprintln!("late joiner: {e:#}");
        Joiner::default()
    });
    let mut viewer = Vec::new();
    if let Some(budget_mb) = args.viewer_budget_mb {
        let frames = args.viewer_frames;
        viewer = tokio::task::spawn_blocking(move || {
            crate::live_viewer::measure_on_daemon(addr, budget_mb, frames)
        })
        .await
        .context("the viewer thread")?
        .unwrap_or_else(|e| {
            eprintln!("viewer: {e:#}");
            Vec::new()
        });
    }
    shutdown.cancel();
    session.wait().await.context("the session failed")?;
    Ok((samples, joiner, viewer))
}

/// A joiner's times over loopback: connect to the listings, to the first scan of
/// every region (the coarse view), to the whole served model. The joiner drops each
/// scan's data once it has arrived, so this process's memory stays the daemon's.
async fn late_joiner(addr: std::net::SocketAddr) -> Result<Joiner> {
    let started = Instant::now();
    let mut client = texel_client::Client::connect(addr, "", "long-session-joiner").await?;
    let mut replica = texel_client::Replica::new();
    let mut j = Joiner::default();
    let mut arrived = 0u64;
    loop {
        let message = tokio::time::timeout(Duration::from_secs(120), client.next_message())
            .await
            .context("the late joiner waited 120 s for a message")??
            .context("the daemon closed the connection")?;
        let added = match &message {
            texel::wire::Message::ScanAdded(w) => Some(w.id),
            _ => None,
        };
        replica.apply(message)?;
        if let Some(id) = added {
            arrived += 1;
            let _ = replica
                .model
                .apply(texel::model::ModelEvent::ScanEvicted { id });
        }
        if replica.live && j.to_listing_s == 0.0 {
            j.to_listing_s = started.elapsed().as_secs_f64();
            j.served = replica.model.len() as u64;
            j.coarse_scans = coarse_count(&replica);
        }
        for id in replica.wanted(16) {
            client.request_scan(id).await?;
        }
        if replica.live {
            if j.to_coarse_s == 0.0 && arrived >= j.coarse_scans {
                j.to_coarse_s = started.elapsed().as_secs_f64();
            }
            if replica.complete() {
                j.to_all_s = started.elapsed().as_secs_f64();
                return Ok(j);
            }
        }
    }
}

/// The scans of the coarse view: one per region, which the daemon lists first.
fn coarse_count(replica: &texel_client::Replica) -> u64 {
    use std::collections::HashSet;
    let regions: HashSet<[i64; 3]> = replica
        .model
        .scans()
        .iter()
        .map(|s| {
            let l = &s.listing;
            let c = nalgebra::Point3::new(
                0.5 * f64::from(l.bounds_min_m[0] + l.bounds_max_m[0]),
                0.5 * f64::from(l.bounds_min_m[1] + l.bounds_max_m[1]),
                0.5 * f64::from(l.bounds_min_m[2] + l.bounds_max_m[2]),
            );
            let w = s.world_from_scan * c;
            let r = texel_daemon::serve_order::REGION_M;
            [
                (w.x / r).floor() as i64,
                (w.y / r).floor() as i64,
                (w.z / r).floor() as i64,
            ]
        })
        .collect();
    regions.len() as u64
}

fn report(
    args: &Args,
    walk: u64,
    samples: &[Sample],
    joiner: &Joiner,
    viewer: &[crate::live_viewer::ViewFigures],
) -> Result<()> {
    let mut out = String::new();
    let last = samples.last().copied().unwrap_or_default();
    let _ = writeln!(
        out,
        "long session: {} ({walk} frames a walk, looped), {} frames in {:.0} s, budget {} MiB, retirement {}",
        args.scene.display(),
        last.frames,
        last.elapsed_s,
        args.budget_mb,
        match (&args.retirement, args.no_retirement) {
            (_, true) => "off".to_string(),
            (Some(text), false) => format!("on ({})", text.trim()),
            (None, false) => "on".to_string(),
        }
    );
    let _ = writeln!(
        out,
        "| frames | resident (MiB) | model in memory (MiB) | of which index (MiB) | scans | served | retired | on disk only | register p50 / p99 (ms) | skipped |"
    );
    let _ = writeln!(out, "|---|---|---|---|---|---|---|---|---|---|");
    let mut next = args.every;
    for s in samples {
        if s.frames >= next || std::ptr::eq(s, samples.last().unwrap_or(s)) {
            let _ = writeln!(
                out,
                "| {} | {:.0} | {:.1} | {:.1} | {} | {} | {} | {} | {:.1} / {:.1} | {} |",
                s.frames,
                s.rss_mb,
                s.model_mb,
                s.index_mb,
                s.scans,
                s.served,
                s.retired,
                s.on_disk,
                s.register_p50_ms,
                s.register_p99_ms,
                s.skipped
            );
            while next <= s.frames {
                next += args.every;
            }
        }
    }
    let peak = samples.iter().map(|s| s.rss_mb).fold(0.0, f64::max);
    let _ = writeln!(out, "peak resident: {peak:.0} MiB");
    let _ = writeln!(
        out,
        "late joiner after {} frames: {} scans served; listings in {:.2} s, the coarse view ({} scans, one per region) in {:.2} s, the whole model in {:.2} s",
        last.frames,
        joiner.served,
        joiner.to_listing_s,
        joiner.coarse_scans,
        joiner.to_coarse_s,
        joiner.to_all_s
    );
    for v in viewer {
        let _ = writeln!(
            out,
            "viewer, {}: {} scans known, {} needed, {} resident, {} left out; GPU {:.1} of {:.0} MiB; {} drawn; frame {:.0} ms ({}x{}, blended, median of {})",
            v.view,
            v.known,
            v.needed,
            v.resident,
            v.left_out,
            v.used_mib,
            v.budget_mib,
            v.drawn,
            v.frame_ms,
            crate::live_viewer::WIDTH,
            crate::live_viewer::HEIGHT,
            args.viewer_frames
        );
    }
    if let Some(path) = &args.record {
        let _ = writeln!(
            out,
            "recording, by the frames recorded so far: /texel/pose and /texel/anchor messages"
        );
        for c in count_poses(path)? {
            let _ = writeln!(
                out,
                "  {:>6} frames: {:>7} /texel/pose ({:.2} per frame), {:>7} /texel/anchor ({:.2} per frame)",
                c.frames,
                c.poses,
                c.poses as f64 / c.frames.max(1) as f64,
                c.anchors,
                c.anchors as f64 / c.frames.max(1) as f64
            );
        }
    }
    print!("{out}");
    write_csv(&args.out.join("samples.csv"), samples)?;
    let stem = args.out.join("resident-memory");
    texel_plots::write_lines(
        &stem,
        "texeld resident memory over a long session",
        "frames",
        "MiB",
        &[
            texel_plots::Line {
                name: "resident".into(),
                points: samples
                    .iter()
                    .map(|s| (s.frames as f64, s.rss_mb))
                    .collect(),
            },
            texel_plots::Line {
                name: "model in memory".into(),
                points: samples
                    .iter()
                    .map(|s| (s.frames as f64, s.model_mb))
                    .collect(),
            },
            texel_plots::Line {
                name: "budget".into(),
                points: vec![
                    (0.0, args.budget_mb as f64),
                    (last.frames as f64, args.budget_mb as f64),
                ],
            },
        ],
    )?;
    println!(
        "samples: {}; plot: {}",
        args.out.join("samples.csv").display(),
        stem.with_extension("png").display()
    );
    Ok(())
}

fn write_csv(path: &Path, samples: &[Sample]) -> Result<()> {
    let mut csv = String::from(
        "elapsed_s,frames,rss_mb,model_mb,index_mb,scans,served,retired,on_disk,register_p50_ms,register_p99_ms,skipped\n",
    );
    for s in samples {
        let _ = writeln!(
            csv,
            "{:.1},{},{:.1},{:.2},{:.2},{},{},{},{},{:.2},{:.2},{}",
            s.elapsed_s,
            s.frames,
            s.rss_mb,
            s.model_mb,
            s.index_mb,
            s.scans,
            s.served,
            s.retired,
            s.on_disk,
            s.register_p50_ms,
            s.register_p99_ms,
            s.skipped
        );
    }
    std::fs::write(path, csv).with_context(|| format!("writing {}", path.display()))
}

/// Pose messages recorded up to a point of a recording.
#[derive(Debug, Clone, Copy, Default)]
struct PoseCount {
    /// Range frames recorded so far.
    frames: u64,
    poses: u64,
    anchors: u64,
}

/// `/texel/pose` and `/texel/anchor` messages in a recording, counted in file order
/// up to 1,000, 5,000, 10,000 and 20,000 range frames and at the end: whether the
/// rate per frame grows with the session.
fn count_poses(path: &Path) -> Result<Vec<PoseCount>> {
    const AT: [u64; 4] = [1_000, 5_000, 10_000, 20_000];
    let mut reader = texel::capture::CaptureReader::open(path)?;
    let mut count = PoseCount::default();
    let mut counts = Vec::new();
    while let Some(next) = reader.next_message() {
        let Ok(message) = next else { continue };
        match message.channel.topic.as_str() {
            texel::capture::topics::LIDAR_RANGE => {
                if AT.contains(&count.frames) {
                    counts.push(count);
                }
                count.frames += 1;
            }
            texel::capture::topics::TEXEL_POSE => count.poses += 1,
            texel::capture::topics::TEXEL_ANCHOR => count.anchors += 1,
            _ => {}
        }
    }
    counts.push(count);
    Ok(counts)
}
