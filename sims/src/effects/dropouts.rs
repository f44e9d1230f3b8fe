//! `dropouts`: pixels where a real lidar gets no return.
//!
//! Rules, checked in this order on the pixel's (possibly mixed) echo:
//! 1. **range limits** (`range_limits = true`): the true range is below the sensor's
//!    `min_range_m` or beyond its `max_range_m`;
//! 2. **grazing incidence**: the angle between the ray and the surface normal exceeds
//!    `max_incidence_deg`;
//! 3. **low signal**: the returned signal `ρ · cos α · (reference_range_m / r)²`
//!    (Lambertian target of lidar reflectivity `ρ`, inverse-square spreading) is below
//!    `min_signal`;
//! 4. **random**: with probability `random_probability` per pixel and frame.
//!
//! Rules 1-3 are deterministic: a pixel drops out exactly where its rule says.

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};
use crate::rng::PixelRng;
use crate::world::SurfaceSample;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Dropouts {
    pub range_limits: bool,
    pub max_incidence_deg: f64,
    pub min_signal: f64,
    pub reference_range_m: f64,
    pub random_probability: f64,
}

impl Default for Dropouts {
    fn default() -> Self {
        Self {
            range_limits: true,
            max_incidence_deg: 85.0,
            min_signal: 0.002,
            reference_range_m: 1.0,
            random_probability: 0.0,
        }
    }
}

/// Why a pixel dropped out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DropReason {
    OutOfRange,
    Grazing,
    LowSignal,
    Random,
}

impl EffectParams for Dropouts {
    const NAME: &'static str = "dropouts";
    const TARGET: Target = Target::Lidar;
    const MODEL: &'static str = "No return where: the range is outside the sensor's \
        [min_range_m, max_range_m] (range_limits); the incidence angle exceeds \
        max_incidence_deg; the signal ρ·cos α·(reference_range_m/r)² is below min_signal \
        (ρ = lidar reflectivity); or at random with random_probability.";
    const PARAMS: &'static [ParamDoc] = &[
        ParamDoc {
            name: "range_limits",
            unit: "bool",
            what: "drop returns outside the sensor's min/max range",
        },
        ParamDoc {
            name: "max_incidence_deg",
            unit: "deg",
            what: "steepest incidence (ray to surface normal) that still returns",
        },
        ParamDoc {
            name: "min_signal",
            unit: "1",
            what: "weakest return detected, as reflectivity·cos·(reference/r)²",
        },
        ParamDoc {
            name: "reference_range_m",
            unit: "m",
            what: "range at which the signal equals reflectivity·cos",
        },
        ParamDoc {
            name: "random_probability",
            unit: "1",
            what: "probability of a dropout anywhere, per pixel and frame",
        },
    ];

    fn validate(&self) -> Result<(), String> {
        check_range("max_incidence_deg", self.max_incidence_deg, 0.0..=90.0)?;
        check_range("min_signal", self.min_signal, 0.0..=1.0e6)?;
        check_range("reference_range_m", self.reference_range_m, 1.0e-3..=1.0e6)?;
        check_range("random_probability", self.random_probability, 0.0..=1.0)
    }
}

impl Dropouts {
    /// The signal of an echo, `ρ cos α (r₀ / r)²`; 0 for a range at or below zero.
    pub fn signal(&self, s: &SurfaceSample) -> f64 {
        if s.range_m <= 0.0 {
            return 0.0;
        }
        let ratio = self.reference_range_m / s.range_m;
        f64::from(s.reflectivity) * s.cos_incidence * ratio * ratio
    }

    /// Whether (and why) the echo is lost.
    pub fn decide(
        &self,
        s: &SurfaceSample,
        min_range_m: f64,
        max_range_m: f64,
        rng: &PixelRng,
    ) -> Option<DropReason> {
        if self.range_limits && (s.range_m < min_range_m || s.range_m > max_range_m) {
            return Some(DropReason::OutOfRange);
        }
        if s.cos_incidence < self.max_incidence_deg.to_radians().cos() {
            return Some(DropReason::Grazing);
        }
        if self.signal(s) < self.min_signal {
            return Some(DropReason::LowSignal);
        }
        if self.random_probability > 0.0 && rng.uniform(0) < self.random_probability {
            return Some(DropReason::Random);
        }
        None
    }
}
