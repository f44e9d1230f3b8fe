//! `specular`: view-dependent highlights.
//!
//! Model: a Blinn-Phong lobe `k_s · E · max(0, n·h)^shininess` per light is added to
//! the Lambertian radiance, with `k_s` and `shininess` from each material
//! (`specular`, `shininess`) and `k_s` multiplied by `scale`. Without this effect every
//! surface is Lambertian, so a surface looks the same from every viewpoint.

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Specular {
    pub scale: f64,
}

impl Default for Specular {
    fn default() -> Self {
        Self { scale: 1.0 }
    }
}

impl EffectParams for Specular {
    const NAME: &'static str = "specular";
    const TARGET: Target = Target::Eo;
    const MODEL: &'static str = "Blinn-Phong highlights k_s·E·max(0, n·h)^shininess per \
        light from each material's specular and shininess; without it surfaces are \
        Lambertian (view-independent).";
    const PARAMS: &'static [ParamDoc] = &[ParamDoc {
        name: "scale",
        unit: "1",
        what: "multiplier on every material's specular reflectance",
    }];

    fn validate(&self) -> Result<(), String> {
        check_range("scale", self.scale, 0.0..=100.0)
    }
}
