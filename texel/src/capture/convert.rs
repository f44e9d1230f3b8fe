//! Conversions between the project's types and the Foxglove messages the capture
//! format stores them in.

use foxglove::messages::{CameraCalibration, FrameTransform, Quaternion, Timestamp, Vector3};

use crate::camera::{CameraError, PinholeCamera};
use crate::pose::{Pose, PoseError, pose_from_parts, pose_to_parts};

/// Nanoseconds since the epoch to a Foxglove timestamp (saturating past 2106).
pub fn timestamp_from_nanos(ns: u64) -> Timestamp {
    let sec = (ns / 1_000_000_000).min(u64::from(u32::MAX)) as u32;
    Timestamp::new_checked(sec, (ns % 1_000_000_000) as u32).unwrap_or(Timestamp::MAX)
}

/// A Foxglove timestamp to nanoseconds (an out-of-range `nsec` carries into seconds).
pub fn nanos_from_timestamp(t: &Timestamp) -> u64 {
    u64::from(t.sec()) * 1_000_000_000 + u64::from(t.nsec())
}

pub fn calibration_from_camera(
    camera: &PinholeCamera,
    frame_id: &str,
    timestamp_ns: u64,
) -> CameraCalibration {
    let (model, d) = camera.distortion_fields();
    // R is the identity and P = [K | 0] for a monocular camera (the ROS convention
    // Foxglove follows).
    let k = camera.k_row_major();
    CameraCalibration {
        timestamp: Some(timestamp_from_nanos(timestamp_ns)),
        frame_id: frame_id.to_string(),
        width: camera.width,
        height: camera.height,
        distortion_model: model.to_string(),
        d,
        k: k.to_vec(),
        r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: vec![
            k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0,
        ],
    }
}

pub fn camera_from_calibration(c: &CameraCalibration) -> Result<PinholeCamera, CameraError> {
    PinholeCamera::from_calibration(c.width, c.height, &c.k, &c.distortion_model, &c.d)
}

pub fn transform_from_pose(
    parent: &str,
    child: &str,
    parent_from_child: &Pose,
    timestamp_ns: u64,
) -> FrameTransform {
    let (t, q) = pose_to_parts(parent_from_child);
    FrameTransform {
        timestamp: Some(timestamp_from_nanos(timestamp_ns)),
        parent_frame_id: parent.to_string(),
        child_frame_id: child.to_string(),
        translation: Some(Vector3 {
            x: t[0],
            y: t[1],
            z: t[2],
        }),
        rotation: Some(Quaternion {
            x: q[0],
            y: q[1],
            z: q[2],
            w: q[3],
        }),
    }
}

/// The transform's `parent_from_child` pose. A missing translation is zero; a missing
/// rotation is the identity (protobuf's defaults would give a zero quaternion, which
/// is no rotation at all).
pub fn pose_from_transform(t: &FrameTransform) -> Result<Pose, PoseError> {
    let tr = t.translation.unwrap_or_default();
    let q = t.rotation.unwrap_or(Quaternion {
        x: 0.0,
        y: 0.0,
        z: 0.0,
        w: 1.0,
    });
    pose_from_parts([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timestamps_round_trip() {
        for ns in [
            0u64,
            1,
            999_999_999,
            1_000_000_000,
            1_700_000_000_123_456_789,
        ] {
            assert_eq!(nanos_from_timestamp(&timestamp_from_nanos(ns)), ns);
        }
    }

    #[test]
    fn transforms_round_trip() {
        let p = pose_from_parts([1.0, -2.0, 3.5], [0.1, 0.2, 0.3, 0.9]).unwrap();
        let back = pose_from_transform(&transform_from_pose("eo", "lidar", &p, 5)).unwrap();
        assert!((back.to_homogeneous() - p.to_homogeneous()).abs().max() < 1e-15);
    }
}
