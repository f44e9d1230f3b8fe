//! `texel-bench zenoh`: the model through Zenoh against today's TCP stream, on the
//! same simulated camera, and through a rate-limited link.
//!
//! 1. Loopback, interleaved (TCP, Zenoh, TCP, Zenoh, ...): an in-process daemon on
//!    the `lab` orbit (seed 1, frames rendered before the first is sent, then sent at
//!    the scene's 10 Hz, scans placed at the simulator's true poses, `keep-newest`, the
//!    daemon's default JPEG textures) publishes on Zenoh on loopback (peer, explicit
//!    endpoint, no multicast scouting). A viewer connected before the first scan,
//!    either a `texel_client::Client` on the daemon's TCP port or a Zenoh gateway
//!    (`texel_client::zenoh_gateway`) with a client on its port, reads until the whole
//!    model is resident: per scan, the latency from the moment the daemon's hub added
//!    it (wall clock, from a hub subscription in this process) to its data at the
//!    client. After the camera has finished, a late joiner of the same kind fetches
//!    the whole model: scans and bytes per second (bytes: what the kernel received on
//!    the viewer's link from the daemon, the TCP stream's socket or the Zenoh link's,
//!    from `ss`).
//! 2. A rate-limited link: a network namespace and a veth pair, the daemon's end
//!    shaped to `--rate-kbit` (`tc ... tbf`), the same camera's TCP stream (with a
//!    token) and Zenoh endpoint (user/password authentication), as anything beyond
//!    loopback needs, on it, and a live viewer (this binary, `--viewer-only`) inside
//!    the namespace, on each path in turn. Reported: each viewer's time to the whole
//!    model against loopback's, its bytes, and the camera's counters and stage
//!    latencies against the loopback runs': a slow viewer must never stall the
//!    camera. Without the right to make namespaces the part is skipped, saying why.
//!
//! The in-process daemon's runtime has one worker thread per core, as texeld's
//! (`--daemon-workers`). `RUST_LOG` turns on the daemon's, the gateway's and Zenoh's
//! logs (stderr).

mod loopback;
mod session;
mod shaped;
mod viewing;

use loopback::*;
use session::*;
use shaped::*;
use viewing::*;

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::io::Read as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context, Result, anyhow, bail};
use serde::{Deserialize, Serialize};
use texel::TexelScan;
use texel::model::ModelEvent;
use texel::wire::Message;
use texel::wire::kind;
use texel::wire::zenoh_keys::frame_head;
use texel_client::Client;
use texel_client::zenoh_gateway::{Gateway, GatewayOptions, split_id};
use texel_daemon::config::SessionConfig;
use texel_daemon::hub::Hub;
use texel_daemon::pipeline::Session;
use texel_daemon::pipeline::placement::{
    Placement, PlacementFailure, Registration, ScanInput, StageOutput,
};
use texel_daemon::status::percentiles;
use tokio_util::sync::CancellationToken;

const SITE: &str = "bench";
const CAMERA: &str = "cam";
/// The daemon's end of the veth pair, and the viewer's in the namespace.
const HOST_IP: &str = "10.77.0.1";
const VIEWER_IP: &str = "10.77.0.2";
const VIEWER_USER: &str = "viewer";

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Scans in the model: the first frames of the scene's trajectory (36: the whole
    /// `lab` orbit).
    #[arg(long, default_value_t = 36)]
    pub frames: usize,
    /// Runs of each path on loopback, interleaved; medians are reported (0: none, the
    /// rate-limited runs alone).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    #[arg(long, default_value = "configs/scenes/lab.toml")]
    pub scene: PathBuf,
    /// The rate-limited link's rate (kbit/s).
    #[arg(long, default_value_t = 2000)]
    pub rate_kbit: u32,
    /// Tokio worker threads of the in-process daemon (default: one per core, as
    /// texeld's runtime has).
    #[arg(long)]
    pub daemon_workers: Option<usize>,
    /// Leave out the rate-limited runs.
    #[arg(long)]
    pub no_shaped: bool,
    /// Runs of each path behind the rate-limited link, interleaved (TCP, Zenoh, ...).
    #[arg(long, default_value_t = 2)]
    pub shaped_repeats: usize,
    /// Scan requests a viewer keeps outstanding (default: the client's, 16).
    #[arg(long)]
    pub viewer_in_flight: Option<usize>,
    /// How long a Zenoh gateway waits for an answer to a query (s; default: the
    /// gateway's, 10).
    #[arg(long)]
    pub query_timeout_s: Option<f64>,
    /// How long a viewer may take to get the whole model (s).
    #[arg(long, default_value_t = 900)]
    pub timeout_s: u64,
    /// The viewer side alone (run inside the namespace by the rate-limited runs):
    /// follows the camera on `--via` and prints what it got as JSON.
    #[arg(long, hide = true)]
    pub viewer_only: bool,
    /// `--viewer-only`: the daemon's TCP stream or a Zenoh gateway.
    #[arg(long, hide = true, value_enum, default_value_t = Via::Zenoh)]
    pub via: Via,
    /// `--viewer-only`: the daemon's address (TCP) or Zenoh endpoint.
    #[arg(long, hide = true)]
    pub connect: Option<String>,
    /// `--viewer-only`: a file whose first line is the stream's token (TCP) or the
    /// password of `viewer` (Zenoh).
    #[arg(long, hide = true)]
    pub secret_file: Option<PathBuf>,
}

