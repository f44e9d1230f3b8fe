//! The texel camera's sensor model: both cameras, the co-boresight extrinsic
//! `eo_from_lidar`, the lidar's range limits, range bias and range-noise model; read
//! from and
//! written to sensor files (`configs/sensors/*.toml`) and the capture's
//! `/texel/sensor` JSON.

use std::path::Path;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::camera::{CameraError, PinholeCamera};
use crate::fusion_tables::{FusionTables, LidarPitch};
use crate::pose::{Pose, PoseError, pose_from_parts, pose_to_parts};
use crate::radiance::EoResponse;
use crate::rays::RayTable;

/// Range noise standard deviation `sigma(r) = sigma_m + sigma_per_m * r` (capture
/// format, `/texel/sensor`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RangeNoise {
    pub sigma_m: f64,
    pub sigma_per_m: f64,
}

impl RangeNoise {
    /// Standard deviation of a range measurement at `range_m`, in metres. Never
    /// negative: a negative range (invalid input) is treated as zero.
    #[inline]
    pub fn sigma_at(&self, range_m: f64) -> f64 {
        (self.sigma_m + self.sigma_per_m * range_m.max(0.0)).max(0.0)
    }
}

impl Default for RangeNoise {
    fn default() -> Self {
        Self {
            sigma_m: 0.01,
            sigma_per_m: 0.0,
        }
    }
}

/// The `/texel/sensor` JSON message of the capture format (`docs/capture-format.md`).
/// Unknown fields are ignored; missing fields take the values given there.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SensorInfo {
    pub version: u32,
    pub range_noise_sigma_m: f64,
    pub range_noise_sigma_per_m: f64,
    /// Constant range bias: a measured range is the true range plus this. Not among
    /// the message's original fields; a reader without it takes it as 0, as
    /// `docs/capture-format.md` says.
    pub range_bias_m: f64,
    pub min_range_m: f64,
    pub max_range_m: f64,
    pub name: String,
    /// The EO camera's response curve, where it was calibrated (`texel-calib
    /// response`): Texel's extension, absent from the original message.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub eo_response: Option<EoResponse>,
}

impl Default for SensorInfo {
    fn default() -> Self {
        Self {
            version: 1,
            range_noise_sigma_m: 0.01,
            range_noise_sigma_per_m: 0.0,
            range_bias_m: 0.0,
            min_range_m: 0.3,
            max_range_m: 30.0,
            name: String::new(),
            eo_response: None,
        }
    }
}

impl SensorInfo {
    pub fn range_noise(&self) -> RangeNoise {
        RangeNoise {
            sigma_m: self.range_noise_sigma_m,
            sigma_per_m: self.range_noise_sigma_per_m,
        }
    }

    /// Checks the values a sensor can physically have.
    pub fn validate(&self) -> Result<(), SensorError> {
        let finite = [
            self.range_noise_sigma_m,
            self.range_noise_sigma_per_m,
            self.range_bias_m,
            self.min_range_m,
            self.max_range_m,
        ]
        .iter()
        .all(|v| v.is_finite());
        if !finite {
            return Err(SensorError::Invalid("range values must be finite".into()));
        }
        if self.range_noise_sigma_m < 0.0 || self.range_noise_sigma_per_m < 0.0 {
            return Err(SensorError::Invalid(
                "range noise sigmas must not be negative".into(),
            ));
        }
        if !(self.min_range_m >= 0.0 && self.max_range_m > self.min_range_m) {
            return Err(SensorError::Invalid(format!(
                "need 0 <= min_range_m < max_range_m, got {} and {}",
                self.min_range_m, self.max_range_m
            )));
        }
        Ok(())
    }
}

/// Everything known about a texel camera.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorModel {
    pub name: String,
    pub lidar: PinholeCamera,
    pub eo: PinholeCamera,
    /// The lidar frame's pose in the EO frame (maps lidar coordinates to EO).
    pub eo_from_lidar: Pose,
    pub range_noise: RangeNoise,
    /// Constant range bias, metres: the lidar reports `true range + range_bias_m`;
    /// fusion subtracts it.
    pub range_bias_m: f64,
    pub min_range_m: f64,
    pub max_range_m: f64,
    /// The EO camera's response curve (Debevec & Malik's `g` per channel), where it
    /// was calibrated: what turns its exposed frames into radiance.
    pub eo_response: Option<EoResponse>,
}

#[derive(Debug, Error)]
pub enum SensorError {
    #[error("cannot read sensor file {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("sensor file {path}: {message}")]
    Parse { path: String, message: String },
    #[error("sensor file {path}: {what}: {source}")]
    Camera {
        path: String,
        what: &'static str,
        source: CameraError,
    },
    #[error("sensor file {path}: eo_from_lidar: {source}")]
    Pose { path: String, source: PoseError },
    #[error("invalid sensor: {0}")]
    Invalid(String),
}

