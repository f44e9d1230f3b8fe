//! The capture format's messages built from the project's types, once, for every
//! program that sends them: the capture writer, and the daemon's live session in
//! Foxglove, which offers the same topics with the same schemas as the recording.

use foxglove::messages::{CameraCalibration, FrameTransform, RawImage};
use thiserror::Error;

use super::convert::{calibration_from_camera, timestamp_from_nanos, transform_from_pose};
use super::images::{
    EoEncoding, ImageError, RangeEncoding, encode_eo, encode_intensity, encode_range,
};
use super::{CameraRole, frame_ids};
use crate::frames::{EoFrame, RangeFrame};
use crate::pose::Pose;
use crate::sensor::SensorModel;

/// A frame that cannot become a message.
#[derive(Debug, Error)]
pub enum FrameMessageError {
    #[error("range frame {seq} has {values} values for {width}x{height} pixels")]
    Range {
        seq: u32,
        values: usize,
        width: u32,
        height: u32,
    },
    #[error("EO frame at {timestamp_ns} ns has {bytes} bytes for {width}x{height} RGB pixels")]
    Eo {
        timestamp_ns: u64,
        bytes: usize,
        width: u32,
        height: u32,
    },
    #[error(transparent)]
    Image(#[from] ImageError),
}

/// `/lidar/range` of a range frame, and its `/lidar/intensity` when it has one.
pub fn range_images(
    frame: &RangeFrame,
    encoding: RangeEncoding,
) -> Result<(RawImage, Option<RawImage>), FrameMessageError> {
    if !frame.is_consistent() {
        return Err(FrameMessageError::Range {
            seq: frame.seq,
            values: frame.ranges_m.len(),
            width: frame.width,
            height: frame.height,
        });
    }
    let (step, data) = encode_range(&frame.ranges_m, frame.width, encoding);
    let range = RawImage {
        timestamp: Some(timestamp_from_nanos(frame.timestamp_ns)),
        frame_id: frame_ids::LIDAR.to_string(),
        width: frame.width,
        height: frame.height,
        encoding: encoding.name().to_string(),
        step,
        data: data.into(),
    };
    let intensity = frame.intensity.as_ref().map(|values| {
        let (encoding, step, data) = encode_intensity(values, frame.width);
        RawImage {
            timestamp: Some(timestamp_from_nanos(frame.timestamp_ns)),
            frame_id: frame_ids::LIDAR.to_string(),
            width: frame.width,
            height: frame.height,
            encoding: encoding.to_string(),
            step,
            data: data.into(),
        }
    });
    Ok((range, intensity))
}

/// `/eo/image` of an EO frame in one of the raw encodings.
pub fn eo_image(frame: &EoFrame, encoding: EoEncoding) -> Result<RawImage, FrameMessageError> {
    if !frame.is_consistent() {
        return Err(FrameMessageError::Eo {
            timestamp_ns: frame.timestamp_ns,
            bytes: frame.rgb.len(),
            width: frame.width,
            height: frame.height,
        });
    }
    let (step, data) = encode_eo(&frame.rgb, frame.width, frame.height, encoding)?;
    Ok(RawImage {
        timestamp: Some(timestamp_from_nanos(frame.timestamp_ns)),
        frame_id: frame_ids::EO.to_string(),
        width: frame.width,
        height: frame.height,
        encoding: encoding.name().to_string(),
        step,
        data: data.into(),
    })
}

/// `/lidar/calibration` or `/eo/calibration` of a sensor model.
pub fn calibration(sensor: &SensorModel, role: CameraRole, timestamp_ns: u64) -> CameraCalibration {
    let camera = match role {
        CameraRole::Lidar => &sensor.lidar,
        CameraRole::Eo => &sensor.eo,
    };
    calibration_from_camera(camera, role.frame_id(), timestamp_ns)
}

/// `/tf_static`: the lidar frame's pose in the EO frame (parent `eo`, child `lidar`).
pub fn eo_from_lidar(eo_from_lidar: &Pose, timestamp_ns: u64) -> FrameTransform {
    transform_from_pose(frame_ids::EO, frame_ids::LIDAR, eo_from_lidar, timestamp_ns)
}

/// `/truth/pose` or `/texel/pose`: the EO camera's pose in the world (parent `world`,
/// child `eo`) at a frame's timestamp.
pub fn world_from_eo(world_from_eo: &Pose, timestamp_ns: u64) -> FrameTransform {
    transform_from_pose(frame_ids::WORLD, frame_ids::EO, world_from_eo, timestamp_ns)
}

/// `/texel/sensor`'s JSON of a sensor model.
pub fn sensor_json(sensor: &SensorModel) -> Result<Vec<u8>, serde_json::Error> {
    serde_json::to_vec(&sensor.info())
}
