//! `texeld info`: what a capture holds (topics, counts, duration, frame sizes,
//! calibrations, sensor JSON) and every way it breaks the capture format.

use std::collections::BTreeMap;
use std::fmt::{self, Write as _};
use std::path::Path;

use texel::PinholeCamera;
use texel::capture::{CaptureError, CaptureEvent, CaptureReader, PoseTopic, topics};
use texel::pose::{Pose, pose_to_parts};
use texel::sensor::SensorInfo;

/// Spec violations listed in full; the rest are counted.
const MAX_LISTED_VIOLATIONS: usize = 20;

#[derive(Debug, Default)]
pub struct TopicSummary {
    pub schema: String,
    pub message_encoding: String,
    pub count: u64,
    /// `WxH encoding` (or compression format) -> count, for image topics.
    pub layouts: BTreeMap<String, u64>,
}

/// Everything `texeld info` reports about one capture.
#[derive(Debug, Default)]
pub struct CaptureSummary {
    pub path: String,
    pub file_len: u64,
    pub topics: BTreeMap<String, TopicSummary>,
    pub first_log_time_ns: Option<u64>,
    pub last_log_time_ns: Option<u64>,
    pub lidar_calibration: Option<PinholeCamera>,
    pub eo_calibration: Option<PinholeCamera>,
    pub eo_from_lidar: Option<Pose>,
    pub sensor_json: Option<String>,
    pub sensor: Option<SensorInfo>,
    pub range_frames: u64,
    pub eo_frames: u64,
    pub poses: BTreeMap<&'static str, u64>,
    pub violations: Vec<String>,
    pub violation_count: u64,
    /// Stretches of the file read around (offsets, reason, the log times lost): the
    /// first ones in full, all of them counted.
    pub damaged: Vec<String>,
    pub damaged_count: u64,
    /// The error that ended reading early (truncation, corruption), if any.
    pub fatal: Option<String>,
}

impl CaptureSummary {
    /// True when the capture was read to its end and follows the format.
    pub fn is_clean(&self) -> bool {
        self.fatal.is_none() && self.violation_count == 0 && self.damaged_count == 0
    }

    pub fn duration_s(&self) -> f64 {
        match (self.first_log_time_ns, self.last_log_time_ns) {
            (Some(a), Some(b)) => b.saturating_sub(a) as f64 * 1e-9,
            _ => 0.0,
        }
    }
}

/// The image layout of a RawImage or CompressedImage message, for the topic table.
fn layout_of(message: &mcap::Message<'_>) -> Option<String> {
    use prost::Message as _;
    let schema = message.channel.schema.as_ref()?;
    match schema.name.as_str() {
        "foxglove.RawImage" => {
            let m = foxglove::messages::RawImage::decode(message.data.as_ref()).ok()?;
            Some(format!("{}x{} {}", m.width, m.height, m.encoding))
        }
        "foxglove.CompressedImage" => {
            let m = foxglove::messages::CompressedImage::decode(message.data.as_ref()).ok()?;
            Some(m.format)
        }
        _ => None,
    }
}

/// Reads the whole capture and summarises it. Only an unopenable file is an `Err`;
/// damage and spec violations are recorded in the summary after what could be read.
pub fn summarize(path: &Path) -> Result<CaptureSummary, CaptureError> {
    let mut reader = CaptureReader::open(path)?;
    let mut summary = CaptureSummary {
        path: path.display().to_string(),
        file_len: std::fs::metadata(path).map(|m| m.len()).unwrap_or(0),
        ..Default::default()
    };
    while let Some(next) = reader.next_message() {
        let message = match next {
            Ok(m) => m,
            Err(e @ CaptureError::Damaged { .. }) => {
                summary.damaged_count += 1;
                if summary.damaged.len() < MAX_LISTED_VIOLATIONS {
                    summary.damaged.push(e.to_string());
                }
                continue;
            }
            Err(e) => {
                summary.fatal = Some(e.to_string());
                break;
            }
        };
        let topic = summary
            .topics
            .entry(message.channel.topic.clone())
            .or_insert_with(|| TopicSummary {
                schema: message
                    .channel
                    .schema
                    .as_ref()
                    .map(|s| s.name.clone())
                    .unwrap_or_default(),
                message_encoding: message.channel.message_encoding.clone(),
                ..Default::default()
            });
        topic.count += 1;
        if let Some(layout) = layout_of(&message) {
            *topic.layouts.entry(layout).or_insert(0) += 1;
        }
        summary.first_log_time_ns = Some(
            summary
                .first_log_time_ns
                .map_or(message.log_time, |t| t.min(message.log_time)),
        );
        summary.last_log_time_ns = Some(
            summary
                .last_log_time_ns
                .map_or(message.log_time, |t| t.max(message.log_time)),
        );
        match reader.decode(&message) {
            Ok(CaptureEvent::LidarCalibration { camera, .. }) => {
                summary.lidar_calibration = Some(camera)
            }
            Ok(CaptureEvent::EoCalibration { camera, .. }) => summary.eo_calibration = Some(camera),
            Ok(CaptureEvent::EoFromLidar { pose, .. }) => summary.eo_from_lidar = Some(pose),
            Ok(CaptureEvent::Sensor { info, .. }) => {
                summary.sensor_json = Some(String::from_utf8_lossy(&message.data).into_owned());
                summary.sensor = Some(info);
            }
            Ok(CaptureEvent::Range(_)) => summary.range_frames += 1,
            Ok(CaptureEvent::Eo(_)) => summary.eo_frames += 1,
            Ok(CaptureEvent::Pose { topic, .. }) => {
                let name = match topic {
                    PoseTopic::Truth => "/truth/pose",
                    PoseTopic::Texel => "/texel/pose",
                };
                *summary.poses.entry(name).or_insert(0) += 1;
            }
            Ok(CaptureEvent::Anchor(_)) => {
                *summary.poses.entry(topics::TEXEL_ANCHOR).or_insert(0) += 1;
            }
            Ok(
                CaptureEvent::Intensity { .. }
                | CaptureEvent::Exposure(_)
                | CaptureEvent::Other { .. },
            ) => {}
            Err(e) => {
                summary.violation_count += 1;
                if summary.violations.len() < MAX_LISTED_VIOLATIONS {
                    summary.violations.push(e.to_string());
                }
            }
        }
    }
    Ok(summary)
}

