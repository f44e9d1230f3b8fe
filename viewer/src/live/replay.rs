//! A capture replayed in-process, without a daemon: its texel frames are read in
//! order, fused (`texel::fuse`, one sensor's tables for every frame that shares it),
//! placed by the registration stage the daemon's replay uses
//! (`texel_register::placement::replay_stage`: the capture's `/texel/pose` when it
//! carries them, else registration anchored at its `/truth/pose`), and handed to the
//! viewer as `Arc<TexelScan>` in the same [`ViewerEvent`] channel a live connection
//! feeds. Nothing is encoded for a wire on the way. Scans appear as the replay
//! reaches them, paced by their timestamps, instead of after the whole file is read.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use texel::FuseConfig;
use texel::capture::{SensorCache, TexelItem, open_texel_frames};
use texel_register::RegistrationConfig;
use texel_register::placement::{CapturePoses, Placement, ScanInput, replay_stage};

use super::{ConnectionState, ViewerEvent, send};

/// The longest wait between two frames, in the capture's time: a frame dated far
/// ahead of the one before it (a damaged or hostile timestamp) is shown after this
/// instead of stalling the replay.
pub const MAX_FRAME_GAP: Duration = Duration::from_secs(5);

/// How to replay.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    pub capture: PathBuf,
    /// Multiple of real time.
    pub speed: f64,
    /// As fast as fusion and registration go.
    pub fast: bool,
}

/// Stops the replay when dropped.
pub struct ReplayHandle {
    stop: Arc<AtomicBool>,
}

impl Drop for ReplayHandle {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
    }
}

/// Starts the replay on a thread of its own.
pub fn spawn(options: ReplayOptions, tx: SyncSender<ViewerEvent>) -> ReplayHandle {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&stop);
    let name = options.capture.display().to_string();
    let spawned = std::thread::Builder::new()
        .name("texel-viewer-replay".into())
        .spawn(move || {
            let reason = match run(&options, &tx, &flag) {
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
    ReplayHandle { stop }
}

/// Replays the whole capture; the reason it ended, or why it could not start.
fn run(
    options: &ReplayOptions,
    tx: &SyncSender<ViewerEvent>,
    stop: &AtomicBool,
) -> Result<String, String> {
    let path = &options.capture;
    let shown = path.display().to_string();
    // 1. The placement: the capture's poses are read first (a replay's truth comes
    //    after the frame it belongs to, and the anchor needs it at the first scan).
    let poses = CapturePoses::from_capture(path).map_err(|e| e.to_string())?;
    let mut stage = replay_stage(poses, &RegistrationConfig::default());
    let frames = open_texel_frames(path).map_err(|e| e.to_string())?;
    // 2. A viewer joining an empty model: reset, an empty snapshot, then live scans.
    let joined = send(
        tx,
        ViewerEvent::Connection(ConnectionState::Connected {
            addr: shown.clone(),
            server_name: "in-process replay".into(),
            session_name: "replay".into(),
        }),
    ) && send(tx, ViewerEvent::Reset)
        && send(tx, ViewerEvent::SnapshotComplete { scans: 0 });
    if !joined {
        return Ok(format!("the replay of {shown} stopped: the viewer closed"));
    }
    let mut sensors = SensorCache::new();
    let fuse_config = FuseConfig::default();
    let mut pacer = Pacer::new(options);
    let (mut placed, mut failed) = (0usize, 0usize);
    for item in frames {
        if stop.load(Ordering::Acquire) {
            return Ok(format!(
                "the replay of {shown} stopped after {placed} scans"
            ));
        }
        let (pair, model) = match item {
            Ok(TexelItem::Pair { pair, sensor }) => (pair, sensor),
            Ok(TexelItem::Pose { .. } | TexelItem::Anchor(_)) => continue,
            // What was read before the damage stays in the model.
            Err(e) if e.is_fatal() => {
                return Ok(format!(
                    "the replay of {shown} ended at damage after {placed} scans: {e}"
                ));
            }
            Err(e) => {
                eprintln!("warning: {shown}: {e}");
                continue;
            }
        };
        let timestamp_ns = pair.timestamp_ns();
        // 3. Paced by the capture's clock.
        if !pacer.wait_for(timestamp_ns, stop) {
            return Ok(format!(
                "the replay of {shown} stopped after {placed} scans"
            ));
        }
        // 4. Fuse, 5. place; every change to the model goes to the viewer in order.
        let scan = match sensors.fuse(pair, &model, &fuse_config) {
            Ok(scan) => Arc::new(scan),
            Err(e) => {
                failed += 1;
                eprintln!("warning: {shown}: frame at {timestamp_ns} ns not fused: {e}");
                continue;
            }
        };
        let input = ScanInput {
            timestamp_ns,
            sensor: &model,
            truth: None,
        };
        let output = stage.register(&scan, input);
        match output.placement {
            Placement::Placed { .. } => placed += 1,
            Placement::Failed(_) => failed += 1,
        }
        for event in output.events {
            if !send(tx, ViewerEvent::model(event)) {
                return Ok(format!("the replay of {shown} stopped: the viewer closed"));
            }
        }
    }
    Ok(format!(
        "the replay of {shown} ended: {placed} scans placed, {failed} frames not placed"
    ))
}

/// Waits until a frame is due at `speed` times the capture's clock.
struct Pacer {
    /// `None`: as fast as it goes.
    speed: Option<f64>,
    started: Instant,
    /// Capture time elapsed up to the last frame (gaps capped), and its timestamp.
    capture_elapsed: Duration,
    last_ns: Option<u64>,
}

impl Pacer {
    fn new(options: &ReplayOptions) -> Self {
        let speed = (!options.fast && options.speed.is_finite() && options.speed > 0.0)
            .then_some(options.speed);
        Self {
            speed,
            started: Instant::now(),
            capture_elapsed: Duration::ZERO,
            last_ns: None,
        }
    }

    /// Sleeps until the frame at `timestamp_ns` is due; false when told to stop.
    fn wait_for(&mut self, timestamp_ns: u64, stop: &AtomicBool) -> bool {
        let Some(speed) = self.speed else {
            return true;
        };
        // A frame dated before the last one is due at once; one far ahead waits at
        // most MAX_FRAME_GAP.
        let gap_ns = self
            .last_ns
            .map_or(0, |last| timestamp_ns.saturating_sub(last));
        self.last_ns = Some(self.last_ns.map_or(timestamp_ns, |l| l.max(timestamp_ns)));
        self.capture_elapsed += Duration::from_nanos(gap_ns).min(MAX_FRAME_GAP);
        let due = self.started + self.capture_elapsed.div_f64(speed);
        loop {
            if stop.load(Ordering::Acquire) {
                return false;
            }
            let now = Instant::now();
            if now >= due {
                return true;
            }
            // Short naps, so a stop is seen within 50 ms.
            std::thread::sleep((due - now).min(Duration::from_millis(50)));
        }
    }
}
