//! The model as it reaches a viewer: [`ViewerEvent`]s (model changes, resets,
//! connection state, the daemon's status) on one bounded channel, fed by a live
//! connection to a daemon ([`connection`]), by a capture replayed in-process
//! ([`replay`]: fused and placed here, no daemon), or by a loaded capture. The window
//! and the headless snapshot writer consume the same channel.

pub mod connection;
pub mod eo_fit;
pub mod fetch;
#[cfg(not(target_arch = "wasm32"))]
pub mod replay;
pub mod snapshots;
pub mod transport;

use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::{Duration, Instant};

use texel::model::{Model, ModelEvent};
use texel::wire::Status;

/// How many events may wait for the consumer. A full channel makes the producer
/// wait (the network thread stops reading; the daemon then resynchronises or drops
/// this viewer by its slow-client policy), except for status messages, which are
/// skipped.
pub const EVENT_QUEUE: usize = 256;

/// How many requests from the window may wait for the connection thread.
pub const COMMAND_QUEUE: usize = 64;

/// What the window asks of its live source.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SourceCommand {
    /// Send scan `id`'s data (the source answers with the scan or says it is
    /// unavailable). `generation`: how many [`ViewerEvent::Reset`]s the asker had
    /// applied; a request made before the latest reset concerns a model that is gone
    /// and is dropped.
    RequestScan {
        id: texel::model::ScanId,
        generation: u64,
    },
}

/// The state of a live connection, as the overlay shows it.
#[derive(Debug, Clone, PartialEq)]
pub enum ConnectionState {
    Connecting {
        addr: String,
        attempt: u32,
    },
    Connected {
        addr: String,
        server_name: String,
        session_name: String,
    },
    /// Lost; trying again after `retry_in`.
    Retrying {
        addr: String,
        reason: String,
        retry_in: Duration,
    },
    /// The source will send nothing more (a replay ended, the viewer was refused).
    Ended {
        reason: String,
    },
}

impl ConnectionState {
    pub fn describe(&self) -> String {
        match self {
            Self::Connecting { addr, attempt } => {
                format!("connecting to {addr} (attempt {attempt})")
            }
            Self::Connected {
                addr,
                server_name,
                session_name,
            } => format!("connected to {addr}: {server_name}, session {session_name:?}"),
            Self::Retrying {
                addr,
                reason,
                retry_in,
            } => format!(
                "{addr}: {reason}; retrying in {:.1} s",
                retry_in.as_secs_f64()
            ),
            Self::Ended { reason } => format!("ended: {reason}"),
        }
    }
}

/// One thing a viewer learns about its model.
#[derive(Debug, Clone)]
pub enum ViewerEvent {
    /// A scan joined or moved. `received` is when its message was complete, for the
    /// stream latency the overlay shows.
    Model {
        event: ModelEvent,
        received: Instant,
    },
    /// The model is cleared; a snapshot follows.
    Reset,
    /// The snapshot is complete: the model matches the source's as of joining.
    SnapshotComplete {
        scans: u64,
    },
    Status {
        status: Box<Status>,
        received: Instant,
    },
    Connection(ConnectionState),
    /// The source cannot give a scan that was asked for.
    ScanUnavailable {
        id: texel::model::ScanId,
        reason: String,
    },
    /// The source's EO response curve (what makes exposed frames radiance).
    EoResponse(Box<texel::radiance::EoResponse>),
}

impl ViewerEvent {
    pub fn model(event: ModelEvent) -> Self {
        Self::Model {
            event,
            received: Instant::now(),
        }
    }
}

/// Sends model and connection events in order (waiting for room), status events
/// only when there is room. Returns false once the consumer is gone.
pub fn send(tx: &SyncSender<ViewerEvent>, event: ViewerEvent) -> bool {
    match event {
        ViewerEvent::Status { .. } => {
            !matches!(tx.try_send(event), Err(TrySendError::Disconnected(_)))
        }
        other => tx.send(other).is_ok(),
    }
}

/// Feeds a whole model (a loaded capture) into a channel, as a snapshot.
pub fn spawn_model_feed(model: Model) -> Receiver<ViewerEvent> {
    let (tx, rx) = std::sync::mpsc::sync_channel(EVENT_QUEUE);
    std::thread::spawn(move || {
        let count = model.len() as u64;
        for event in model.snapshot() {
            if !send(&tx, ViewerEvent::model(event)) {
                return;
            }
        }
        let _ = send(&tx, ViewerEvent::SnapshotComplete { scans: count });
    });
    rx
}

/// Applies viewer events to a model; what a consumer without a GPU needs (the
/// snapshot writer, tests). Returns whether the model changed.
pub fn apply_to_model(model: &mut Model, event: &ViewerEvent) -> bool {
    match event {
        ViewerEvent::Model { event, .. } => model.apply(event.clone()).is_ok(),
        ViewerEvent::Reset => {
            *model = Model::new();
            true
        }
        _ => false,
    }
}

