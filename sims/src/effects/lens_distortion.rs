//! `lens_distortion`: whether the texel camera's lenses distort.
//!
//! The sensor file's distortion coefficients describe the camera; a capture carries
//! the calibration its pixels were formed with, so fusing a capture is exact whatever
//! the effects. With this effect, both cameras are rendered through the sensor file's
//! `plumb_bob` model (coefficients multiplied by `scale`) and the capture's
//! calibrations carry those coefficients; without it both cameras are ideal pinholes
//! (same K, no distortion) and the calibrations say so. Rays are always formed by the
//! camera model the capture reports.

use serde::{Deserialize, Serialize};
use texel::{Distortion, PinholeCamera, SensorModel};

use super::{EffectParams, ParamDoc, Target, check_range};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LensDistortion {
    pub scale: f64,
}

impl Default for LensDistortion {
    fn default() -> Self {
        Self { scale: 1.0 }
    }
}

impl EffectParams for LensDistortion {
    const NAME: &'static str = "lens_distortion";
    const TARGET: Target = Target::Optics;
    const MODEL: &'static str = "Both cameras are rendered through the sensor file's \
        plumb_bob model (coefficients × scale) and the capture's calibrations carry \
        it; without this effect both are ideal pinholes with the same K, and the \
        calibrations say so.";
    const PARAMS: &'static [ParamDoc] = &[ParamDoc {
        name: "scale",
        unit: "1",
        what: "multiplier on every distortion coefficient of the sensor file",
    }];

    fn validate(&self) -> Result<(), String> {
        check_range("scale", self.scale, 0.0..=10.0)
    }
}

fn scaled(camera: &PinholeCamera, scale: Option<f64>) -> PinholeCamera {
    let mut c = camera.clone();
    c.distortion = match (scale, c.distortion) {
        (Some(s), Distortion::PlumbBob(mut d)) => {
            d.k1 *= s;
            d.k2 *= s;
            d.p1 *= s;
            d.p2 *= s;
            d.k3 *= s;
            if d.is_identity() {
                Distortion::None
            } else {
                Distortion::PlumbBob(d)
            }
        }
        _ => Distortion::None,
    };
    c
}

/// The sensor model the simulation renders with and the capture carries: the file's
/// model with distortion kept (scaled) when `effect` is present, removed otherwise.
pub fn effective_model(model: &SensorModel, effect: Option<&LensDistortion>) -> SensorModel {
    let scale = effect.map(|e| e.scale);
    let mut out = model.clone();
    out.lidar = scaled(&model.lidar, scale);
    out.eo = scaled(&model.eo, scale);
    out
}
