//! `vignetting`: light fall-off towards the image corners.
//!
//! Model: natural vignetting of a thin lens, the `cos⁴θ` law, generalised: each pixel's
//! irradiance is multiplied by `1 - strength · (1 - cos^exponent θ)`, with `θ` the
//! angle between the pixel's ray and the optical axis (from the EO camera model).

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Vignetting {
    pub strength: f64,
    pub exponent: f64,
}

impl Default for Vignetting {
    fn default() -> Self {
        Self {
            strength: 1.0,
            exponent: 4.0,
        }
    }
}

impl EffectParams for Vignetting {
    const NAME: &'static str = "vignetting";
    const TARGET: Target = Target::Eo;
    const MODEL: &'static str = "Irradiance × (1 - strength·(1 - cos^exponent θ)), θ the \
        pixel ray's angle off the optical axis (cos⁴ law of a thin lens at strength 1, \
        exponent 4).";
    const PARAMS: &'static [ParamDoc] = &[
        ParamDoc {
            name: "strength",
            unit: "1",
            what: "0 = none, 1 = the full cos^exponent law",
        },
        ParamDoc {
            name: "exponent",
            unit: "1",
            what: "power of cos θ (4 for natural vignetting)",
        },
    ];

    fn validate(&self) -> Result<(), String> {
        check_range("strength", self.strength, 0.0..=1.0)?;
        check_range("exponent", self.exponent, 0.0..=16.0)
    }
}

impl Vignetting {
    /// The irradiance factor for a pixel whose unit ray has `cos θ = cos_theta`.
    #[inline]
    pub fn factor(&self, cos_theta: f64) -> f32 {
        let c = cos_theta.clamp(0.0, 1.0);
        (1.0 - self.strength * (1.0 - c.powf(self.exponent))) as f32
    }
}
