//! `range_quantisation`: the range counter's resolution.
//!
//! Model: the reported range is rounded to the nearest multiple of `step_m`
//! (a time-of-flight counter's bin, or the TXL1 `range_unit_um`). A range that
//! rounds to zero is a no-return.

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RangeQuantisation {
    pub step_m: f64,
}

impl Default for RangeQuantisation {
    fn default() -> Self {
        Self { step_m: 0.001 }
    }
}

impl EffectParams for RangeQuantisation {
    const NAME: &'static str = "range_quantisation";
    const TARGET: Target = Target::Lidar;
    const MODEL: &'static str = "The range is rounded to the nearest multiple of step_m.";
    const PARAMS: &'static [ParamDoc] = &[ParamDoc {
        name: "step_m",
        unit: "m",
        what: "range resolution (quantisation step)",
    }];

    fn validate(&self) -> Result<(), String> {
        check_range("step_m", self.step_m, 1.0e-6..=10.0)
    }
}

impl RangeQuantisation {
    #[inline]
    pub fn apply(&self, range_m: f64) -> f64 {
        // step_m > 0 by validation.
        (range_m / self.step_m).round() * self.step_m
    }
}
