//! The capture format (`docs/capture-format.md`, version 1): topics, message
//! conversions, a streaming reader that enforces the reading rules, and a writer
//! that flushes often enough that a crash loses at most a second.

mod anchors;
mod convert;
mod exposure;
mod frames;
mod fused;
mod images;
pub mod messages;
mod reader;
mod records;
mod summary;
mod writer;

pub use anchors::{
    ANCHOR_JSON_SCHEMA, ANCHOR_SCHEMA_NAME, AnchorError, PoseAnchor, RegisteredPoses,
};
pub use convert::{
    calibration_from_camera, camera_from_calibration, nanos_from_timestamp, pose_from_transform,
    timestamp_from_nanos, transform_from_pose,
};
pub use exposure::{EXPOSURE_JSON_SCHEMA, EXPOSURE_SCHEMA_NAME, ExposureRecord};
pub use frames::{DEFAULT_REPLAY_TOLERANCE_NS, TexelFrameReader, TexelItem};
pub use fused::SensorCache;
pub use images::{
    EoEncoding, ImageError, RangeEncoding, decode_compressed, decode_eo, decode_intensity,
    decode_range, encode_compressed, encode_eo, encode_intensity, encode_range,
};
pub use reader::{CaptureEvent, CaptureReader, ReadPosition};
pub use writer::{CaptureWriter, DEFAULT_FLUSH_INTERVAL, WriterOptions};

use std::fs::File;
use std::path::Path;

use thiserror::Error;

/// Opens a capture file as a stream of texel frames and poses.
pub fn open_texel_frames(path: &Path) -> Result<TexelFrameReader<File>, CaptureError> {
    Ok(TexelFrameReader::new(
        CaptureReader::open(path)?,
        DEFAULT_REPLAY_TOLERANCE_NS,
    ))
}

/// Topic names of the capture format.
pub mod topics {
    pub const LIDAR_RANGE: &str = "/lidar/range";
    pub const LIDAR_INTENSITY: &str = "/lidar/intensity";
    pub const LIDAR_CALIBRATION: &str = "/lidar/calibration";
    pub const EO_IMAGE: &str = "/eo/image";
    pub const EO_IMAGE_COMPRESSED: &str = "/eo/image/compressed";
    pub const EO_CALIBRATION: &str = "/eo/calibration";
    /// The project's extension: each EO frame's exposure time and gain.
    pub const EO_EXPOSURE: &str = "/eo/exposure";
    pub const TF_STATIC: &str = "/tf_static";
    pub const TEXEL_SENSOR: &str = "/texel/sensor";
    pub const TRUTH_POSE: &str = "/truth/pose";
    pub const TEXEL_POSE: &str = "/texel/pose";
    /// The project's extension: the keyframe a registered frame hangs from.
    pub const TEXEL_ANCHOR: &str = "/texel/anchor";

    /// Every topic the format defines.
    pub const ALL: [&str; 12] = [
        LIDAR_RANGE,
        LIDAR_INTENSITY,
        LIDAR_CALIBRATION,
        EO_IMAGE,
        EO_IMAGE_COMPRESSED,
        EO_CALIBRATION,
        EO_EXPOSURE,
        TF_STATIC,
        TEXEL_SENSOR,
        TRUTH_POSE,
        TEXEL_POSE,
        TEXEL_ANCHOR,
    ];
}

/// Frame ids of the capture format.
pub mod frame_ids {
    pub const LIDAR: &str = "lidar";
    pub const EO: &str = "eo";
    pub const WORLD: &str = "world";
}

/// Schema name and JSON schema of `/texel/sensor`.
pub const SENSOR_SCHEMA_NAME: &str = "texel.Sensor";
pub const SENSOR_JSON_SCHEMA: &str = r#"{
  "title": "texel.Sensor",
  "type": "object",
  "properties": {
    "version": {"type": "integer"},
    "range_noise_sigma_m": {"type": "number"},
    "range_noise_sigma_per_m": {"type": "number"},
    "range_bias_m": {"type": "number"},
    "min_range_m": {"type": "number"},
    "max_range_m": {"type": "number"},
    "name": {"type": "string"},
    "eo_response": {
      "description": "The EO camera's inverse log response g(z) = ln(exposure) per 8-bit value and channel (Debevec & Malik 1997)",
      "type": "object",
      "properties": {
        "r": {"type": "array", "items": {"type": "number"}, "minItems": 256, "maxItems": 256},
        "g": {"type": "array", "items": {"type": "number"}, "minItems": 256, "maxItems": 256},
        "b": {"type": "array", "items": {"type": "number"}, "minItems": 256, "maxItems": 256}
      }
    }
  }
}"#;

/// Which pose topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseTopic {
    /// `/truth/pose`: the simulator's ground truth.
    Truth,
    /// `/texel/pose`: the project's registration.
    Texel,
}

impl PoseTopic {
    pub fn topic(self) -> &'static str {
        match self {
            Self::Truth => topics::TRUTH_POSE,
            Self::Texel => topics::TEXEL_POSE,
        }
    }
}

/// Which camera a calibration belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraRole {
    Lidar,
    Eo,
}

impl CameraRole {
    pub fn calibration_topic(self) -> &'static str {
        match self {
            Self::Lidar => topics::LIDAR_CALIBRATION,
            Self::Eo => topics::EO_CALIBRATION,
        }
    }

    pub fn frame_id(self) -> &'static str {
        match self {
            Self::Lidar => frame_ids::LIDAR,
            Self::Eo => frame_ids::EO,
        }
    }
}

/// Everything that can go wrong reading or writing a capture.
#[derive(Debug, Error)]
pub enum CaptureError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: not an MCAP file (it does not start with the MCAP magic)")]
    NotMcap { path: String },
    #[error(
        "{path}: truncated: the file ends at byte {file_len} inside a record; \
         {messages} complete messages were read before it"
    )]
    Truncated {
        path: String,
        file_len: u64,
        messages: u64,
    },
    #[error("{path}: corrupt MCAP at or before byte {offset}: {source}")]
    Mcap {
        path: String,
        offset: u64,
        source: mcap::McapError,
    },
    /// A stretch of the file that could not be read (a chunk that fails its CRC,
    /// damaged framing); reading went on after it.
    #[error(
        "{path}: bytes {offset}..{end} are damaged and were skipped ({reason}); {}",
        describe_lost(*.lost_log_time_ns)
    )]
    Damaged {
        path: String,
        offset: u64,
        end: u64,
        /// The log times of the messages lost with it, where known.
        lost_log_time_ns: Option<(u64, u64)>,
        reason: String,
    },
    /// A message that breaks the capture format; reading can go on past it.
    #[error("{path}: topic {topic} at log time {log_time_ns} ns: {message}")]
    Spec {
        path: String,
        topic: String,
        log_time_ns: u64,
        message: String,
    },
    #[error("{path}: cannot write: {message}")]
    Write { path: String, message: String },
}

impl CaptureError {
    /// True when reading cannot continue after this error (the file ends, is not
    /// MCAP, cannot be read); false for a single message that breaks the spec and for
    /// a damaged stretch that was read around.
    pub fn is_fatal(&self) -> bool {
        !matches!(self, Self::Spec { .. } | Self::Damaged { .. })
    }
}

/// The messages a damaged stretch cost, in words.
fn describe_lost(lost_log_time_ns: Option<(u64, u64)>) -> String {
    match lost_log_time_ns {
        Some((a, u64::MAX)) => format!("messages logged after {a} ns are lost"),
        Some((a, b)) => format!("messages logged {a}..{b} ns are lost"),
        None => "no message is known to be lost".into(),
    }
}
