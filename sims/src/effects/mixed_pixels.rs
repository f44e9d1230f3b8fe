//! `mixed_pixels`: a beam footprint that straddles a depth edge.
//!
//! Model: a lidar pixel's beam has a footprint `footprint_px` pixels wide (square,
//! uniform). It is sampled by `samples_per_side²` sub-rays on a regular grid inside
//! that footprint, each formed through the lidar's camera model. Each sub-ray that hits
//! a surface returns an echo of energy `ρ · cos α / r²`. The detector cannot separate
//! echoes closer together than the pulse resolution: it reports the energy-weighted
//! mean range of all echoes within `pulse_resolution_m` of the strongest one. Across a
//! depth step smaller than the resolution this gives the classic mixed pixel, a
//! point between the two surfaces; across a larger step the strongest surface wins.
//! The incidence and reflectivity reported with a mixed echo are energy-weighted too.
//!
//! With `adaptive` (the default) only beams that may straddle surfaces are sampled:
//! those where a pixel within half a footprint (at least one pixel) has a return and
//! this one none or the reverse, a return from another object, a range that differs
//! by more than one smooth surface explains (twice the change the incidence predicts,
//! plus 1 mm), or a reflectivity step that could walk the echo's range by more than
//! 1 mm; and pixels at the image border. Elsewhere the footprint lies on one smooth,
//! evenly reflecting surface and the centre ray's echo stands for it: the footprint
//! is symmetric about the centre, so their ranges differ only to second order. A
//! feature narrower than the pixel spacing that meets no pixel's centre ray is
//! missed, where sampling everywhere could catch it.

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};
use crate::world::SurfaceSample;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MixedPixels {
    pub footprint_px: f64,
    pub samples_per_side: u32,
    pub pulse_resolution_m: f64,
    /// Sample the footprint only where the beam may straddle surfaces (see the module
    /// documentation); `false` samples every pixel's footprint.
    pub adaptive: bool,
}

impl Default for MixedPixels {
    fn default() -> Self {
        Self {
            footprint_px: 1.0,
            samples_per_side: 3,
            pulse_resolution_m: 1.5,
            adaptive: true,
        }
    }
}

impl EffectParams for MixedPixels {
    const NAME: &'static str = "mixed_pixels";
    const TARGET: Target = Target::Lidar;
    const MODEL: &'static str = "Each pixel's beam footprint (footprint_px wide) is \
        sampled by samples_per_side² sub-rays; echoes of energy ρ·cos α/r² within \
        pulse_resolution_m of the strongest are merged into their energy-weighted mean \
        range (a mixed pixel between two surfaces). With adaptive, only beams that may \
        straddle surfaces or a reflectivity step are sampled; the others take the \
        centre ray's echo.";
    const PARAMS: &'static [ParamDoc] = &[
        ParamDoc {
            name: "footprint_px",
            unit: "px",
            what: "beam footprint width in lidar pixels",
        },
        ParamDoc {
            name: "samples_per_side",
            unit: "count",
            what: "sub-rays per side of the footprint (cost grows with its square)",
        },
        ParamDoc {
            name: "pulse_resolution_m",
            unit: "m",
            what: "echoes closer than this are merged (range resolution of the pulse)",
        },
        ParamDoc {
            name: "adaptive",
            unit: "bool",
            what: "sample the footprint only where the beam may straddle surfaces \
                   (false: at every pixel)",
        },
    ];

    fn validate(&self) -> Result<(), String> {
        check_range("footprint_px", self.footprint_px, 0.0..=8.0)?;
        check_range(
            "samples_per_side",
            f64::from(self.samples_per_side),
            1.0..=16.0,
        )?;
        check_range("pulse_resolution_m", self.pulse_resolution_m, 0.0..=1.0e3)
    }
}

impl MixedPixels {
    /// Sub-ray offsets from the pixel centre, in pixels, row-major.
    pub fn offsets_px(&self) -> Vec<[f64; 2]> {
        let n = self.samples_per_side.max(1);
        let step = |k: u32| ((f64::from(k) + 0.5) / f64::from(n) - 0.5) * self.footprint_px;
        (0..n)
            .flat_map(|j| (0..n).map(move |i| [step(i), step(j)]))
            .collect()
    }

    /// Merges the echoes of one pixel's sub-rays (`None` = no hit).
    pub fn combine<'a, I>(&self, echoes: I) -> Option<SurfaceSample>
    where
        I: IntoIterator<Item = &'a Option<SurfaceSample>> + Clone,
    {
        let energy = |s: &SurfaceSample| {
            let r2 = (s.range_m * s.range_m).max(1.0e-12);
            (f64::from(s.reflectivity) * s.cos_incidence).max(0.0) / r2
        };
        let mut strongest: Option<(f64, &SurfaceSample)> = None;
        for s in echoes.clone().into_iter().flatten() {
            let e = energy(s);
            if strongest.is_none_or(|(best, _)| e > best) {
                strongest = Some((e, s));
            }
        }
        let (_, peak) = strongest?;
        let (mut w_sum, mut r_sum, mut cos_sum, mut rho_sum) = (0.0, 0.0, 0.0, 0.0);
        for s in echoes.into_iter().flatten() {
            if (s.range_m - peak.range_m).abs() <= self.pulse_resolution_m {
                let w = energy(s);
                w_sum += w;
                r_sum += w * s.range_m;
                cos_sum += w * s.cos_incidence;
                rho_sum += w * f64::from(s.reflectivity);
            }
        }
        if w_sum <= 0.0 {
            // Every echo has zero energy (black or grazing): report the peak as is.
            return Some(*peak);
        }
        Some(SurfaceSample {
            range_m: r_sum / w_sum,
            cos_incidence: cos_sum / w_sum,
            reflectivity: (rho_sum / w_sum) as f32,
            object: peak.object,
        })
    }
}