fn write_camera(out: &mut String, name: &str, c: &PinholeCamera) -> fmt::Result {
    let (model, d) = c.distortion_fields();
    writeln!(
        out,
        "  {name}: {}x{}  fx {:.4}  fy {:.4}  cx {:.4}  cy {:.4}  skew {:.4}  distortion {}{}",
        c.width,
        c.height,
        c.fx,
        c.fy,
        c.cx,
        c.cy,
        c.skew,
        if model.is_empty() { "none" } else { model },
        if d.is_empty() {
            String::new()
        } else {
            format!(" {d:?}")
        }
    )
}

impl fmt::Display for CaptureSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut out = String::new();
        writeln!(out, "capture: {} ({} bytes)", self.path, self.file_len)?;
        writeln!(
            out,
            "duration: {:.3} s ({} messages)",
            self.duration_s(),
            self.topics.values().map(|t| t.count).sum::<u64>()
        )?;
        writeln!(out, "topics:")?;
        for (name, t) in &self.topics {
            writeln!(
                out,
                "  {name:<24} {:>7} msgs  {} ({})",
                t.count, t.schema, t.message_encoding
            )?;
            for (layout, n) in &t.layouts {
                writeln!(out, "  {:<24} {n:>7} x {layout}", "")?;
            }
        }
        writeln!(
            out,
            "frames: {} range, {} EO",
            self.range_frames, self.eo_frames
        )?;
        for (topic, n) in &self.poses {
            writeln!(out, "poses: {n} on {topic}")?;
        }
        writeln!(out, "calibrations:")?;
        match &self.lidar_calibration {
            Some(c) => write_camera(&mut out, "lidar", c)?,
            None => writeln!(out, "  lidar: none")?,
        }
        match &self.eo_calibration {
            Some(c) => write_camera(&mut out, "eo", c)?,
            None => writeln!(out, "  eo: none")?,
        }
        match &self.eo_from_lidar {
            Some(p) => {
                let (t, q) = pose_to_parts(p);
                writeln!(
                    out,
                    "  eo_from_lidar: translation_m {t:?}  rotation_xyzw {q:?}"
                )?;
            }
            None => writeln!(out, "  eo_from_lidar: none")?,
        }
        match &self.sensor_json {
            Some(j) => writeln!(out, "sensor: {j}")?,
            None => writeln!(out, "sensor: none (the format's defaults apply)")?,
        }
        if self.violation_count > 0 {
            writeln!(out, "spec violations: {}", self.violation_count)?;
            for v in &self.violations {
                writeln!(out, "  {v}")?;
            }
            if self.violation_count as usize > self.violations.len() {
                writeln!(
                    out,
                    "  ... and {} more",
                    self.violation_count as usize - self.violations.len()
                )?;
            }
        }
        if self.damaged_count > 0 {
            writeln!(out, "damaged stretches read around: {}", self.damaged_count)?;
            for d in &self.damaged {
                writeln!(out, "  {d}")?;
            }
        }
        if let Some(e) = &self.fatal {
            writeln!(out, "error: {e}")?;
        }
        f.write_str(&out)
    }
}
