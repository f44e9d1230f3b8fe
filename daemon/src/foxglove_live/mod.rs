//! The live session offered to the Foxglove app (`[foxglove]`, `docs/daemon.md`,
//! "Live in Foxglove"): the foxglove crate's WebSocket server, in a
//! `foxglove::Context` of the session's own, with the recording's topics and schemas
//! (`/lidar/calibration`, `/eo/calibration`, `/tf_static`, `/texel/sensor`,
//! `/lidar/range`, `/eo/image`, `/truth/pose`, `/texel/pose`; `frames.rs`), so a
//! layout made on a recording works live, and two live-only topics: `/texel/scan`,
//! the served model as scene entities holding each scan's textured mesh as a binary
//! glTF, and `/texel/status` (`scenes.rs`).
//!
//! Nothing here can slow the camera down: raw frames and poses come through the live
//! tap (`pipeline::tap`, which drops rather than waits), the model and the status
//! through a hub subscription (the hub's bounded queue, which cuts a slow subscriber
//! off and resynchronises it), and the foxglove crate queues each client's messages
//! in a bounded queue of `client_queue` messages that drops the oldest to make room.
//! Building a scan's glTF happens on the scene thread, and only while someone
//! subscribes to `/texel/scan`.

mod channels;
mod frames;
mod model;
mod scenes;

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use foxglove::Context;
use thiserror::Error;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

pub use channels::{STATUS_SCHEMA_NAME, live_topics};
pub use model::GLB_MEDIA_TYPE;

use crate::config::FoxgloveSection;
use crate::hub::Hub;
use crate::pipeline::tap::{self, Tap, TapCounters};
use crate::status::Metrics;

#[derive(Debug, Error)]
pub enum FoxgloveLiveError {
    #[error("foxglove: channel {topic}: {message}")]
    Channel { topic: String, message: String },
    #[error("foxglove: cannot listen on {addr}: {message}")]
    Bind { addr: SocketAddr, message: String },
    #[error("foxglove: cannot start a thread: {0}")]
    Thread(String),
}

/// What the Foxglove server did, in `/texel/status` under `foxglove`.
#[derive(Debug, Default)]
pub struct LiveCounters {
    /// Range and EO frames sent (to at least one subscriber).
    pub frames_sent: AtomicU64,
    /// Frames (or sensor facts) that could not become a message.
    pub frame_errors: AtomicU64,
    /// Scan models (glTF) built.
    pub scan_models: AtomicU64,
    /// Time spent building them (the hub's frame read back when need be, decoded,
    /// made a glTF), microseconds.
    pub scan_model_micros: AtomicU64,
    /// Their glTF bytes.
    pub scan_model_bytes: AtomicU64,
    /// Scans whose model could not be built (not sent).
    pub scan_model_errors: AtomicU64,
    /// Times the hub cut the scene subscriber off for being slow (it resynchronised).
    pub resyncs: AtomicU64,
}

impl LiveCounters {
    fn to_json(&self, tap: &TapCounters) -> serde_json::Value {
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let models = get(&self.scan_models);
        let mean = |total: u64, scale: f64| {
            if models == 0 {
                0.0
            } else {
                total as f64 / models as f64 / scale
            }
        };
        serde_json::json!({
            "frames_sent": get(&self.frames_sent),
            "frames_dropped": get(&tap.frames_dropped),
            "records_dropped": get(&tap.records_dropped),
            "frame_errors": get(&self.frame_errors),
            "scan_models": models,
            "scan_model_mean_ms": mean(get(&self.scan_model_micros), 1e3),
            "scan_model_mean_bytes": mean(get(&self.scan_model_bytes), 1.0).round(),
            "scan_model_errors": get(&self.scan_model_errors),
            "resyncs": get(&self.resyncs),
        })
    }
}

/// New `/texel/scan` subscribers waiting for the scene thread at most.
const JOIN_QUEUE: usize = 64;

/// Inputs waiting for the scene thread at most (the hub's queue is behind them).
const SCENE_QUEUE: usize = 16;

/// The running Foxglove server of a session. Dropping it stops the server.
pub struct FoxgloveLive {
    local_addr: SocketAddr,
    /// Kept for [`Self::tap`]; let go in [`Self::wait`], so the frames thread ends
    /// with the pipeline's own copies.
    tap: Option<Tap>,
    stop: CancellationToken,
    supervisor: Option<JoinHandle<()>>,
}

/// `ws://HOST:PORT` for an address (IPv6 in brackets).
pub fn websocket_url(addr: SocketAddr) -> String {
    format!("ws://{addr}")
}

