//! The replay source: a recorded capture's raw frames, sensor model and poses, paced
//! at real time (x1), N times real time, or as fast as the pipeline takes them.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use texel::capture::{CaptureError, CaptureEvent, CaptureReader};
use texel::{PinholeCamera, Pose, RangeFrame, SensorInfo, SensorModel};
use tokio_util::sync::CancellationToken;

use super::{FrameSink, Source, SourceError, SourceEvent, SourceFuture, SourceState};

/// How fast a capture replays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pace {
    /// `speed` times real time (1.0 = as recorded).
    Speed(f64),
    /// As fast as the pipeline accepts frames.
    Fast,
}

/// Replays one capture.
#[derive(Debug, Clone)]
pub struct ReplaySource {
    pub name: String,
    pub capture: PathBuf,
    pub pace: Pace,
}

/// The longest single sleep, so shutdown is noticed promptly.
const SLEEP_SLICE: Duration = Duration::from_millis(50);

impl Source for ReplaySource {
    fn name(&self) -> &str {
        &self.name
    }

    fn kind(&self) -> &'static str {
        "replay"
    }

    fn run(self: Box<Self>, sink: FrameSink, shutdown: CancellationToken) -> SourceFuture {
        Box::pin(async move {
            let name = self.name.clone();
            super::on_blocking_thread(&name, "replay thread", move || {
                self.replay(&sink, &shutdown)
            })
            .await?
        })
    }
}

/// Assembles the sensor model from the capture's calibration messages.
#[derive(Default)]
struct SensorParts {
    lidar: Option<PinholeCamera>,
    eo: Option<PinholeCamera>,
    eo_from_lidar: Option<Pose>,
    info: SensorInfo,
    current: Option<Arc<SensorModel>>,
}

impl SensorParts {
    /// The model if it is complete and differs from the last one sent.
    fn changed(&mut self) -> Option<Arc<SensorModel>> {
        let (lidar, eo) = (self.lidar.clone()?, self.eo.clone()?);
        let model = SensorModel::from_capture_parts(
            lidar,
            eo,
            self.eo_from_lidar.unwrap_or_else(Pose::identity),
            &self.info,
        );
        if self.current.as_deref() == Some(&model) {
            return None;
        }
        let model = Arc::new(model);
        self.current = Some(Arc::clone(&model));
        Some(model)
    }
}

/// A frame dated further than this from the one before it (ahead or back, in
/// capture time) is not waited for: the clock restarts at it. A capture's frames
/// come tens of milliseconds apart; a pause in a recording of more than this is
/// replayed without its wait, and a corrupt timestamp (years ahead) cannot stall the
/// replay.
pub const MAX_PACED_GAP_NS: u64 = 5_000_000_000;

/// Wall-clock pacing against the capture's timestamps.
struct Pacer<'a> {
    pace: Pace,
    /// A capture timestamp and the instant it was due: the clock frames are paced by.
    origin: Option<(u64, Instant)>,
    /// The previous frame's timestamp.
    last_ns: Option<u64>,
    metrics: &'a super::SourceMetrics,
    source_name: &'a str,
}

impl Pacer<'_> {
    /// Waits until the frame at `timestamp_ns` is due; true if shut down meanwhile.
    fn wait_for(&mut self, timestamp_ns: u64, shutdown: &CancellationToken) -> bool {
        let Pace::Speed(speed) = self.pace else {
            return shutdown.is_cancelled();
        };
        let previous = self.last_ns.replace(timestamp_ns);
        let out_of_pace = previous.is_some_and(|p| timestamp_ns.abs_diff(p) > MAX_PACED_GAP_NS);
        if out_of_pace {
            // Counted, named and replayed at once; the clock restarts here.
            self.metrics.add_counter("timestamps_out_of_pace", 1);
            let message = format!(
                "frame at {timestamp_ns} ns is {:.3} s from the one before it \
                 (more than {} s): replayed without waiting",
                (timestamp_ns as f64 - previous.unwrap_or(0) as f64) * 1e-9,
                MAX_PACED_GAP_NS / 1_000_000_000
            );
            tracing::warn!(source = %self.source_name, "{message}");
            self.metrics.report_error(message);
            self.origin = Some((timestamp_ns, Instant::now()));
            return shutdown.is_cancelled();
        }
        let (t0, wall0) = match self.origin {
            Some(o) => o,
            None => {
                let o = (timestamp_ns, Instant::now());
                self.origin = Some(o);
                self.metrics.set_clock_origin(o.0, o.1);
                o
            }
        };
        // Timestamps that go backwards are not waited for; forwards, at most the gap
        // limit past the previous frame (checked above), so the wait is bounded.
        let offset_s = timestamp_ns.saturating_sub(t0) as f64 * 1e-9 / speed;
        let due = wall0 + Duration::from_secs_f64(offset_s.clamp(0.0, 1e6));
        loop {
            if shutdown.is_cancelled() {
                return true;
            }
            let now = Instant::now();
            if now >= due {
                return false;
            }
            std::thread::sleep((due - now).min(SLEEP_SLICE));
        }
    }
}

impl ReplaySource {
    fn fatal(&self, message: String) -> SourceError {
        SourceError::Fatal {
            source_name: self.name.clone(),
            message,
        }
    }

