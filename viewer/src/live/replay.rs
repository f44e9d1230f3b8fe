//! A capture replayed through the daemon's own library in-process: its replay
//! source and pipeline (sync, fusion, placement at the capture's poses, encoding
//! for the wire) and its hub, whose frames are decoded and applied exactly as a
//! remote viewer would (`Replica`), feeding the same [`ViewerEvent`] channel as a
//! live connection. Scans appear as the replay reaches them instead of after the
//! whole file is loaded.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::SyncSender;

use texel::wire::{Limits, TextureFormat, decode_frame};
use texel_daemon::cli::{ReplayArgs, RunOverrides, build_config};
use texel_daemon::client::Replica;
use texel_daemon::pipeline::Session;
use tokio_util::sync::CancellationToken;

use super::connection::forward;
use super::{ConnectionState, ViewerEvent, send};

/// How to replay.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    pub capture: PathBuf,
    /// Multiple of real time.
    pub speed: f64,
    /// As fast as the pipeline goes.
    pub fast: bool,
}

/// Stops the replay when dropped.
pub struct ReplayHandle {
    shutdown: CancellationToken,
}

impl Drop for ReplayHandle {
    fn drop(&mut self) {
        self.shutdown.cancel();
    }
}

/// Starts the replay on a thread of its own (with its own runtime).
pub fn spawn(options: ReplayOptions, tx: SyncSender<ViewerEvent>) -> ReplayHandle {
    let shutdown = CancellationToken::new();
    let token = shutdown.clone();
    let name = options.capture.display().to_string();
    let spawned = std::thread::Builder::new()
        .name("texel-viewer-replay".into())
        .spawn(move || {
            let reason = match run(&options, &tx, token) {
                Ok(reason) => reason,
                Err(e) => format!("replay of {name} failed: {e}"),
            };
            let _ = send(
                &tx,
                ViewerEvent::Connection(ConnectionState::Ended { reason }),
            );
        });
    if let Err(e) = spawned {
        eprintln!("warning: cannot start the replay thread: {e}");
    }
    ReplayHandle { shutdown }
}

fn run(
    options: &ReplayOptions,
    tx: &SyncSender<ViewerEvent>,
    shutdown: CancellationToken,
) -> Result<String, String> {
    let replay = ReplayArgs {
        capture: options.capture.clone(),
        speed: options.speed,
        fast: options.fast,
        stay: false,
        registration: None,
    };
    let overrides = RunOverrides {
        no_serve: true,
        ..Default::default()
    };
    let mut config = build_config(None, Some(&replay), &overrides)?;
    // In-process: raw textures, nothing lost to compression, nothing to encode.
    config.serve.texture = TextureFormat::Rgb8;
    config.session.name = "replay".into();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .thread_name("texel-viewer-replay")
        .build()
        .map_err(|e| format!("cannot start the runtime: {e}"))?;
    let result = runtime.block_on(async move {
        let session = Session::start(config, shutdown.clone())
            .await
            .map_err(|e| e.to_string())?;
        let hub = Arc::clone(&session.hub);
        if !send(
            tx,
            ViewerEvent::Connection(ConnectionState::Connected {
                addr: options.capture.display().to_string(),
                server_name: "in-process replay".into(),
                session_name: "replay".into(),
            }),
        ) {
            shutdown.cancel();
        }
        let mut replica = Replica::new();
        // Subscribe again whenever the hub cut this feed off for lagging: a fresh
        // snapshot (starting with a reset) follows.
        'subscriptions: while !shutdown.is_cancelled() {
            let Ok(mut sub) = hub.subscribe() else {
                break;
            };
            for frame in &sub.snapshot {
                if !apply_frame(&mut replica, frame, tx)? {
                    shutdown.cancel();
                    break 'subscriptions;
                }
            }
            loop {
                let frame = tokio::select! {
                    f = sub.live.recv() => f,
                    () = shutdown.cancelled() => None,
                };
                let Some(frame) = frame else {
                    if sub.lagged.load(Ordering::Acquire) && hub.closed_reason().is_none() {
                        continue 'subscriptions;
                    }
                    break 'subscriptions;
                };
                // The consumer went away: stop the session.
                let keep = tokio::task::block_in_place(|| apply_frame(&mut replica, &frame, tx))?;
                if !keep {
                    shutdown.cancel();
                    break 'subscriptions;
                }
            }
        }
        let summary = session.wait().await.map_err(|e| e.to_string())?;
        Ok::<_, String>(format!(
            "the replay of {} ended: {} scans",
            options.capture.display(),
            summary.scans
        ))
    });
    runtime.shutdown_timeout(std::time::Duration::from_millis(200));
    result
}

/// Decodes one hub frame and forwards it; `Ok(false)` when the consumer is gone.
fn apply_frame(
    replica: &mut Replica,
    frame: &[u8],
    tx: &SyncSender<ViewerEvent>,
) -> Result<bool, String> {
    match decode_frame(frame, &Limits::FROM_SERVER) {
        Ok(Some((message, _))) => forward(replica, message, tx).map_err(|e| e.describe()),
        Ok(None) => Err("the pipeline produced a truncated frame".into()),
        Err(e) => Err(format!("the pipeline produced an invalid frame: {e}")),
    }
}