pub fn run(args: &Args) -> Result<()> {
    if args.frames == 0 || args.shaped_repeats == 0 || args.daemon_workers == Some(0) {
        bail!("--frames, --shaped-repeats and --daemon-workers must be positive");
    }
    if args.viewer_in_flight == Some(0) {
        bail!("--viewer-in-flight must be positive");
    }
    if args
        .query_timeout_s
        .is_some_and(|t| !(t.is_finite() && t > 0.0))
    {
        bail!("--query-timeout-s must be positive");
    }
    if std::env::var_os("RUST_LOG").is_some() {
        texel_daemon::cli::init_logging();
    }
    if args.viewer_only {
        return viewer_only(args);
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(daemon_workers(args))
        .enable_all()
        .build()?;
    let scene = args
        .scene
        .canonicalize()
        .with_context(|| format!("--scene {}", args.scene.display()))?;

    // 1. Loopback, interleaved.
    let mut runs: Vec<Run> = Vec::new();
    for round in 0..args.repeats {
        for path in [Via::Tcp, Via::Zenoh] {
            eprintln!(
                "zenoh: loopback run {} of {}, {}",
                round + 1,
                args.repeats,
                path.name()
            );
            let run = runtime.block_on(loopback_run(args, &scene, path))?;
            eprintln!("  {}", run.summary_line());
            runs.push(run);
        }
    }
    let tcp: Vec<&Run> = runs.iter().filter(|r| r.path == Via::Tcp).collect();
    let zenoh: Vec<&Run> = runs.iter().filter(|r| r.path == Via::Zenoh).collect();
    if !runs.is_empty() {
        let mut out = String::new();
        loopback_report(&mut out, args, &runs, &tcp, &zenoh);
        print!("{out}");
    }

    // 2. The rate-limited link.
    if args.no_shaped {
        println!("\nrate-limited run: left out (--no-shaped)");
        return Ok(());
    }
    let net = match Netns::create(args.rate_kbit) {
        Ok(net) => net,
        Err(e) => {
            println!("\nrate-limited run: skipped: {e:#}");
            return Ok(());
        }
    };
    eprintln!(
        "zenoh: rate-limited runs: namespace {}, {} shaped to {} kbit/s",
        net.name, net.host_if, args.rate_kbit
    );
    let mut shaped = Vec::new();
    let result = runtime.block_on(async {
        for round in 0..args.shaped_repeats {
            for via in [Via::Tcp, Via::Zenoh] {
                eprintln!(
                    "zenoh: rate-limited run {} of {}, {}",
                    round + 1,
                    args.shaped_repeats,
                    via.name()
                );
                let run = tokio::select! {
                    r = shaped_run(args, &scene, &net, via) => r?,
                    _ = tokio::signal::ctrl_c() => bail!("interrupted"),
                };
                shaped.push(run);
            }
        }
        Ok(())
    });
    let qdisc = net.qdisc_stats();
    drop(net);
    result?;
    let mut out = String::new();
    shaped_report(&mut out, args, &shaped, &qdisc, &tcp, &zenoh);
    print!("{out}");
    Ok(())
}

pub(super) fn cores() -> usize {
    std::thread::available_parallelism().map_or(0, std::num::NonZeroUsize::get)
}

/// The in-process daemon's worker threads.
pub(super) fn daemon_workers(args: &Args) -> usize {
    args.daemon_workers.unwrap_or(cores().max(1))
}

/// Which path a viewer takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Via {
    Tcp,
    Zenoh,
}

impl Via {
    pub(super) fn arg(self) -> &'static str {
        match self {
            Self::Tcp => "tcp",
            Self::Zenoh => "zenoh",
        }
    }

    pub(super) fn name(self) -> &'static str {
        match self {
            Self::Tcp => "TCP",
            Self::Zenoh => "Zenoh",
        }
    }
}

pub(super) fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

pub(super) fn secs(ns: u64) -> f64 {
    ns as f64 * 1e-9
}

pub(super) fn median(values: impl IntoIterator<Item = f64>) -> f64 {
    let mut v: Vec<f64> = values.into_iter().collect();
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}