impl FoxgloveLive {
    /// Starts the server on `config.bind` (port 0: a free port, in
    /// [`Self::local_addr`]) and the threads that feed it from `hub` and from the
    /// tap (give [`Self::tap`] to ingest and the worker). It stops when the hub
    /// closes (the session's end), or when dropped.
    pub async fn start(
        config: &FoxgloveSection,
        session_name: &str,
        hub: Arc<Hub>,
        metrics: &Metrics,
    ) -> Result<Self, FoxgloveLiveError> {
        let ctx = Context::new();
        let channels = Arc::new(channels::Channels::new(&ctx)?);
        let (joins_tx, joins_rx) = mpsc::channel(JOIN_QUEUE);
        let listener = channels::Listener {
            channels: Arc::clone(&channels),
            joins: joins_tx,
        };
        let counters = Arc::new(LiveCounters::default());
        let (tap, tap_rx) = tap::tap();
        let tap_counters = Arc::clone(&tap_rx.counters);
        let thread = |name: &str| std::thread::Builder::new().name(name.into());
        let frames = {
            let (channels, counters) = (Arc::clone(&channels), Arc::clone(&counters));
            thread("texel-foxglove")
                .spawn(move || frames::run(tap_rx, channels, counters))
                .map_err(|e| FoxgloveLiveError::Thread(e.to_string()))?
        };
        let (scene_tx, scene_rx) = mpsc::channel(SCENE_QUEUE);
        let scenes = scenes::Scenes::new(
            Arc::clone(&hub),
            Arc::clone(&channels),
            Arc::clone(&counters),
            tap_counters,
        );
        let scene_thread = thread("texel-foxglove-scenes")
            .spawn(move || scenes.run(scene_rx))
            .map_err(|e| FoxgloveLiveError::Thread(e.to_string()))?;
        // The threads first: a server that started and was then given up would run
        // on (the foxglove crate keeps a server whose handle is dropped).
        let addr = config.bind;
        let server = ctx
            .websocket_server()
            .name(format!("texeld: {session_name}"))
            .bind(addr.ip().to_string(), addr.port())
            .message_backlog_size(config.client_queue)
            .listener(Arc::new(listener))
            .start()
            .await
            .map_err(|e| FoxgloveLiveError::Bind {
                addr,
                message: e.to_string(),
            })?;
        let local_addr = SocketAddr::new(addr.ip(), server.port());
        let url = websocket_url(local_addr);
        if addr.ip().is_unspecified() {
            tracing::info!(
                "Foxglove: {url} (every interface: open it by one of this machine's \
                 addresses) in the Foxglove app: Open connection, Foxglove WebSocket"
            );
        } else {
            tracing::info!(
                "Foxglove: {url}; in the Foxglove app: Open connection, Foxglove WebSocket, \
                 {url} (or {})",
                server.app_url()
            );
        }
        if !addr.ip().is_loopback() {
            tracing::warn!(
                "Foxglove: {url} is reachable beyond this machine, without authentication \
                 (foxglove.allow_remote)"
            );
        }

        metrics.add_queue(tap.probe("foxglove"));
        let stop = CancellationToken::new();
        let forwarder = tokio::spawn(scenes::forward(
            hub,
            scene_tx,
            joins_rx,
            stop.clone(),
            Arc::clone(&counters),
        ));
        let supervisor = {
            let stop = stop.clone();
            tokio::spawn(async move {
                // The forwarder ends when the hub closes (or on `stop`).
                let mut forwarder = forwarder;
                tokio::select! {
                    _ = &mut forwarder => {}
                    () = stop.cancelled() => forwarder.abort(),
                }
                // The scene thread sends what it was handed; the frames thread ends
                // with the pipeline's producers of the tap.
                let joined = tokio::task::spawn_blocking(move || {
                    (scene_thread.join().is_ok(), frames.join().is_ok())
                });
                if let Ok(Ok((scenes_ok, frames_ok))) =
                    tokio::time::timeout(Duration::from_secs(2), joined).await
                    && !(scenes_ok && frames_ok)
                {
                    tracing::error!("foxglove: a thread panicked");
                }
                server.stop().wait().await;
                tracing::info!("Foxglove: {url} closed");
            })
        };
        Ok(Self {
            local_addr,
            tap: Some(tap),
            stop,
            supervisor: Some(supervisor),
        })
    }

    /// Where Foxglove connects (the real port when bound to port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The tap the pipeline offers its records to.
    pub fn tap(&self) -> Option<Tap> {
        self.tap.clone()
    }

    /// Waits (at most `timeout`) for the server to stop by itself once the session
    /// has ended (the hub closed), then stops it.
    pub async fn wait(mut self, timeout: Duration) {
        self.tap = None;
        if let Some(mut supervisor) = self.supervisor.take()
            && tokio::time::timeout(timeout, &mut supervisor)
                .await
                .is_err()
        {
            self.stop.cancel();
            // The supervisor's own waits are bounded (2 s for the threads).
            let _ = tokio::time::timeout(Duration::from_secs(5), supervisor).await;
        }
    }
}

impl Drop for FoxgloveLive {
    fn drop(&mut self) {
        // A session that ends without `wait` (or fails to start) stops its server.
        if self.supervisor.is_some() {
            self.stop.cancel();
        }
    }
}
