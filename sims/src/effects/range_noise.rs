//! `range_noise`: Gaussian range noise with the sensor's standard deviation.
//!
//! Model: the reported range is `r + scale · σ(r) · n`, `n ~ N(0, 1)` drawn per pixel
//! and frame, with `σ(r) = range_noise_sigma_m + range_noise_sigma_per_m · r` from the
//! sensor model (the same σ the capture's `/texel/sensor` reports, so downstream code
//! that trusts the sensor's σ is right). A noisy range at or below zero is a
//! no-return.

use serde::{Deserialize, Serialize};
use texel::RangeNoise;

use super::{EffectParams, ParamDoc, Target, check_range};
use crate::rng::PixelRng;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RangeNoiseEffect {
    /// Multiplier on the sensor's σ(r).
    pub scale: f64,
}

impl Default for RangeNoiseEffect {
    fn default() -> Self {
        Self { scale: 1.0 }
    }
}

impl EffectParams for RangeNoiseEffect {
    const NAME: &'static str = "range_noise";
    const TARGET: Target = Target::Lidar;
    const MODEL: &'static str = "Gaussian range noise: r + scale·σ(r)·N(0,1) with \
        σ(r) = range_noise_sigma_m + range_noise_sigma_per_m·r from the sensor model; \
        a result <= 0 is a no-return.";
    const PARAMS: &'static [ParamDoc] = &[ParamDoc {
        name: "scale",
        unit: "1",
        what: "multiplier on the sensor's sigma(r); 1 simulates the sensor as specified",
    }];

    fn validate(&self) -> Result<(), String> {
        check_range("scale", self.scale, 0.0..=100.0)
    }
}

impl RangeNoiseEffect {
    /// The noisy range.
    #[inline]
    pub fn apply(&self, range_m: f64, noise: &RangeNoise, rng: &PixelRng) -> f64 {
        range_m + self.scale * noise.sigma_at(range_m) * f64::from(rng.gaussian(0))
    }
}