/// The vertical field of view (degrees) of the EO camera that textured `scan`,
/// estimated from its vertices and texture coordinates (a scan on the wire does not
/// carry the camera model): the least-squares focal length of
/// `v_px - h/2 = f_y * y / z` over the textured vertices. `None` when the scan has
/// too few usable vertices or the fit is degenerate.
pub fn fov_y_deg_of_scan(scan: &texel::TexelScan) -> Option<f64> {
    let h = f64::from(scan.texture.height);
    if h < 1.0 {
        return None;
    }
    let (mut sxy, mut sxx, mut n) = (0.0f64, 0.0f64, 0usize);
    for ((v, t), textured) in scan
        .vertices
        .iter()
        .zip(&scan.tex_coords)
        .zip(&scan.vertex_textured)
    {
        let z = f64::from(v[2]);
        if !*textured || !z.is_finite() || z <= 1e-3 {
            continue;
        }
        let a = f64::from(v[1]) / z;
        let b = f64::from(t[1]) * h - h * 0.5;
        if a.is_finite() && b.is_finite() {
            sxy += a * b;
            sxx += a * a;
            n += 1;
        }
    }
    if n < 16 || sxx < 1e-9 {
        return None;
    }
    let fy = sxy / sxx;
    if !(fy.is_finite() && fy > 1.0) {
        return None;
    }
    let fov = (2.0 * (h / (2.0 * fy)).atan()).to_degrees();
    (crate::camera::MIN_FOV_DEG..=crate::camera::MAX_FOV_DEG)
        .contains(&fov)
        .then_some(fov)
}

/// The stream latency the overlay shows: how long scans took from the moment their
/// message was complete to the first frame that drew them (viewer side), with the
/// daemon's own `end_to_end` stage (frame received -> scan published).
#[derive(Debug, Clone, Default)]
pub struct LatencyMeter {
    pending: Vec<Instant>,
    /// Most recent samples, milliseconds.
    samples: std::collections::VecDeque<f64>,
}

impl LatencyMeter {
    const WINDOW: usize = 64;

    pub fn received(&mut self, at: Instant) {
        if self.pending.len() < 4096 {
            self.pending.push(at);
        }
    }

    /// A frame showing everything received so far was submitted.
    pub fn drawn(&mut self, now: Instant) {
        for at in self.pending.drain(..) {
            if self.samples.len() == Self::WINDOW {
                self.samples.pop_front();
            }
            self.samples
                .push_back(now.saturating_duration_since(at).as_secs_f64() * 1e3);
        }
    }

    /// Median and maximum over the recent window, milliseconds.
    pub fn summary(&self) -> Option<(f64, f64)> {
        if self.samples.is_empty() {
            return None;
        }
        let mut v: Vec<f64> = self.samples.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        Some((v[v.len() / 2], v[v.len() - 1]))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_field_of_view_is_recovered_from_a_fused_scan() {
        let sensor = crate::scenes::test_sensor();
        let model = crate::scenes::model_of(
            &crate::scenes::box_scene(),
            &sensor,
            &crate::scenes::box_scene_poses(),
            &texel::Pose::identity(),
        );
        let scan = model.scans()[0].scan.as_ref().unwrap();
        let truth = crate::camera::VirtualCamera::fov_y_deg_of(&sensor.model.eo);
        let got = fov_y_deg_of_scan(scan).unwrap();
        assert!((got - truth).abs() < 0.5, "{got} vs {truth}");
    }

    #[test]
    fn the_window_feed_joins_exposures_to_their_scans_and_passes_the_response_on() {
        let model = crate::scenes::model_of(
            &crate::scenes::box_scene(),
            &crate::scenes::test_sensor(),
            &crate::scenes::box_scene_poses()[..1],
            &texel::Pose::identity(),
        );
        let scan = model.scans()[0].scan.clone().unwrap();
        let wire = texel::wire::WireScan::from_scan(
            5,
            &scan,
            texel::Pose::identity(),
            texel::wire::TextureFormat::Png,
            90,
        )
        .unwrap();
        let exposure = texel::EoExposure {
            exposure_time_s: 0.03,
            gain: 1.0,
        };
        let (tx, rx) = std::sync::mpsc::sync_channel(8);
        let mut join = texel_client::ExposureJoin::default();
        let messages = [
            texel::wire::Message::EoResponse(Box::new(texel::radiance::EoResponse::srgb())),
            texel::wire::Message::ScanExposure { id: 5, exposure },
            texel::wire::Message::ScanAdded(Box::new(wire)),
        ];
        for m in messages {
            assert!(matches!(connection::forward(m, &tx, &mut join), Ok(true)));
        }
        drop(tx);
        let events: Vec<ViewerEvent> = rx.iter().collect();
        assert!(matches!(events[0], ViewerEvent::EoResponse(_)));
        match &events[1] {
            ViewerEvent::Model {
                event: ModelEvent::ScanAdded { id: 5, scan, .. },
                ..
            } => assert_eq!(scan.texture.exposure, Some(exposure)),
            other => panic!("{other:?}"),
        }
        assert_eq!(events.len(), 2);
    }

    #[test]
    fn latency_is_measured_from_receipt_to_drawing() {
        let mut m = LatencyMeter::default();
        assert!(m.summary().is_none());
        let t0 = Instant::now();
        m.received(t0);
        m.drawn(t0 + Duration::from_millis(30));
        let (p50, max) = m.summary().unwrap();
        assert!((p50 - 30.0).abs() < 1e-6 && (max - 30.0).abs() < 1e-6);
    }
}
