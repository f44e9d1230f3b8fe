//! `motion_blur`: the EO exposure integrates over the camera's motion.
//!
//! Model: the EO image is the mean of `samples` renders at times evenly spread over the
//! exposure `[t - shutter_s/2, t + shutter_s/2]` (stratified midpoints), each at the
//! trajectory's true pose at that time; `t` is the frame's timestamp, the mid-exposure
//! instant, where `/truth/pose` is given. The lidar frame is instantaneous at `t`.

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionBlur {
    pub shutter_s: f64,
    pub samples: u32,
}

impl Default for MotionBlur {
    fn default() -> Self {
        Self {
            shutter_s: 0.01,
            samples: 8,
        }
    }
}

impl EffectParams for MotionBlur {
    const NAME: &'static str = "motion_blur";
    const TARGET: Target = Target::Eo;
    const MODEL: &'static str = "The EO image is the mean of `samples` renders at poses \
        spread evenly over the exposure [t - shutter_s/2, t + shutter_s/2] around the \
        frame time t (the /truth/pose instant).";
    const PARAMS: &'static [ParamDoc] = &[
        ParamDoc {
            name: "shutter_s",
            unit: "s",
            what: "exposure time",
        },
        ParamDoc {
            name: "samples",
            unit: "count",
            what: "renders averaged over the exposure (cost grows linearly)",
        },
    ];

    fn validate(&self) -> Result<(), String> {
        check_range("shutter_s", self.shutter_s, 0.0..=1.0)?;
        check_range("samples", f64::from(self.samples), 1.0..=64.0)
    }
}

impl MotionBlur {
    /// Offsets from the frame time (seconds) of the sub-exposures.
    pub fn offsets_s(&self) -> Vec<f64> {
        let n = self.samples.max(1);
        (0..n)
            .map(|k| ((f64::from(k) + 0.5) / f64::from(n) - 0.5) * self.shutter_s)
            .collect()
    }
}
