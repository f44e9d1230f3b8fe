//! Pipeline metrics and the periodic status: counters, per-stage latency windows
//! (p50/p99), queue depths, per-source frame rates, recording size; logged as one
//! line and broadcast to viewers as a `Status` message.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use texel::wire::{QueueStatus, RecordingStatus, SourceStatus, StageLatency, Status};

use crate::source::SourceMetrics;

/// Pipeline counters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Counter {
    Paired,
    UnpairedRange,
    UnpairedEo,
    LateRange,
    LateEo,
    /// Pairs dropped because no sensor model was known yet.
    NoSensor,
    /// Frames whose size differs from the sensor model: recorded, not paired.
    FrameSizeMismatch,
    FuseFailures,
    RegistrationFailures,
    RegistrationDegenerate,
    /// Earlier failed scans that a retry placed later.
    RegistrationRecovered,
    /// Scans whose texture could not be compressed and went out as raw RGB.
    EncodeFallbacks,
    /// Scans that could not be encoded at all (not streamed; should never happen).
    EncodeFailures,
    /// Scans the on-disk model store could not take (kept in memory instead).
    StoreErrors,
    /// Pairs not registered because registration was behind (recorded all the same).
    SkippedByOverload,
    Scans,
    PoseRevisions,
    RecordErrors,
    ClientsResynced,
    /// Viewers disconnected as too slow: fell behind too often, or stalled.
    ClientsDropped,
    /// Of those, viewers whose write made no progress within the write timeout.
    ClientsWriteTimeouts,
    /// Connections refused for their hello (invalid, wrong version or token) or for
    /// a full server.
    ClientsRefused,
    /// Connections closed for not sending a hello within the handshake timeout.
    HandshakeTimeouts,
    /// Pending handshakes closed to make room for a newer connection.
    HandshakesEvicted,
}

impl Counter {
    pub const ALL: [Counter; 24] = [
        Self::Paired,
        Self::UnpairedRange,
        Self::UnpairedEo,
        Self::LateRange,
        Self::LateEo,
        Self::NoSensor,
        Self::FrameSizeMismatch,
        Self::FuseFailures,
        Self::RegistrationFailures,
        Self::RegistrationDegenerate,
        Self::RegistrationRecovered,
        Self::EncodeFallbacks,
        Self::EncodeFailures,
        Self::StoreErrors,
        Self::SkippedByOverload,
        Self::Scans,
        Self::PoseRevisions,
        Self::RecordErrors,
        Self::ClientsResynced,
        Self::ClientsDropped,
        Self::ClientsWriteTimeouts,
        Self::ClientsRefused,
        Self::HandshakeTimeouts,
        Self::HandshakesEvicted,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Self::Paired => "paired",
            Self::UnpairedRange => "unpaired_range",
            Self::UnpairedEo => "unpaired_eo",
            Self::LateRange => "late_range",
            Self::LateEo => "late_eo",
            Self::NoSensor => "no_sensor",
            Self::FrameSizeMismatch => "frame_size_mismatch",
            Self::FuseFailures => "fuse_failures",
            Self::RegistrationFailures => "registration_failures",
            Self::RegistrationDegenerate => "registration_degenerate",
            Self::RegistrationRecovered => "registration_recovered",
            Self::EncodeFallbacks => "encode_fallbacks",
            Self::EncodeFailures => "encode_failures",
            Self::StoreErrors => "store_errors",
            Self::SkippedByOverload => "skipped_by_overload",
            Self::Scans => "scans",
            Self::PoseRevisions => "pose_revisions",
            Self::RecordErrors => "record_errors",
            Self::ClientsResynced => "clients_resynced",
            Self::ClientsDropped => "clients_dropped",
            Self::ClientsWriteTimeouts => "clients_write_timeouts",
            Self::ClientsRefused => "clients_refused",
            Self::HandshakeTimeouts => "handshake_timeouts",
            Self::HandshakesEvicted => "handshakes_evicted",
        }
    }
}

/// Pipeline stages whose latency is measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Frame received by ingest -> its pair formed.
    Sync,
    Fuse,
    Register,
    /// Wire encoding of a scan (texture compression included).
    Encode,
    /// Range frame received by ingest -> its scan published to clients.
    EndToEnd,
}

impl Stage {
    pub const ALL: [Stage; 5] = [
        Self::Sync,
        Self::Fuse,
        Self::Register,
        Self::Encode,
        Self::EndToEnd,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Self::Sync => "sync",
            Self::Fuse => "fuse",
            Self::Register => "register",
            Self::Encode => "encode",
            Self::EndToEnd => "end_to_end",
        }
    }
}

/// The most recent latency samples of one stage (a ring of fixed size).
#[derive(Debug, Clone)]
pub struct LatencyWindow {
    samples_ms: Vec<f64>,
    next: usize,
    total: u64,
}

const WINDOW: usize = 1024;

