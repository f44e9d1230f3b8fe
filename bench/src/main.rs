//! `texel-bench`: benchmarks and reports across Texel's crates (the `cargo xtask`
//! manner): what the daemon and the viewer cost, what accuracy costs in time
//! (`docs/tradeoffs.md`), and calibration against the simulator's truth.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use texel_bench::calibration::commands::CalibCommand;
use texel_bench::tradeoffs;

mod zenoh_link;

#[derive(Parser)]
#[command(
    name = "texel-bench",
    version,
    about = "Texel's benchmarks and accuracy-against-time reports"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Measure the daemon: on a capture (replay --fast speed against real time,
    /// end-to-end latency at --speed, memory per scan, texture encoders), or without
    /// one on simulator input (latency at --rate-hz with registration and a truth
    /// baseline, replay --fast with registration, memory per scan).
    Daemon {
        /// The capture (MCAP) file; without one, the simulator renders --scene.
        capture: Option<PathBuf>,
        /// Replay speed for the latency run on a capture.
        #[arg(long, default_value_t = 1.0)]
        speed: f64,
        #[arg(long, default_value = "configs/scenes/lab.toml")]
        scene: PathBuf,
        #[arg(long, default_value_t = 90)]
        frames: usize,
        #[arg(long, default_value_t = 30.0)]
        rate_hz: f64,
        /// Where the simulator runs' recordings go.
        #[arg(long, default_value = "target/bench-sim")]
        work_dir: PathBuf,
    },
    /// Run the daemon over a long simulated session (the trajectory looped): resident
    /// memory, the model's memory and budget, registration latency per 1,000 frames, a
    /// late joiner's time to the whole model, `/texel/pose` messages per frame.
    LongSession(texel_bench::long_session::Args),
    /// The field display in headless Chromium (WebGPU and WebGL2) against the native
    /// viewer: wasm size, page load to the full model, frame time, bytes per scan.
    Web(texel_bench::web_viewer::Args),
    /// Peak resident memory of daemon binaries (this build or an older one) replaying
    /// captures as fast as they go.
    ReplayMemory(texel_bench::replay_memory::Args),
    /// The model through Zenoh against the TCP stream on the same simulated camera
    /// (loopback, interleaved: scans and bytes per second, latency p50/p99), and
    /// through a rate-limited link in a network namespace.
    Zenoh(zenoh_link::Args),
    /// Measure the TXL1 decoder on a hostile stream against a clean one.
    Txl1(texel_bench::txl1_decode::Args),
    /// Measure the capture reader against the mcap crate's own reader.
    CaptureRead(texel_bench::capture_read::Args),
    /// Measure the viewer: frame time and GPU memory (k-buffer against naive layers).
    Viewer(texel_bench::viewer_bench::BenchArgs),
    /// Regenerate a section of docs/tradeoffs.md (what accuracy costs in time) from
    /// measurements on simulator captures.
    #[command(subcommand)]
    Tradeoffs(TradeoffsCommand),
    /// Calibration against the simulator's truth.
    #[command(subcommand)]
    Calib(CalibCommand),
}

