//! `texeld run` and `texeld replay`: the session from its config file and command-line
//! overrides, a runtime, signal handling (SIGINT/SIGTERM: stop sources, drain,
//! finalise the recording, tell clients, exit 0). Exit codes: 0 done, 1 failed while
//! running (a source or the recording failed), 2 bad configuration (the session
//! file, its options or a file it names); the reason is the last line on stderr.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use tokio_util::sync::CancellationToken;

use crate::config::{OverloadPolicy, RegistrationMode, ReplayConfig, SessionConfig};
use crate::pipeline::{Session, SessionSummary};

/// Command-line settings that override the session file.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct RunOverrides {
    /// Listen for viewers on this address (default 127.0.0.1:7878; port 0 picks one).
    #[arg(long)]
    pub bind: Option<std::net::SocketAddr>,
    /// The token viewers must present (required when not bound to loopback).
    #[arg(long)]
    pub token: Option<String>,
    /// Record the session to this capture.
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// Do not serve viewers.
    #[arg(long)]
    pub no_serve: bool,
    /// Status interval in milliseconds.
    #[arg(long)]
    pub status_interval_ms: Option<u64>,
    /// Resume the session its recording holds (after a crash or a restart): rebuild
    /// the model and the registration from the recording, then go on with live frames,
    /// recording to the next segment (`NAME.resume-1.mcap`, ...).
    #[arg(long)]
    pub resume: bool,
}

/// What `texeld replay` adds to a session.
#[derive(Debug, Clone)]
pub struct ReplayArgs {
    pub capture: PathBuf,
    pub speed: f64,
    pub fast: bool,
    /// Keep serving after the capture ends.
    pub stay: bool,
    /// How scans are placed; `None`: the session file's mode, else `auto` (capture
    /// poses when the capture has `/texel/pose`, else registration).
    pub registration: Option<RegistrationMode>,
}

/// The session config: file (or defaults), then the replay, then the overrides.
pub fn build_config(
    file: Option<&Path>,
    replay: Option<&ReplayArgs>,
    overrides: &RunOverrides,
) -> Result<SessionConfig, String> {
    let mut config = match file {
        Some(path) => SessionConfig::load(path).map_err(|e| e.to_string())?,
        None => SessionConfig::default(),
    };
    if let Some(r) = replay {
        config.source.serial.clear();
        config.source.v4l.clear();
        config.source.sim.clear();
        config.source.sim_serial.clear();
        config.source.replay = vec![ReplayConfig {
            name: "replay".into(),
            capture: r.capture.clone(),
            speed: r.speed,
            fast: r.fast,
        }];
        config.session.exit_when_sources_end = !r.stay;
        // A replay registers every frame: the file waits, nothing is skipped.
        config.pipeline.overload = OverloadPolicy::Backpressure;
        if let Some(mode) = r.registration {
            config.pipeline.registration = mode;
        } else if file.is_none() {
            config.pipeline.registration = RegistrationMode::Auto;
        }
        config.pipeline.pose_capture = None;
    }
    if let Some(bind) = overrides.bind {
        config.serve.bind = bind;
    }
    if let Some(token) = &overrides.token {
        config.serve.token = Some(token.clone());
    }
    if let Some(record) = &overrides.record {
        config.record.path = Some(record.clone());
    }
    if overrides.no_serve {
        config.serve.enabled = false;
    }
    if let Some(ms) = overrides.status_interval_ms {
        config.status.interval_ms = ms;
    }
    if overrides.resume {
        config.record.resume = true;
    }
    let origin = file.map_or_else(|| "command line".to_string(), |p| p.display().to_string());
    config.validate(&origin).map_err(|e| e.to_string())?;
    config.check_files(&origin).map_err(|e| e.to_string())?;
    Ok(config)
}

/// Zenoh's own crates log their start-up at `info`; the daemon says what matters
/// (where it publishes) itself. A `RUST_LOG` that names zenoh keeps its own levels.
const QUIET_ZENOH: &str = "zenoh=warn,zenoh_transport=warn,zenoh_link_tcp=warn,zenoh_config=warn";

/// Logs to stderr; `RUST_LOG` overrides the default `info`.
pub fn init_logging() {
    let directives = match std::env::var("RUST_LOG") {
        Ok(v) if v.contains("zenoh") => v,
        Ok(v) if !v.trim().is_empty() => format!("{v},{QUIET_ZENOH}"),
        _ => format!("info,{QUIET_ZENOH}"),
    };
    let filter = tracing_subscriber::EnvFilter::try_new(&directives)
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(format!("info,{QUIET_ZENOH}")));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// Cancels `token` on SIGINT or SIGTERM.
async fn cancel_on_signal(token: CancellationToken) {
    use tokio::signal::unix::{SignalKind, signal};
    let (Ok(mut term), Ok(mut int)) = (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
    ) else {
        tracing::error!("cannot install signal handlers; stop with SIGKILL");
        return;
    };
    let name = tokio::select! {
        _ = term.recv() => "SIGTERM",
        _ = int.recv() => "SIGINT",
        () = token.cancelled() => return,
    };
    tracing::info!("{name}: shutting down");
    token.cancel();
}

fn runtime() -> Result<tokio::runtime::Runtime, String> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("texeld")
        .build()
        .map_err(|e| format!("cannot start the runtime: {e}"))
}

/// `texeld run` / `texeld replay`.
pub fn run_command(
    file: Option<&Path>,
    replay: Option<ReplayArgs>,
    overrides: &RunOverrides,
) -> ExitCode {
    init_logging();
    let config = match build_config(file, replay.as_ref(), overrides) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("texeld: {e}");
            return ExitCode::from(2);
        }
    };
    let rt = match runtime() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("texeld: {e}");
            return ExitCode::FAILURE;
        }
    };
    let result: Result<SessionSummary, String> = rt.block_on(async {
        let shutdown = CancellationToken::new();
        tokio::spawn(cancel_on_signal(shutdown.clone()));
        let session = Session::start(config, shutdown.clone())
            .await
            .map_err(|e| e.to_string())?;
        let summary = session.wait().await.map_err(|e| e.to_string());
        shutdown.cancel();
        summary
    });
    // Blocking threads still waiting on a device are not waited for.
    rt.shutdown_timeout(std::time::Duration::from_millis(200));
    match result {
        Ok(summary) => {
            let failed: Vec<String> = summary
                .status
                .sources
                .iter()
                .filter(|s| s.state == "failed")
                .map(|s| {
                    format!(
                        "source {} failed: {}",
                        s.name,
                        s.last_error.as_deref().unwrap_or("no reason given")
                    )
                })
                .collect();
            println!(
                "texeld: {} scans in the model{}",
                summary.scans,
                summary
                    .recording
                    .as_ref()
                    .map_or(String::new(), |r| format!(
                        "; recorded {} messages to {}",
                        r.messages,
                        r.path.display()
                    ))
            );
            let recording_failed = summary.recording.and_then(|r| r.first_error);
            if let Some(e) = &recording_failed {
                eprintln!("texeld: recording failed: {e}");
            }
            // The reason comes last on stderr.
            for f in &failed {
                eprintln!("texeld: {f}");
            }
            if failed.is_empty() && recording_failed.is_none() {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            }
        }
        Err(e) => {
            eprintln!("texeld: {e}");
            ExitCode::FAILURE
        }
    }
}