impl Default for LatencyWindow {
    fn default() -> Self {
        Self {
            samples_ms: Vec::with_capacity(WINDOW),
            next: 0,
            total: 0,
        }
    }
}

impl LatencyWindow {
    pub fn record(&mut self, d: Duration) {
        let ms = d.as_secs_f64() * 1e3;
        if self.samples_ms.len() < WINDOW {
            self.samples_ms.push(ms);
        } else {
            self.samples_ms[self.next] = ms;
        }
        self.next = (self.next + 1) % WINDOW;
        self.total += 1;
    }

    /// `(p50, p99)` in milliseconds by the nearest-rank method; zeros when empty.
    pub fn percentiles(&self) -> (f64, f64) {
        percentiles(&self.samples_ms)
    }

    pub fn total(&self) -> u64 {
        self.total
    }
}

/// `(p50, p99)` of `samples` by the nearest-rank method (`texel::stats::quantile`);
/// zeros for no samples.
pub fn percentiles(samples: &[f64]) -> (f64, f64) {
    use texel::stats::quantile;
    (quantile(samples, 0.50), quantile(samples, 0.99))
}

/// A queue whose depth the status reports.
pub struct QueueProbe {
    pub name: &'static str,
    pub capacity: usize,
    /// Current depth; `None` once the queue is gone.
    pub depth: Box<dyn Fn() -> Option<usize> + Send + Sync>,
}

/// Everything the pipeline measures, shared by its stages.
pub struct Metrics {
    started: Instant,
    counters: [AtomicU64; Counter::ALL.len()],
    stages: Mutex<[LatencyWindow; Stage::ALL.len()]>,
    pub sources: Mutex<Vec<Arc<SourceMetrics>>>,
    pub queues: Mutex<Vec<QueueProbe>>,
    pub recording: Mutex<Option<RecordingProbe>>,
    pub clients: AtomicU64,
    /// Frame counts at the previous status, for rates.
    last_rates: Mutex<(Instant, Vec<(u64, u64)>)>,
}

/// The recording's path and message count, for the status.
pub struct RecordingProbe {
    pub path: std::path::PathBuf,
    pub messages: Arc<AtomicU64>,
    pub errors: Arc<AtomicU64>,
}

