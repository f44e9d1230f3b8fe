//! The EO camera's exposure as V4L2 reports it: when the camera is in manual exposure
//! mode, its `V4L2_CID_EXPOSURE_ABSOLUTE` control (in units of 100 µs) is the frame's
//! exposure time, and the frame carries it (`EoFrame::exposure`, recorded on
//! `/eo/exposure`). In automatic mode the control does not follow the camera's own
//! choice on every driver, so no exposure is claimed. The gain is taken as 1: V4L2's
//! gain controls have driver-defined units, so a session that changes the gain must
//! say so another way.

use texel::EoExposure;

/// `V4L2_CID_CAMERA_CLASS_BASE + 1`: `V4L2_CID_EXPOSURE_AUTO`.
pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
/// `V4L2_CID_CAMERA_CLASS_BASE + 2`: `V4L2_CID_EXPOSURE_ABSOLUTE`, 100 µs units.
pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// `V4L2_EXPOSURE_MANUAL`, a value of `V4L2_CID_EXPOSURE_AUTO`.
pub const EXPOSURE_MANUAL: i64 = 1;
/// `V4L2_EXPOSURE_SHUTTER_PRIORITY`: the exposure time is the user's too.
pub const EXPOSURE_SHUTTER_PRIORITY: i64 = 2;

/// The exposure a frame was taken with, from the camera's exposure mode and absolute
/// exposure control (`None` when either is unknown, the mode leaves the time to the
/// camera, or the value is not a positive time).
pub fn exposure_from_controls(
    mode: Option<i64>,
    absolute_100us: Option<i64>,
) -> Option<EoExposure> {
    let mode = mode?;
    if mode != EXPOSURE_MANUAL && mode != EXPOSURE_SHUTTER_PRIORITY {
        return None;
    }
    let units = absolute_100us?;
    let exposure = EoExposure {
        exposure_time_s: units as f64 * 100.0e-6,
        gain: 1.0,
    };
    exposure.validate().ok().map(|()| exposure)
}

/// Reads the two controls from an open device (any error: unknown).
pub fn read_exposure(device: &v4l::Device) -> Option<EoExposure> {
    let integer = |id: u32| match device.control(id).ok()?.value {
        v4l::control::Value::Integer(v) => Some(v),
        _ => None,
    };
    exposure_from_controls(integer(CID_EXPOSURE_AUTO), integer(CID_EXPOSURE_ABSOLUTE))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manual_exposure_is_claimed_and_automatic_is_not() {
        let e = exposure_from_controls(Some(EXPOSURE_MANUAL), Some(156)).unwrap();
        assert!((e.exposure_time_s - 0.0156).abs() < 1e-12);
        assert_eq!(e.gain, 1.0);
        assert!(exposure_from_controls(Some(EXPOSURE_SHUTTER_PRIORITY), Some(10)).is_some());
        // V4L2_EXPOSURE_AUTO (0) and APERTURE_PRIORITY (3): the camera chooses.
        assert_eq!(exposure_from_controls(Some(0), Some(156)), None);
        assert_eq!(exposure_from_controls(Some(3), Some(156)), None);
        // Unknown controls or values that are no time.
        assert_eq!(exposure_from_controls(None, Some(156)), None);
        assert_eq!(exposure_from_controls(Some(EXPOSURE_MANUAL), None), None);
        assert_eq!(exposure_from_controls(Some(EXPOSURE_MANUAL), Some(0)), None);
        assert_eq!(
            exposure_from_controls(Some(EXPOSURE_MANUAL), Some(-5)),
            None
        );
        assert_eq!(
            exposure_from_controls(Some(EXPOSURE_MANUAL), Some(i64::MAX)),
            None
        );
    }
}