/// The on-disk layout of a sensor file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SensorFile {
    name: String,
    lidar: PinholeCamera,
    eo: PinholeCamera,
    eo_from_lidar: ExtrinsicFile,
    #[serde(default)]
    range: RangeFile,
    /// `[eo_response]`: `r`, `g`, `b`, 256 values of ln(exposure) each.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    eo_response: Option<EoResponse>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ExtrinsicFile {
    translation_m: [f64; 3],
    rotation_xyzw: [f64; 4],
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RangeFile {
    noise_sigma_m: f64,
    noise_sigma_per_m: f64,
    /// Measured range minus true range, metres.
    bias_m: f64,
    min_range_m: f64,
    max_range_m: f64,
}

impl Default for RangeFile {
    fn default() -> Self {
        let info = SensorInfo::default();
        Self {
            noise_sigma_m: info.range_noise_sigma_m,
            noise_sigma_per_m: info.range_noise_sigma_per_m,
            bias_m: info.range_bias_m,
            min_range_m: info.min_range_m,
            max_range_m: info.max_range_m,
        }
    }
}

impl SensorModel {
    /// Reads and validates a sensor file.
    pub fn load(path: &Path) -> Result<Self, SensorError> {
        let text = std::fs::read_to_string(path).map_err(|source| SensorError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    /// Parses and validates a sensor file's text; `origin` names it in errors.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, SensorError> {
        let file: SensorFile = toml::from_str(text).map_err(|e| SensorError::Parse {
            path: origin.to_string(),
            message: e.to_string(),
        })?;
        let camera_error = |what, source| SensorError::Camera {
            path: origin.to_string(),
            what,
            source,
        };
        file.lidar
            .validate()
            .map_err(|e| camera_error("lidar", e))?;
        file.eo.validate().map_err(|e| camera_error("eo", e))?;
        let eo_from_lidar = pose_from_parts(
            file.eo_from_lidar.translation_m,
            file.eo_from_lidar.rotation_xyzw,
        )
        .map_err(|source| SensorError::Pose {
            path: origin.to_string(),
            source,
        })?;
        let model = Self {
            name: file.name,
            lidar: file.lidar,
            eo: file.eo,
            eo_from_lidar,
            range_noise: RangeNoise {
                sigma_m: file.range.noise_sigma_m,
                sigma_per_m: file.range.noise_sigma_per_m,
            },
            range_bias_m: file.range.bias_m,
            min_range_m: file.range.min_range_m,
            max_range_m: file.range.max_range_m,
            eo_response: file.eo_response,
        };
        model.info().validate().map_err(|e| SensorError::Parse {
            path: origin.to_string(),
            message: e.to_string(),
        })?;
        Ok(model)
    }

    /// The sensor file text for this model.
    pub fn to_toml_string(&self) -> String {
        let (translation_m, rotation_xyzw) = pose_to_parts(&self.eo_from_lidar);
        let file = SensorFile {
            name: self.name.clone(),
            lidar: self.lidar.clone(),
            eo: self.eo.clone(),
            eo_from_lidar: ExtrinsicFile {
                translation_m,
                rotation_xyzw,
            },
            range: RangeFile {
                noise_sigma_m: self.range_noise.sigma_m,
                noise_sigma_per_m: self.range_noise.sigma_per_m,
                bias_m: self.range_bias_m,
                min_range_m: self.min_range_m,
                max_range_m: self.max_range_m,
            },
            eo_response: self.eo_response.clone(),
        };
        // Serialising plain numbers, strings and arrays cannot fail.
        toml::to_string_pretty(&file).unwrap_or_default()
    }

    /// The `/texel/sensor` message for this model.
    pub fn info(&self) -> SensorInfo {
        SensorInfo {
            version: 1,
            range_noise_sigma_m: self.range_noise.sigma_m,
            range_noise_sigma_per_m: self.range_noise.sigma_per_m,
            range_bias_m: self.range_bias_m,
            min_range_m: self.min_range_m,
            max_range_m: self.max_range_m,
            name: self.name.clone(),
            eo_response: self.eo_response.clone(),
        }
    }

    /// Assembles a model from the parts a capture carries.
    pub fn from_capture_parts(
        lidar: PinholeCamera,
        eo: PinholeCamera,
        eo_from_lidar: Pose,
        info: &SensorInfo,
    ) -> Self {
        Self {
            name: info.name.clone(),
            lidar,
            eo,
            eo_from_lidar,
            range_noise: info.range_noise(),
            range_bias_m: info.range_bias_m,
            min_range_m: info.min_range_m,
            max_range_m: info.max_range_m,
            eo_response: info.eo_response.clone(),
        }
    }
}

/// A sensor model with the lidar's ray table computed once: what fusion and the
/// simulator take.
#[derive(Debug, Clone)]
pub struct Sensor {
    pub model: SensorModel,
    pub lidar_rays: RayTable,
    /// Angles between neighbouring lidar rays (for the stretched-triangle rule).
    pub lidar_pitch: LidarPitch,
    /// The EO distortion model's valid-domain bound, computed once.
    pub eo_max_r2: Option<f64>,
    /// The lidar rays in the EO frame and the EO projection constants, so that
    /// fusion does per frame only what depends on the frame.
    pub fusion: FusionTables,
}

impl Sensor {
    pub fn new(model: SensorModel) -> Self {
        let lidar_rays = RayTable::new(&model.lidar);
        let lidar_pitch = LidarPitch::new(&lidar_rays);
        let eo_max_r2 = model.eo.max_radius_squared();
        let fusion = FusionTables::new(&model.eo_from_lidar, &model.eo, &lidar_rays);
        Self {
            model,
            lidar_rays,
            lidar_pitch,
            eo_max_r2,
            fusion,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FILE: &str = r#"
name = "test"

[lidar]
width = 128
height = 96
fx = 120.0
fy = 120.0
cx = 63.5
cy = 47.5

[eo]
width = 640
height = 480
fx = 600.0
fy = 600.0
cx = 319.5
cy = 239.5
distortion = { model = "plumb_bob", k1 = -0.1, k2 = 0.01, p1 = 0.0, p2 = 0.0, k3 = 0.0 }

[eo_from_lidar]
translation_m = [0.02, 0.0, 0.0]
rotation_xyzw = [0.0, 0.0, 0.0, 1.0]

[range]
noise_sigma_m = 0.005
"#;

    #[test]
    fn sensor_file_round_trips() {
        let m = SensorModel::from_toml_str(FILE, "test.toml").unwrap();
        assert_eq!(m.lidar.width, 128);
        assert_eq!(m.range_noise.sigma_m, 0.005);
        assert_eq!(m.max_range_m, 30.0);
        assert_eq!(m.range_bias_m, 0.0);
        let text = m.to_toml_string();
        let back = SensorModel::from_toml_str(&text, "again").unwrap();
        assert_eq!(back, m);
    }

    #[test]
    fn unknown_keys_and_bad_values_are_named() {
        let bad = FILE.replace("noise_sigma_m = 0.005", "noise_sigma = 0.005");
        let e = SensorModel::from_toml_str(&bad, "bad.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("bad.toml") && e.contains("noise_sigma"), "{e}");
        let bad = FILE.replace("fx = 120.0", "fx = -1.0");
        let e = SensorModel::from_toml_str(&bad, "neg.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("lidar") && e.contains("focal"), "{e}");
        let bad = FILE.replace("k1 = -0.1", "k9 = -0.1");
        let e = SensorModel::from_toml_str(&bad, "k9.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("k9"), "{e}");
    }

    #[test]
    fn sensor_json_ignores_unknown_and_defaults_missing() {
        let info: SensorInfo =
            serde_json::from_str(r#"{"range_noise_sigma_m": 0.02, "colour": "red"}"#).unwrap();
        assert_eq!(info.range_noise_sigma_m, 0.02);
        assert_eq!(info.max_range_m, 30.0);
        assert_eq!(info.version, 1);
        assert_eq!(info.range_bias_m, 0.0);
        assert!((info.range_noise().sigma_at(10.0) - 0.02).abs() < 1e-15);
    }

    #[test]
    fn range_bias_reads_round_trips_and_must_be_finite() {
        let biased = FILE.replace(
            "noise_sigma_m = 0.005",
            "noise_sigma_m = 0.005\nbias_m = 0.02",
        );
        let m = SensorModel::from_toml_str(&biased, "biased.toml").unwrap();
        assert_eq!(m.range_bias_m, 0.02);
        assert_eq!(m.info().range_bias_m, 0.02);
        let back = SensorModel::from_toml_str(&m.to_toml_string(), "again").unwrap();
        assert_eq!(back.range_bias_m, 0.02);
        let json = serde_json::to_string(&m.info()).unwrap();
        let info: SensorInfo = serde_json::from_str(&json).unwrap();
        assert_eq!(info.range_bias_m, 0.02);
        let bad = FILE.replace(
            "noise_sigma_m = 0.005",
            "noise_sigma_m = 0.005\nbias_m = nan",
        );
        let e = SensorModel::from_toml_str(&bad, "nan.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("nan.toml") && e.contains("finite"), "{e}");
        let info = SensorInfo {
            range_bias_m: f64::INFINITY,
            ..SensorInfo::default()
        };
        assert!(info.validate().is_err());
    }

    #[test]
    fn the_eo_response_rides_in_the_sensor_file_and_the_sensor_json() {
        let plain = SensorModel::from_toml_str(FILE, "plain.toml").unwrap();
        assert_eq!(plain.eo_response, None);
        assert!(!plain.to_toml_string().contains("eo_response"));
        assert!(
            !serde_json::to_string(&plain.info())
                .unwrap()
                .contains("eo_response")
        );
        let mut m = plain.clone();
        m.eo_response = Some(EoResponse::srgb());
        let back = SensorModel::from_toml_str(&m.to_toml_string(), "again").unwrap();
        assert_eq!(back, m);
        let json = serde_json::to_string(&m.info()).unwrap();
        let info: SensorInfo = serde_json::from_str(&json).unwrap();
        assert_eq!(info.eo_response, m.eo_response);
        // A curve of the wrong length is named, with its file.
        let short = format!("{FILE}\n[eo_response]\nr = [0.0, 1.0]\ng = [0.0]\nb = [0.0]\n");
        let e = SensorModel::from_toml_str(&short, "short.toml")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("short.toml") && e.contains("eo_response.r has 2 values"),
            "{e}"
        );
    }
}