impl Default for Metrics {
    fn default() -> Self {
        Self {
            started: Instant::now(),
            counters: std::array::from_fn(|_| AtomicU64::new(0)),
            stages: Mutex::new(std::array::from_fn(|_| LatencyWindow::default())),
            sources: Mutex::new(Vec::new()),
            queues: Mutex::new(Vec::new()),
            recording: Mutex::new(None),
            clients: AtomicU64::new(0),
            last_rates: Mutex::new((Instant::now(), Vec::new())),
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Metrics {
    pub fn new() -> Arc<Self> {
        Arc::new(Self::default())
    }

    fn slot(&self, c: Counter) -> &AtomicU64 {
        let i = Counter::ALL.iter().position(|&x| x == c).unwrap_or(0);
        &self.counters[i]
    }

    pub fn add(&self, c: Counter, n: u64) {
        self.slot(c).fetch_add(n, Ordering::Relaxed);
    }

    pub fn set(&self, c: Counter, v: u64) {
        self.slot(c).store(v, Ordering::Relaxed);
    }

    pub fn get(&self, c: Counter) -> u64 {
        self.slot(c).load(Ordering::Relaxed)
    }

    pub fn record_latency(&self, stage: Stage, d: Duration) {
        let i = Stage::ALL.iter().position(|&x| x == stage).unwrap_or(0);
        lock(&self.stages)[i].record(d);
    }

    pub fn latency(&self, stage: Stage) -> LatencyWindow {
        let i = Stage::ALL.iter().position(|&x| x == stage).unwrap_or(0);
        lock(&self.stages)[i].clone()
    }

    pub fn add_source(&self, m: Arc<SourceMetrics>) {
        lock(&self.sources).push(m);
    }

    pub fn add_queue(&self, probe: QueueProbe) {
        lock(&self.queues).push(probe);
    }

    /// The status now; frame rates are over the time since the previous call.
    pub fn snapshot(&self) -> Status {
        let sources = lock(&self.sources).clone();
        let now = Instant::now();
        let counts: Vec<(u64, u64)> = sources
            .iter()
            .map(|s| {
                (
                    s.range_frames.load(Ordering::Relaxed),
                    s.eo_frames.load(Ordering::Relaxed),
                )
            })
            .collect();
        let (then, previous) = {
            let mut last = lock(&self.last_rates);
            std::mem::replace(&mut *last, (now, counts.clone()))
        };
        let dt = now.duration_since(then).as_secs_f64();
        let rate = |now: u64, before: u64| {
            if dt > 0.0 {
                now.saturating_sub(before) as f64 / dt
            } else {
                0.0
            }
        };
        let sources = sources
            .iter()
            .zip(&counts)
            .enumerate()
            .map(|(i, (s, &(r, e)))| {
                let (r0, e0) = previous.get(i).copied().unwrap_or((0, 0));
                let mut counters = s.counters();
                counters.insert("range_frames".into(), r);
                counters.insert("eo_frames".into(), e);
                SourceStatus {
                    name: s.name.clone(),
                    kind: s.kind.to_string(),
                    state: s.state().name().to_string(),
                    range_fps: rate(r, r0),
                    eo_fps: rate(e, e0),
                    counters,
                    last_error: s.last_error(),
                }
            })
            .collect();
        let stages = {
            let windows = lock(&self.stages);
            Stage::ALL
                .iter()
                .zip(windows.iter())
                .map(|(s, w)| {
                    let (p50_ms, p99_ms) = w.percentiles();
                    StageLatency {
                        stage: s.name().to_string(),
                        samples: w.total(),
                        p50_ms,
                        p99_ms,
                    }
                })
                .collect()
        };
        let queues = lock(&self.queues)
            .iter()
            .map(|q| QueueStatus {
                name: q.name.to_string(),
                depth: (q.depth)().unwrap_or(0) as u64,
                capacity: q.capacity as u64,
            })
            .collect();
        let counters: BTreeMap<String, u64> = Counter::ALL
            .iter()
            .map(|&c| (c.name().to_string(), self.get(c)))
            .collect();
        let recording = lock(&self.recording).as_ref().map(|r| RecordingStatus {
            path: r.path.display().to_string(),
            bytes: std::fs::metadata(&r.path).map(|m| m.len()).unwrap_or(0),
            messages: r.messages.load(Ordering::Relaxed),
            errors: r.errors.load(Ordering::Relaxed),
        });
        Status {
            uptime_s: self.started.elapsed().as_secs_f64(),
            sources,
            stages,
            queues,
            counters,
            recording,
            clients: self.clients.load(Ordering::Relaxed),
            model: None,
            lod: None,
        }
    }
}

/// One log line for a status.
pub fn status_line(s: &Status) -> String {
    let mut line = String::new();
    for src in &s.sources {
        line.push_str(&format!(
            "{}[{}] {:.1}/{:.1} fps",
            src.name, src.state, src.range_fps, src.eo_fps
        ));
        for key in [
            "bytes_skipped",
            "crc_errors",
            "lost_frames",
            "disconnects",
            "stalls",
        ] {
            if let Some(v) = src.counters.get(key).filter(|&&v| v > 0) {
                line.push_str(&format!(" {key}={v}"));
            }
        }
        line.push_str("; ");
    }
    for st in &s.stages {
        if st.samples > 0 {
            line.push_str(&format!(
                "{} p50 {:.1} p99 {:.1} ms; ",
                st.stage, st.p50_ms, st.p99_ms
            ));
        }
    }
    for q in &s.queues {
        line.push_str(&format!("{} {}/{}; ", q.name, q.depth, q.capacity));
    }
    for (k, v) in &s.counters {
        if *v > 0 {
            line.push_str(&format!("{k}={v} "));
        }
    }
    if let Some(r) = &s.recording {
        line.push_str(&format!("; recording {} B, {} msgs", r.bytes, r.messages));
        if r.errors > 0 {
            line.push_str(&format!(", {} write errors", r.errors));
        }
    }
    if let Some(m) = &s.model {
        line.push_str(&format!(
            "; model {} served of {} ({} retired), {} in memory, {} on disk only, {:.1}/{:.0} MiB",
            m.served,
            m.scans,
            m.retired,
            m.in_memory,
            m.on_disk,
            m.memory_bytes as f64 / 1048576.0,
            m.memory_budget_bytes as f64 / 1048576.0
        ));
    }
    if let Some(l) = &s.lod {
        line.push_str(&format!(
            "; lod {} tiles (top {}), {} scans and {} tiles pending, lag {:.1} s, {:.0} B/tile, fields {:.0} MiB in memory and {:.0} MiB paged",
            l.tiles,
            l.top_lod,
            l.pending_scans,
            l.pending_tiles,
            l.lag_s,
            l.mean_tile_bytes,
            l.field_bytes as f64 / 1048576.0,
            l.field_paged_bytes as f64 / 1048576.0
        ));
        if l.field_page_errors > 0 {
            line.push_str(&format!(" ({} field page errors)", l.field_page_errors));
        }
    }
    line.push_str(&format!("; clients {}", s.clients));
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_percentiles() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentiles(&v), (50.0, 99.0));
        assert_eq!(percentiles(&[3.0]), (3.0, 3.0));
        assert_eq!(percentiles(&[]), (0.0, 0.0));
        let mut w = LatencyWindow::default();
        for i in 0..(WINDOW + 10) {
            w.record(Duration::from_millis(if i < 10 { 1000 } else { 2 }));
        }
        // The ten old slow samples were overwritten.
        assert_eq!(w.percentiles(), (2.0, 2.0));
        assert_eq!(w.total(), WINDOW as u64 + 10);
    }
}
