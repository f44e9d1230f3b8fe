//! `/eo/exposure`, the project's extension that says how each EO frame was exposed
//! (exposure time and gain), so a capture's images can be turned back into radiance.
//! One message per exposed EO frame, with the frame's timestamp, written before the
//! frame; a capture without the topic reads as before (its frames have no exposure).

use serde::{Deserialize, Serialize};

use super::anchors::Time;
use crate::frames::EoExposure;

/// Schema name and JSON schema of `/eo/exposure`.
pub const EXPOSURE_SCHEMA_NAME: &str = "texel.EoExposure";
pub const EXPOSURE_JSON_SCHEMA: &str = r##"{
  "title": "texel.EoExposure",
  "description": "How the EO frame at `timestamp` was exposed: a pixel value is f(radiance * exposure_time_s * gain) for the camera's response curve f.",
  "type": "object",
  "properties": {
    "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}, "required": ["sec", "nsec"]},
    "exposure_time_s": {"type": "number", "exclusiveMinimum": 0},
    "gain": {"type": "number", "exclusiveMinimum": 0, "default": 1.0}
  },
  "required": ["timestamp", "exposure_time_s"]
}"##;

/// One `/eo/exposure` message: the EO frame at `timestamp_ns` was exposed so.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExposureRecord {
    pub timestamp_ns: u64,
    pub exposure: EoExposure,
}

#[derive(Debug, Serialize, Deserialize)]
struct ExposureJson {
    timestamp: Time,
    exposure_time_s: f64,
    #[serde(default = "unit_gain")]
    gain: f64,
}

fn unit_gain() -> f64 {
    1.0
}

impl ExposureRecord {
    /// The message's JSON.
    pub fn to_json(&self) -> Result<Vec<u8>, String> {
        self.exposure.validate()?;
        serde_json::to_vec(&ExposureJson {
            timestamp: Time::from_nanos(self.timestamp_ns),
            exposure_time_s: self.exposure.exposure_time_s,
            gain: self.exposure.gain,
        })
        .map_err(|e| e.to_string())
    }

    /// Parses a message (unknown fields ignored, a missing gain is 1); an exposure
    /// time or gain that is not a finite positive number in range is an error that
    /// names it.
    pub fn from_json(data: &[u8]) -> Result<Self, String> {
        let json: ExposureJson =
            serde_json::from_slice(data).map_err(|e| format!("invalid exposure JSON: {e}"))?;
        let timestamp_ns = json
            .timestamp
            .to_nanos("timestamp")
            .map_err(|e| e.to_string())?;
        let exposure = EoExposure {
            exposure_time_s: json.exposure_time_s,
            gain: json.gain,
        };
        exposure.validate()?;
        Ok(Self {
            timestamp_ns,
            exposure,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_exposure_round_trips_through_json_exactly() {
        let record = ExposureRecord {
            timestamp_ns: 1_700_000_000_123_456_789,
            exposure: EoExposure {
                exposure_time_s: 1.0 / 480.0,
                gain: 2.5,
            },
        };
        let back = ExposureRecord::from_json(&record.to_json().unwrap()).unwrap();
        assert_eq!(back, record);
        serde_json::from_str::<serde_json::Value>(EXPOSURE_JSON_SCHEMA).unwrap();
    }

    #[test]
    fn a_missing_gain_is_unity_and_bad_values_are_named() {
        let r = ExposureRecord::from_json(
            br#"{"timestamp": {"sec": 1, "nsec": 5}, "exposure_time_s": 0.01, "extra": 3}"#,
        )
        .unwrap();
        assert_eq!(r.timestamp_ns, 1_000_000_005);
        assert_eq!(r.exposure.gain, 1.0);
        for (data, needle) in [
            (
                &br#"{"timestamp": {"sec": 1, "nsec": 0}, "exposure_time_s": 0}"#[..],
                "exposure_time_s 0",
            ),
            (
                br#"{"timestamp": {"sec": 1, "nsec": 0}, "exposure_time_s": -1}"#,
                "exposure_time_s -1",
            ),
            (
                br#"{"timestamp": {"sec": 1, "nsec": 0}, "exposure_time_s": 1e9}"#,
                "exposure_time_s",
            ),
            (
                br#"{"timestamp": {"sec": 1, "nsec": 0}, "exposure_time_s": 0.1, "gain": 0}"#,
                "gain 0",
            ),
            (
                br#"{"timestamp": {"sec": 1, "nsec": 2000000000}, "exposure_time_s": 0.1}"#,
                "nsec",
            ),
            (
                br#"{"timestamp": {"sec": 1, "nsec": 0}}"#,
                "exposure_time_s",
            ),
            (b"[", "invalid exposure JSON"),
        ] {
            let e = ExposureRecord::from_json(data).unwrap_err();
            assert!(e.contains(needle), "{e:?} lacks {needle:?}");
        }
        let bad = ExposureRecord {
            timestamp_ns: 0,
            exposure: EoExposure {
                exposure_time_s: f64::NAN,
                gain: 1.0,
            },
        };
        assert!(bad.to_json().is_err());
    }
}