#[derive(Subcommand)]
enum TradeoffsCommand {
    /// Registration: accuracy against time for every knob, against Open3D.
    Registration {
        /// Fewer frames and settings, for a quick look.
        #[arg(long)]
        quick: bool,
        /// The repository root (default: the current directory).
        #[arg(long, default_value = ".")]
        repo: PathBuf,
        /// Where rendered captures are kept between runs.
        #[arg(long, default_value = "target/tradeoffs-cache")]
        cache: PathBuf,
        /// The Python with Open3D (default: the venv of scripts/setup.sh).
        #[arg(long)]
        python: Option<PathBuf>,
    },
    /// Rendering: quality against time for every mode and knob.
    Rendering(tradeoffs::rendering::TradeoffsArgs),
    /// Calibration: error against truth and time over views and LM iterations.
    Calibration(tradeoffs::calibration::Args),
    /// Retirement: held-out image quality against scans kept and memory held.
    Retirement(tradeoffs::retirement::RetirementArgs),
    /// Level of detail: build cost, size and distance from the truth per setting.
    Lod(tradeoffs::lod::LodArgs),
    /// Level of detail in the daemon: the tree's lag behind a 30 Hz walk, bytes per
    /// tile, a late joiner's first overview against fetching every scan.
    LodLive(tradeoffs::lod_live::LodLiveArgs),
    /// Level of detail in the viewer: frame time, GPU bytes, quality and popping.
    LodView(tradeoffs::lod_view::LodViewArgs),
    /// What exposure brackets buy on the high-dynamic-range scenes: saturated and
    /// black shares and log-radiance error on held-out views, LDR against HDR.
    Hdr(tradeoffs::hdr::HdrArgs),
    /// The point proxy's per-view depth maps (splatting, classification, pull-push)
    /// against the true depth on held-out views.
    Points(tradeoffs::points::PointsArgs),
    /// The merged surface on lab and courtyard: time, memory and distance from the
    /// truth per voxel size.
    Surface(tradeoffs::surface::SurfaceArgs),
    /// View-dependent texture mapping's preprocessing on lab and courtyard: time and
    /// memory of visibility, hole filling and view maps against the number of views.
    VdtmPrep(tradeoffs::surface::SurfaceArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let (name, result) = match cli.command {
        Command::Daemon {
            capture,
            speed,
            scene,
            frames,
            rate_hz,
            work_dir,
        } => {
            let result = match capture {
                Some(capture) => daemon_on_capture(&capture, speed),
                None => daemon_on_simulator(&texel_bench::daemon_sim::SimBench {
                    scene,
                    frames,
                    rate_hz,
                    work_dir,
                }),
            };
            ("daemon", result)
        }
        Command::Viewer(args) => ("viewer", texel_bench::viewer_bench::run(&args)),
        Command::LongSession(args) => ("long-session", texel_bench::long_session::run(&args)),
        Command::Web(args) => ("web", texel_bench::web_viewer::run(&args)),
        Command::ReplayMemory(args) => ("replay-memory", texel_bench::replay_memory::run(&args)),
        Command::Zenoh(args) => ("zenoh", zenoh_link::run(&args)),
        Command::Txl1(args) => ("txl1", texel_bench::txl1_decode::run(&args)),
        Command::CaptureRead(args) => ("capture-read", texel_bench::capture_read::run(&args)),
        Command::Tradeoffs(TradeoffsCommand::Registration {
            quick,
            repo,
            cache,
            python,
        }) => {
            let paths = tradeoffs::Paths { repo, cache };
            let options = tradeoffs::RunOptions { quick, python };
            (
                "tradeoffs registration",
                tradeoffs::run(tradeoffs::Section::Registration, &paths, &options),
            )
        }
        Command::Tradeoffs(TradeoffsCommand::Rendering(args)) => {
            ("tradeoffs rendering", tradeoffs::rendering::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::Calibration(args)) => {
            ("tradeoffs calibration", tradeoffs::calibration::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::Retirement(args)) => {
            ("tradeoffs retirement", tradeoffs::retirement::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::Lod(args)) => {
            ("tradeoffs lod", tradeoffs::lod::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::LodLive(args)) => {
            ("tradeoffs lod-live", tradeoffs::lod_live::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::LodView(args)) => {
            ("tradeoffs lod-view", tradeoffs::lod_view::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::Hdr(args)) => {
            ("tradeoffs hdr", tradeoffs::hdr::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::Points(args)) => {
            ("tradeoffs points", tradeoffs::points::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::Surface(args)) => {
            ("tradeoffs surface", tradeoffs::surface::run(&args))
        }
        Command::Tradeoffs(TradeoffsCommand::VdtmPrep(args)) => {
            ("tradeoffs vdtm-prep", tradeoffs::vdtm_prep::run(&args))
        }
        Command::Calib(command) => ("calib", texel_bench::calibration::commands::run(command)),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("texel-bench {name}: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?)
}

/// `texel-bench daemon CAPTURE`.
fn daemon_on_capture(capture: &std::path::Path, speed: f64) -> anyhow::Result<()> {
    let report = runtime()?
        .block_on(texel_bench::daemon_capture::run(capture, speed))
        .map_err(anyhow::Error::msg)?;
    print!("{report}");
    Ok(())
}

/// `texel-bench daemon` on simulator input.
fn daemon_on_simulator(bench: &texel_bench::daemon_sim::SimBench) -> anyhow::Result<()> {
    if !(bench.rate_hz.is_finite() && bench.rate_hz > 0.0) || bench.frames < 2 {
        anyhow::bail!("--rate-hz must be positive and --frames at least 2");
    }
    let report = runtime()?
        .block_on(texel_bench::daemon_sim::run(bench))
        .map_err(anyhow::Error::msg)?;
    print!("{report}");
    Ok(())
}
