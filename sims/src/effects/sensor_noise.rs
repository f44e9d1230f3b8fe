//! `sensor_noise`: photon shot noise and read noise of the EO sensor.
//!
//! Model: a pixel value `x` in linear units (1 = full well) collects `N = x · full_well_e`
//! photo-electrons; the measured charge is `N + √N · n₁ + read_noise_e · n₂` with
//! `n₁, n₂ ~ N(0, 1)` per pixel, channel and frame (the Gaussian limit of Poisson shot
//! noise, accurate above a few electrons), clipped to `[0, full_well_e]` (saturation),
//! then divided by `full_well_e` again. The two independent Gaussian terms are drawn
//! as one, `√(N + read_noise_e²) · n`, which has the same distribution. The numbers
//! `n` come from the table sampler (`rng::normal_table`): three per pixel from two
//! hashes.

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorNoise {
    pub full_well_e: f64,
    pub read_noise_e: f64,
}

impl Default for SensorNoise {
    fn default() -> Self {
        Self {
            full_well_e: 6000.0,
            read_noise_e: 4.0,
        }
    }
}

impl EffectParams for SensorNoise {
    const NAME: &'static str = "sensor_noise";
    const TARGET: Target = Target::Eo;
    const MODEL: &'static str = "Linear value x → N = x·full_well_e electrons; measured \
        N + √N·N(0,1) (shot) + read_noise_e·N(0,1) (read), clipped to [0, full_well_e], \
        per pixel, channel and frame.";
    const PARAMS: &'static [ParamDoc] = &[
        ParamDoc {
            name: "full_well_e",
            unit: "e-",
            what: "electrons at saturation (linear value 1)",
        },
        ParamDoc {
            name: "read_noise_e",
            unit: "e- rms",
            what: "read noise standard deviation",
        },
    ];

    fn validate(&self) -> Result<(), String> {
        check_range("full_well_e", self.full_well_e, 1.0..=1.0e9)?;
        check_range("read_noise_e", self.read_noise_e, 0.0..=1.0e6)
    }
}

impl SensorNoise {
    /// Noisy linear values of one RGB pixel (inputs clipped to [0, 1] first), given
    /// the pixel's three standard normal numbers (one per channel, carrying the shot
    /// and read variances added).
    #[inline]
    pub fn apply(&self, rgb: [f32; 3], normals: [f32; 3]) -> [f32; 3] {
        // In units of the full well (validate keeps it >= 1): the measured charge over
        // the full well is x + √(x / full_well_e + (read_noise_e / full_well_e)²) · n,
        // the model above divided through, without a division per channel.
        let per_electron = 1.0 / self.full_well_e;
        let read = self.read_noise_e * per_electron;
        let read_variance = read * read;
        let mut out = [0.0f32; 3];
        for ((o, &v), &n) in out.iter_mut().zip(&rgb).zip(&normals) {
            let x = f64::from(v);
            let x = if x.is_finite() {
                x.clamp(0.0, 1.0)
            } else {
                0.0
            };
            let sigma = (x * per_electron + read_variance).sqrt();
            let measured = x + sigma * f64::from(n);
            *o = measured.clamp(0.0, 1.0) as f32;
        }
        out
    }
}