    fn replay(&self, sink: &FrameSink, shutdown: &CancellationToken) -> Result<(), SourceError> {
        let metrics = sink.metrics();
        let mut reader = CaptureReader::open(&self.capture).map_err(|e| {
            metrics.set_state(SourceState::Failed);
            metrics.report_error(e.to_string());
            self.fatal(e.to_string())
        })?;
        metrics.set_state(SourceState::Running);
        tracing::info!(source = %self.name, capture = %self.capture.display(), pace = ?self.pace, "replay started");
        let mut parts = SensorParts::default();
        let mut pacer = Pacer {
            pace: self.pace,
            origin: None,
            last_ns: None,
            metrics,
            source_name: &self.name,
        };
        // A range frame waits for its intensity (same timestamp, next message).
        let mut held: Option<RangeFrame> = None;
        let send = |event: SourceEvent| sink.blocking_send(event).is_ok();
        let flush_held = |held: &mut Option<RangeFrame>, pacer: &mut Pacer| -> Option<bool> {
            let frame = held.take()?;
            if pacer.wait_for(frame.timestamp_ns, shutdown) {
                return Some(false);
            }
            metrics.add_counter("range_frames_replayed", 1);
            Some(send(SourceEvent::Range(Arc::new(frame))))
        };
        for next in reader.by_ref() {
            let event = match next {
                Ok(event) => event,
                Err(e @ CaptureError::Truncated { messages, .. }) if messages > 0 => {
                    // A recording cut short: everything before the cut was replayed,
                    // which is all there is to replay.
                    flush_held(&mut held, &mut pacer);
                    metrics.add_counter("truncated", 1);
                    metrics.report_error(e.to_string());
                    tracing::warn!(source = %self.name, "{e}");
                    break;
                }
                Err(e) if e.is_fatal() => {
                    // Everything complete before the damage was replayed.
                    flush_held(&mut held, &mut pacer);
                    metrics.report_error(e.to_string());
                    metrics.set_state(SourceState::Failed);
                    tracing::warn!(source = %self.name, "capture ends early: {e}");
                    return Err(self.fatal(e.to_string()));
                }
                Err(e @ CaptureError::Damaged { .. }) => {
                    // Read around: the frames after it still replay.
                    metrics.add_counter("damaged_stretches", 1);
                    metrics.report_error(e.to_string());
                    tracing::warn!(source = %self.name, "{e}");
                    continue;
                }
                Err(e) => {
                    metrics.add_counter("capture_errors", 1);
                    metrics.report_error(e.to_string());
                    continue;
                }
            };
            let is_intensity_for_held = matches!(
                (&event, &held),
                (CaptureEvent::Intensity { timestamp_ns, .. }, Some(h)) if *timestamp_ns == h.timestamp_ns
            );
            if !is_intensity_for_held && flush_held(&mut held, &mut pacer) == Some(false) {
                break;
            }
            let keep_going = match event {
                CaptureEvent::LidarCalibration { camera, .. } => {
                    parts.lidar = Some(camera);
                    true
                }
                CaptureEvent::EoCalibration { camera, .. } => {
                    parts.eo = Some(camera);
                    true
                }
                CaptureEvent::EoFromLidar { pose, .. } => {
                    parts.eo_from_lidar = Some(pose);
                    true
                }
                CaptureEvent::Sensor { info, .. } => {
                    parts.info = info;
                    true
                }
                CaptureEvent::Range(frame) => {
                    held = Some(frame);
                    // The model is sent once complete, before the frames taken with
                    // it (calibration messages come one by one).
                    parts.changed().is_none_or(|m| send(SourceEvent::Sensor(m)))
                }
                CaptureEvent::Intensity {
                    timestamp_ns,
                    values,
                    ..
                } => {
                    if let Some(h) = held.as_mut()
                        && h.timestamp_ns == timestamp_ns
                        && h.pixel_count() == values.len()
                    {
                        h.intensity = Some(values);
                    }
                    flush_held(&mut held, &mut pacer) != Some(false)
                }
                CaptureEvent::Eo(frame) => {
                    parts.changed().is_none_or(|m| send(SourceEvent::Sensor(m)))
                        && !pacer.wait_for(frame.timestamp_ns, shutdown)
                        && send(SourceEvent::Eo(Arc::new(frame)))
                }
                CaptureEvent::Pose {
                    topic,
                    timestamp_ns,
                    world_from_eo,
                } => send(SourceEvent::Pose {
                    topic,
                    timestamp_ns,
                    world_from_eo,
                }),
                // The session records its own registration; the reader has put each
                // exposure on its EO frame.
                CaptureEvent::Anchor(_)
                | CaptureEvent::Exposure(_)
                | CaptureEvent::Other { .. } => true,
            };
            if !keep_going {
                break;
            }
        }
        flush_held(&mut held, &mut pacer);
        let damage = metrics.counter("damaged_stretches") + metrics.counter("capture_errors");
        if metrics.counter("range_frames_replayed") == 0 && damage > 0 && !shutdown.is_cancelled() {
            // Nothing readable: the replay could not do what it was asked.
            let message = format!(
                "{}: no range frame could be read ({damage} damaged stretches or broken \
                 messages; `texeld info` lists them)",
                self.capture.display()
            );
            metrics.report_error(message.clone());
            metrics.set_state(SourceState::Failed);
            return Err(self.fatal(message));
        }
        metrics.set_state(SourceState::Ended);
        tracing::info!(source = %self.name, "replay finished");
        Ok(())
    }
}
