//! Sources: where raw frames come from. Every source (serial lidar, V4L2 camera,
//! capture replay, the simulator) implements [`Source`] and yields the same
//! frame types, so everything downstream is the same whatever the hardware.

pub mod replay;
pub mod serial;
#[cfg(feature = "sim")]
pub mod sim;
#[cfg(feature = "sim")]
pub mod sim_serial;
pub mod v4l;
pub mod v4l_convert;
pub mod v4l_exposure;

use std::collections::BTreeMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use texel::capture::PoseTopic;
use texel::{EoFrame, Pose, RangeFrame, SensorModel};
use thiserror::Error;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

/// What a source hands to the pipeline.
#[derive(Debug, Clone)]
pub enum SourceEvent {
    /// The sensor model the following frames were taken with (a replayed capture
    /// carries its own; live sessions take it from the session's sensor file).
    Sensor(Arc<SensorModel>),
    /// Frames are shared from here on: the recorder and fusion hold the same one.
    Range(Arc<RangeFrame>),
    Eo(Arc<EoFrame>),
    /// A pose the source knows (a replayed capture's `/truth/pose` or `/texel/pose`);
    /// recorded as it is, never used to place scans unless the session says so.
    Pose {
        topic: PoseTopic,
        timestamp_ns: u64,
        world_from_eo: Pose,
    },
}

/// An event tagged with the index of the source that produced it.
#[derive(Debug)]
pub struct Tagged {
    pub source: usize,
    pub event: SourceEvent,
}

/// Why a source stopped for good (a transient fault is retried inside the source and
/// only reported through its metrics).
#[derive(Debug, Error)]
pub enum SourceError {
    #[error("{source_name}: {message}")]
    Fatal {
        source_name: String,
        message: String,
    },
}

/// A source's lifecycle state, as the status reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SourceState {
    Starting,
    Running,
    /// The device went away or fell silent; the source is trying to reopen it.
    Reopening,
    /// The source has no more frames (a replay at its end).
    Ended,
    Failed,
}

impl SourceState {
    pub fn name(self) -> &'static str {
        match self {
            Self::Starting => "starting",
            Self::Running => "running",
            Self::Reopening => "reopening",
            Self::Ended => "ended",
            Self::Failed => "failed",
        }
    }
}

/// What a source counts, readable at any time by the status task.
#[derive(Debug)]
pub struct SourceMetrics {
    pub name: String,
    pub kind: &'static str,
    pub range_frames: AtomicU64,
    pub eo_frames: AtomicU64,
    inner: Mutex<MetricsInner>,
}

#[derive(Debug)]
struct MetricsInner {
    state: SourceState,
    counters: BTreeMap<String, u64>,
    last_error: Option<String>,
    clock_origin: Option<(u64, std::time::Instant)>,
}

impl SourceMetrics {
    pub fn new(name: &str, kind: &'static str) -> Arc<Self> {
        Arc::new(Self {
            name: name.to_string(),
            kind,
            range_frames: AtomicU64::new(0),
            eo_frames: AtomicU64::new(0),
            inner: Mutex::new(MetricsInner {
                state: SourceState::Starting,
                counters: BTreeMap::new(),
                last_error: None,
                clock_origin: None,
            }),
        })
    }

    fn with<R>(&self, f: impl FnOnce(&mut MetricsInner) -> R) -> R {
        // A panic elsewhere while holding the lock leaves plain counters behind, which
        // are still worth reporting.
        let mut guard = self
            .inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        f(&mut guard)
    }

    pub fn set_state(&self, state: SourceState) {
        self.with(|m| m.state = state);
    }

    pub fn state(&self) -> SourceState {
        self.with(|m| m.state)
    }

    /// Records an error for the status (the newest one wins).
    pub fn report_error(&self, message: impl Into<String>) {
        let message = message.into();
        self.with(|m| m.last_error = Some(message));
    }

    pub fn last_error(&self) -> Option<String> {
        self.with(|m| m.last_error.clone())
    }

    /// For a paced replay: the wall-clock instant at which the capture's timestamp
    /// `t0_ns` was due (frame `t` is due `(t - t0) / speed` later).
    pub fn set_clock_origin(&self, t0_ns: u64, at: std::time::Instant) {
        self.with(|m| m.clock_origin = Some((t0_ns, at)));
    }

    pub fn clock_origin(&self) -> Option<(u64, std::time::Instant)> {
        self.with(|m| m.clock_origin)
    }

    /// Sets a source-specific counter.
    pub fn set_counter(&self, name: &str, value: u64) {
        self.with(|m| {
            m.counters.insert(name.to_string(), value);
        });
    }

