//! `global_illumination`: light that reaches a surface after bouncing off others
//! (inter-reflection, colour bleeding, glossy reflections of the scene under
//! `specular`). Only the Mitsuba backend simulates it; asking for it selects that
//! backend (and is an error with `--backend builtin`).
//!
//! Model: unidirectional path tracing (Mitsuba's `path` integrator) with paths of at
//! most `max_depth` segments from the camera (2 = direct light only, as the built-in
//! renderer), `samples_per_pixel` paths through each pixel's exact ray, averaged. The
//! scene's ambient term is added once at the first hit, as without the effect, so the
//! effect adds only the light that bounced.

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GlobalIllumination {
    pub max_depth: u32,
    pub samples_per_pixel: u32,
}

impl Default for GlobalIllumination {
    fn default() -> Self {
        Self {
            max_depth: 4,
            samples_per_pixel: 16,
        }
    }
}

impl EffectParams for GlobalIllumination {
    const NAME: &'static str = "global_illumination";
    const TARGET: Target = Target::Eo;
    const NEEDS_MITSUBA: bool = true;
    const MODEL: &'static str = "Path-traced inter-reflection (Mitsuba's path integrator): \
        paths of at most max_depth segments (2 = direct light only), samples_per_pixel \
        paths along each pixel's ray, averaged; the ambient term is added once at the \
        first hit. Needs the Mitsuba backend, which it selects.";
    const PARAMS: &'static [ParamDoc] = &[
        ParamDoc {
            name: "max_depth",
            unit: "segments",
            what: "longest light path from the camera (2 = direct light only)",
        },
        ParamDoc {
            name: "samples_per_pixel",
            unit: "paths",
            what: "paths traced per pixel (noise falls as 1/sqrt)",
        },
    ];

    fn validate(&self) -> Result<(), String> {
        check_range("max_depth", f64::from(self.max_depth), 2.0..=64.0)?;
        check_range(
            "samples_per_pixel",
            f64::from(self.samples_per_pixel),
            1.0..=4096.0,
        )
    }
}
