//! Reads a capture as texel frames: assembles the sensor model from the calibration
//! messages, attaches intensity to its range frame, pairs range and EO frames through
//! [`FrameSync`], and passes poses through.

use std::collections::VecDeque;
use std::io::Read;

use super::reader::{CaptureEvent, CaptureReader};
use super::{CaptureError, PoseAnchor, PoseTopic};
use crate::camera::PinholeCamera;
use crate::frames::{FramePair, RangeFrame};
use crate::pose::Pose;
use crate::sensor::{SensorInfo, SensorModel};
use crate::sync::{FrameSync, SyncCounters};

/// Replayed captures pair frames whose timestamps differ by at most this (a live
/// recording stores each sensor's own timestamp).
pub const DEFAULT_REPLAY_TOLERANCE_NS: u64 = 20_000_000;

/// What a capture yields at the texel-frame level.
#[derive(Debug, Clone)]
pub enum TexelItem {
    /// A texel frame, with the sensor model in force when it was taken.
    Pair {
        pair: FramePair,
        sensor: std::sync::Arc<SensorModel>,
    },
    Pose {
        topic: PoseTopic,
        timestamp_ns: u64,
        world_from_eo: Pose,
    },
    /// `/texel/anchor`: a registered frame hangs from a keyframe.
    Anchor(PoseAnchor),
}

/// Texel frames from a capture.
pub struct TexelFrameReader<R: Read> {
    reader: CaptureReader<R>,
    sync: FrameSync,
    lidar: Option<PinholeCamera>,
    eo: Option<PinholeCamera>,
    eo_from_lidar: Option<Pose>,
    info: SensorInfo,
    sensor: Option<std::sync::Arc<SensorModel>>,
    /// A range frame held back until its intensity (same timestamp) arrives or a
    /// later message shows none will.
    held_range: Option<RangeFrame>,
    ready: VecDeque<Result<TexelItem, CaptureError>>,
    missing_extrinsic_reported: bool,
    finished: bool,
}

impl<R: Read> TexelFrameReader<R> {
    pub fn new(reader: CaptureReader<R>, tolerance_ns: u64) -> Self {
        Self {
            reader,
            sync: FrameSync::new(tolerance_ns, 8),
            lidar: None,
            eo: None,
            eo_from_lidar: None,
            info: SensorInfo::default(),
            sensor: None,
            held_range: None,
            ready: VecDeque::new(),
            missing_extrinsic_reported: false,
            finished: false,
        }
    }

    pub fn sync_counters(&self) -> SyncCounters {
        self.sync.counters()
    }

    /// The sensor model as far as the capture has described it.
    pub fn sensor(&self) -> Option<&std::sync::Arc<SensorModel>> {
        self.sensor.as_ref()
    }

    pub fn capture(&self) -> &CaptureReader<R> {
        &self.reader
    }

    fn rebuild_sensor(&mut self) {
        if let (Some(lidar), Some(eo)) = (&self.lidar, &self.eo) {
            let model = SensorModel::from_capture_parts(
                lidar.clone(),
                eo.clone(),
                self.eo_from_lidar.unwrap_or_else(Pose::identity),
                &self.info,
            );
            if self.sensor.as_deref() != Some(&model) {
                self.sensor = Some(std::sync::Arc::new(model));
            }
        }
    }

    fn release_held(&mut self) {
        if let Some(range) = self.held_range.take() {
            self.offer_range(range);
        }
    }

    fn offer_range(&mut self, range: RangeFrame) {
        if let Some(pair) = self.sync.push_range(range) {
            self.emit_pair(pair);
        }
    }

    fn emit_pair(&mut self, pair: FramePair) {
        let Some(sensor) = self.sensor.clone() else {
            // Cannot happen for a range frame (the reader refuses one before its
            // calibration), but an EO calibration may still be missing.
            self.ready.push_back(Err(CaptureError::Spec {
                path: self.reader.path().to_string(),
                topic: super::topics::EO_CALIBRATION.to_string(),
                log_time_ns: pair.timestamp_ns(),
                message: "texel frame before any /eo/calibration; frame skipped".into(),
            }));
            return;
        };
        if self.eo_from_lidar.is_none() && !self.missing_extrinsic_reported {
            self.missing_extrinsic_reported = true;
            self.ready.push_back(Err(CaptureError::Spec {
                path: self.reader.path().to_string(),
                topic: super::topics::TF_STATIC.to_string(),
                log_time_ns: pair.timestamp_ns(),
                message:
                    "no /tf_static before the first frame; assuming eo_from_lidar is the identity"
                        .into(),
            }));
        }
        self.ready.push_back(Ok(TexelItem::Pair { pair, sensor }));
    }

    fn handle(&mut self, event: CaptureEvent) {
        // Anything later than the held range frame means its intensity is not coming.
        let event_time = match &event {
            CaptureEvent::Intensity { timestamp_ns, .. } => Some(*timestamp_ns),
            CaptureEvent::Range(f) => Some(f.timestamp_ns),
            CaptureEvent::Eo(f) => Some(f.timestamp_ns),
            _ => None,
        };
        if let (Some(held), Some(t)) = (&self.held_range, event_time)
            && t > held.timestamp_ns
        {
            self.release_held();
        }
        match event {
            CaptureEvent::LidarCalibration { camera, .. } => {
                self.lidar = Some(camera);
                self.rebuild_sensor();
            }
            CaptureEvent::EoCalibration { camera, .. } => {
                self.eo = Some(camera);
                self.rebuild_sensor();
            }
            CaptureEvent::EoFromLidar { pose, .. } => {
                self.eo_from_lidar = Some(pose);
                self.rebuild_sensor();
            }
            CaptureEvent::Sensor { info, .. } => {
                self.info = info;
                self.rebuild_sensor();
            }
            CaptureEvent::Range(frame) => {
                self.release_held();
                self.held_range = Some(frame);
            }
            CaptureEvent::Intensity {
                timestamp_ns,
                values,
                ..
            } => match &mut self.held_range {
                Some(held)
                    if held.timestamp_ns == timestamp_ns && held.pixel_count() == values.len() =>
                {
                    held.intensity = Some(values);
                    self.release_held();
                }
                // Intensity without its range frame is of no use on its own.
                _ => {}
            },
            CaptureEvent::Eo(frame) => {
                if let Some(pair) = self.sync.push_eo(frame) {
                    self.emit_pair(pair);
                }
            }
            CaptureEvent::Pose {
                topic,
                timestamp_ns,
                world_from_eo,
            } => self.ready.push_back(Ok(TexelItem::Pose {
                topic,
                timestamp_ns,
                world_from_eo,
            })),
            CaptureEvent::Anchor(anchor) => self.ready.push_back(Ok(TexelItem::Anchor(anchor))),
            // The reader has attached it to its EO frame already.
            CaptureEvent::Exposure(_) | CaptureEvent::Other { .. } => {}
        }
    }
}

impl<R: Read> Iterator for TexelFrameReader<R> {
    type Item = Result<TexelItem, CaptureError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(item) = self.ready.pop_front() {
                return Some(item);
            }
            if self.finished {
                return None;
            }
            match self.reader.next() {
                Some(Ok(event)) => self.handle(event),
                Some(Err(e)) => {
                    if e.is_fatal() {
                        // Deliver what was complete before the damage, then the error.
                        self.release_held();
                        self.sync.finish();
                        self.finished = true;
                    }
                    self.ready.push_back(Err(e));
                }
                None => {
                    self.release_held();
                    self.sync.finish();
                    self.finished = true;
                }
            }
        }
    }
}