    pub fn add_counter(&self, name: &str, delta: u64) {
        self.with(|m| *m.counters.entry(name.to_string()).or_insert(0) += delta);
    }

    pub fn counter(&self, name: &str) -> u64 {
        self.with(|m| m.counters.get(name).copied().unwrap_or(0))
    }

    pub fn counters(&self) -> BTreeMap<String, u64> {
        self.with(|m| m.counters.clone())
    }
}

/// Where a source sends its events: a bounded channel shared by all sources. A full
/// channel makes the source wait (backpressure); the ingest stage behind it only
/// records and pairs, so it keeps up unless the disk cannot.
#[derive(Debug, Clone)]
pub struct FrameSink {
    index: usize,
    tx: mpsc::Sender<Tagged>,
    metrics: Arc<SourceMetrics>,
}

/// The pipeline has stopped listening.
#[derive(Debug, Error)]
#[error("the pipeline stopped")]
pub struct SinkClosed;

impl FrameSink {
    pub fn new(index: usize, tx: mpsc::Sender<Tagged>, metrics: Arc<SourceMetrics>) -> Self {
        Self { index, tx, metrics }
    }

    pub fn metrics(&self) -> &Arc<SourceMetrics> {
        &self.metrics
    }

    fn count(&self, event: &SourceEvent) {
        match event {
            SourceEvent::Range(_) => {
                self.metrics.range_frames.fetch_add(1, Ordering::Relaxed);
            }
            SourceEvent::Eo(_) => {
                self.metrics.eo_frames.fetch_add(1, Ordering::Relaxed);
            }
            _ => {}
        }
    }

    /// Sends from async code, waiting while the pipeline is full.
    pub async fn send(&self, event: SourceEvent) -> Result<(), SinkClosed> {
        self.count(&event);
        self.tx
            .send(Tagged {
                source: self.index,
                event,
            })
            .await
            .map_err(|_| SinkClosed)
    }

    /// Sends an event another sink sharing these metrics has counted already (a
    /// source that wraps another, like `sim-serial` around `serial`).
    pub async fn forward(&self, event: SourceEvent) -> Result<(), SinkClosed> {
        self.tx
            .send(Tagged {
                source: self.index,
                event,
            })
            .await
            .map_err(|_| SinkClosed)
    }

    /// Sends from a blocking thread, waiting while the pipeline is full.
    pub fn blocking_send(&self, event: SourceEvent) -> Result<(), SinkClosed> {
        self.count(&event);
        self.tx
            .blocking_send(Tagged {
                source: self.index,
                event,
            })
            .map_err(|_| SinkClosed)
    }
}

/// The future a running source is.
pub type SourceFuture = Pin<Box<dyn Future<Output = Result<(), SourceError>> + Send>>;

/// A producer of raw frames.
///
/// `run` yields frames into `sink` until the source ends (a replay at its end:
/// `Ok(())`), fails for good (`Err`), or `shutdown` is cancelled (`Ok(())`, promptly:
/// within a few hundred milliseconds). Transient faults (an unplugged cable, a silent
/// line) are handled inside: reported through the sink's metrics and retried.
/// Blocking sources (V4L2, file replay) run their loop on a blocking thread inside
/// the returned future.
pub trait Source: Send {
    /// The source's name in the session (status, logs).
    fn name(&self) -> &str;
    /// `serial`, `v4l`, `replay`, ...
    fn kind(&self) -> &'static str;
    fn run(self: Box<Self>, sink: FrameSink, shutdown: CancellationToken) -> SourceFuture;
}

/// Sleeps for `duration` unless shutdown comes first; true when shut down.
pub(crate) async fn sleep_or_shutdown(
    duration: std::time::Duration,
    shutdown: &CancellationToken,
) -> bool {
    tokio::select! {
        () = tokio::time::sleep(duration) => false,
        () = shutdown.cancelled() => true,
    }
}

/// Runs a source's blocking loop (a file read, a simulator, a camera's ioctls) on a
/// blocking thread; a panic of that thread becomes the source's fatal error, named by
/// `thread` ("replay thread"), instead of taking the daemon down.
pub(crate) async fn on_blocking_thread<T: Send + 'static>(
    source_name: &str,
    thread: &str,
    body: impl FnOnce() -> T + Send + 'static,
) -> Result<T, SourceError> {
    tokio::task::spawn_blocking(body)
        .await
        .map_err(|e| SourceError::Fatal {
            source_name: source_name.to_string(),
            message: format!("{thread} failed: {e}"),
        })
}
