//! `moving_lights`: lamps that swing and flicker while the geometry stands still.
//!
//! Model: every point light of the scene moves along a sinusoid about its position in
//! the scene file, `p(t) = p₀ + amplitude_m · sin(2π t / period_s + φ_k) · axis`, and
//! its intensity is modulated as `I(t) = I₀ · (1 + intensity_modulation · sin(2π t /
//! flicker_period_s + φ_k))`, with `t` the frame's timestamp in seconds and `φ_k = k ·
//! 137.5°` for the k-th point light (so the lamps do not move in step). Directional
//! lights, the ambient term and every surface stay as they are: the EO shading changes
//! from frame to frame while the lidar sees the same geometry, which breaks the
//! brightness constancy photometric registration assumes. A frame stays a function of
//! (scene, seed, frame index): its lights are those of its timestamp.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};
use crate::light::{Light, Lighting};

/// The golden angle, radians: the phase step from one point light to the next.
const PHASE_STEP_RAD: f64 = 2.399_963_229_728_653;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MovingLights {
    pub amplitude_m: f64,
    pub axis: [f64; 3],
    pub period_s: f64,
    pub intensity_modulation: f64,
    pub flicker_period_s: f64,
}

impl Default for MovingLights {
    fn default() -> Self {
        Self {
            amplitude_m: 0.3,
            axis: [1.0, 0.0, 0.0],
            period_s: 4.0,
            intensity_modulation: 0.3,
            flicker_period_s: 1.3,
        }
    }
}

impl EffectParams for MovingLights {
    const NAME: &'static str = "moving_lights";
    const TARGET: Target = Target::Eo;
    const MODEL: &'static str = "Every point light swings along `axis` by amplitude_m · \
        sin(2π t / period_s + φ_k) about its scene position and its intensity is scaled by \
        1 + intensity_modulation · sin(2π t / flicker_period_s + φ_k), t the frame's \
        timestamp, φ_k = k · 137.5° for the k-th point light. Geometry and the lidar are \
        unchanged; the EO shading changes between frames (no brightness constancy).";
    const PARAMS: &'static [ParamDoc] = &[
        ParamDoc {
            name: "amplitude_m",
            unit: "m",
            what: "peak displacement of each point light along axis (0: lights stay put)",
        },
        ParamDoc {
            name: "axis",
            unit: "1",
            what: "world direction of the swing (normalised)",
        },
        ParamDoc {
            name: "period_s",
            unit: "s",
            what: "period of the swing",
        },
        ParamDoc {
            name: "intensity_modulation",
            unit: "1",
            what: "relative amplitude of the flicker, in [0, 1] (0: steady lights)",
        },
        ParamDoc {
            name: "flicker_period_s",
            unit: "s",
            what: "period of the flicker",
        },
    ];

    fn validate(&self) -> Result<(), String> {
        check_range("amplitude_m", self.amplitude_m, 0.0..=100.0)?;
        let n = Vector3::from(self.axis).norm();
        if !(n.is_finite() && n > 1.0e-9) {
            return Err(format!(
                "axis = {:?} must be a non-zero finite vector",
                self.axis
            ));
        }
        check_range("period_s", self.period_s, 0.01..=1.0e6)?;
        check_range("intensity_modulation", self.intensity_modulation, 0.0..=1.0)?;
        check_range("flicker_period_s", self.flicker_period_s, 0.01..=1.0e6)
    }
}

impl MovingLights {
    /// The scene's `lighting` at time `t_s` (seconds, the frame's timestamp).
    pub fn lighting_at(&self, lighting: &Lighting, t_s: f64) -> Lighting {
        let axis = Vector3::from(self.axis).normalize();
        let tau = std::f64::consts::TAU;
        let mut k = 0u32;
        let lights = lighting
            .lights
            .iter()
            .map(|light| match light {
                Light::Point {
                    position,
                    color,
                    intensity,
                    shadows,
                } => {
                    let phase = f64::from(k) * PHASE_STEP_RAD;
                    k += 1;
                    let swing = self.amplitude_m * (tau * t_s / self.period_s + phase).sin();
                    let flicker = 1.0
                        + self.intensity_modulation
                            * (tau * t_s / self.flicker_period_s + phase).sin();
                    Light::Point {
                        position: position + axis * swing,
                        color: *color,
                        intensity: (f64::from(*intensity) * flicker).max(0.0) as f32,
                        shadows: *shadows,
                    }
                }
                other => other.clone(),
            })
            .collect();
        Lighting {
            ambient: lighting.ambient,
            lights,
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Point3;

    use super::*;

    #[test]
    fn point_lights_swing_and_flicker_directional_ones_do_not() {
        let lighting = Lighting {
            ambient: [0.1; 3],
            lights: vec![
                Light::Point {
                    position: Point3::new(1.0, 2.0, 3.0),
                    color: [1.0; 3],
                    intensity: 2.0,
                    shadows: true,
                },
                Light::Directional {
                    towards_light: Vector3::z(),
                    color: [1.0; 3],
                    intensity: 1.0,
                    shadows: false,
                },
            ],
        };
        let m = MovingLights {
            amplitude_m: 0.5,
            axis: [0.0, 2.0, 0.0],
            period_s: 4.0,
            intensity_modulation: 0.25,
            flicker_period_s: 4.0,
        };
        // A quarter period in: the first light (phase 0) at its peak.
        let lit = m.lighting_at(&lighting, 1.0);
        let Light::Point {
            position,
            intensity,
            ..
        } = &lit.lights[0]
        else {
            panic!("not a point light");
        };
        assert!((position - Point3::new(1.0, 2.5, 3.0)).norm() < 1e-12);
        assert!((intensity - 2.5).abs() < 1e-6);
        assert_eq!(lit.lights[1], lighting.lights[1]);
        assert_eq!(lit.ambient, lighting.ambient);
        // At t = 0 (and every full period) the first light is where the scene puts it.
        assert_eq!(m.lighting_at(&lighting, 0.0).lights[0], lighting.lights[0]);
        // Nothing moves with zero amplitude and modulation.
        let still = MovingLights {
            amplitude_m: 0.0,
            intensity_modulation: 0.0,
            ..m
        };
        assert_eq!(still.lighting_at(&lighting, 1.7), lighting);
    }

    #[test]
    fn bad_parameters_are_named() {
        let bad = MovingLights {
            axis: [0.0; 3],
            ..MovingLights::default()
        };
        assert!(bad.validate().unwrap_err().contains("axis"));
        let bad = MovingLights {
            intensity_modulation: 1.5,
            ..MovingLights::default()
        };
        assert!(bad.validate().unwrap_err().contains("intensity_modulation"));
        let bad = MovingLights {
            period_s: 0.0,
            ..MovingLights::default()
        };
        assert!(bad.validate().unwrap_err().contains("period_s"));
    }
}
