//! Tone mapping of linear radiance to display values, on the CPU: the reference the
//! GPU pass (`tonemap.wgsl`, [`crate::gpu::ToneMapPass`]) is tested against, and the
//! settings both take. Reinhard's operator as Lechelek et al. (2019, §5, eqs. 8-12)
//! use it, a filmic curve (Narkowicz's fit of the ACES reference rendering transform)
//! and plain clipping, each after scaling by `key / L_a`, where `L_a` is the view's
//! log-average luminance (auto-exposure) or a fixed adaptation level.

/// Rec. 709 luminance weights (the seed's eq. 8, to three decimals there).
pub const LUMINANCE: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// The offset inside the log-average (the seed's ε in eq. 9), in radiance units (1 is
/// white at 0 EV): black pixels count as this, not as log 0.
pub const LOG_AVERAGE_EPSILON: f32 = 1.0e-4;

/// How radiance is compressed into `[0, 1]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ToneOperator {
    /// `L_d = L_s / (1 + L_s)` on luminance, the colour keeping its channel ratios
    /// (eq. 11).
    #[default]
    Reinhard,
    /// Narkowicz's ACES fit `x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)` per
    /// channel: a toe and a shoulder, as film.
    Filmic,
    /// Scaled and clipped at 1: what an 8-bit camera at that exposure would show.
    Clip,
}

impl ToneOperator {
    pub const ALL: [Self; 3] = [Self::Reinhard, Self::Filmic, Self::Clip];

    pub fn name(self) -> &'static str {
        match self {
            Self::Reinhard => "reinhard",
            Self::Filmic => "filmic",
            Self::Clip => "clip",
        }
    }

    /// The shader's code for the operator.
    pub fn code(self) -> u32 {
        match self {
            Self::Reinhard => 0,
            Self::Filmic => 1,
            Self::Clip => 2,
        }
    }

    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|o| o.name() == name)
    }
}

/// The user's controls.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToneMapSettings {
    pub operator: ToneOperator,
    /// The key `k` of eq. 10: the display value the adaptation level maps to.
    pub key: f32,
    /// Exposure in stops: the display values are scaled by `2^exposure_ev` (eq. 12's
    /// `exposure`, for Reinhard after compression; before it for the others).
    pub exposure_ev: f32,
    /// The display gamma of eq. 12.
    pub gamma: f32,
    /// `None`: auto-exposure, `L_a` the view's log-average luminance (eq. 9); a value:
    /// that fixed adaptation level (no flicker as the view changes).
    pub adaptation: Option<f32>,
}

impl Default for ToneMapSettings {
    fn default() -> Self {
        Self {
            operator: ToneOperator::Reinhard,
            key: 0.18,
            exposure_ev: 0.0,
            gamma: 2.2,
            adaptation: None,
        }
    }
}

/// Why settings are refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ToneMapError {
    #[error("{name} = {value}: must be a finite number in {range}")]
    OutOfRange {
        name: &'static str,
        value: f32,
        range: &'static str,
    },
}

impl ToneMapSettings {
    /// Key, gamma and adaptation positive, exposure within ±30 stops, all finite.
    pub fn validate(&self) -> Result<(), ToneMapError> {
        let check = |name, value: f32, ok: bool, range| {
            if value.is_finite() && ok {
                Ok(())
            } else {
                Err(ToneMapError::OutOfRange { name, value, range })
            }
        };
        check(
            "key",
            self.key,
            self.key > 0.0 && self.key <= 100.0,
            "(0, 100]",
        )?;
        check(
            "exposure_ev",
            self.exposure_ev,
            self.exposure_ev.abs() <= 30.0,
            "[-30, 30]",
        )?;
        check(
            "gamma",
            self.gamma,
            (0.1..=10.0).contains(&self.gamma),
            "[0.1, 10]",
        )?;
        if let Some(a) = self.adaptation {
            check("adaptation", a, a > 0.0, "(0, inf)")?;
        }
        Ok(())
    }
}

/// The luminance of a linear colour (eq. 8), never negative.
#[inline]
pub fn luminance(c: [f32; 3]) -> f32 {
    (LUMINANCE[0] * c[0] + LUMINANCE[1] * c[1] + LUMINANCE[2] * c[2]).max(0.0)
}

/// The log-average luminance of eq. 9, `exp(mean(ln(ε + L)))` (the seed prints the
/// `1/N` outside the exponential, a typo for Reinhard et al.'s geometric mean); 1 for
/// an empty image. Non-finite values count as black.
pub fn log_average_luminance(radiance: &[[f32; 3]]) -> f32 {
    if radiance.is_empty() {
        return 1.0;
    }
    let sum: f64 = radiance
        .iter()
        .map(|c| {
            let l = luminance(*c);
            let l = if l.is_finite() { l } else { 0.0 };
            f64::from(LOG_AVERAGE_EPSILON + l).ln()
        })
        .sum();
    ((sum / radiance.len() as f64).exp() as f32).max(f32::MIN_POSITIVE)
}

/// Narkowicz's ACES fit, for `x >= 0`.
#[inline]
fn aces(x: f32) -> f32 {
    (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)
}

/// One colour's display value in `[0, 1]` per channel, with adaptation level `l_a`
/// (eqs. 10-12). `tonemap.wgsl` computes the same, step for step.
pub fn tone_map(c: [f32; 3], l_a: f32, settings: &ToneMapSettings) -> [f32; 3] {
    let clean = |v: f32| if v.is_finite() { v.max(0.0) } else { 0.0 };
    let c = c.map(clean);
    let scale = settings.key / l_a.max(f32::MIN_POSITIVE);
    let exposure = settings.exposure_ev.exp2();
    let display = match settings.operator {
        ToneOperator::Reinhard => {
            // L_d / L = scale / (1 + L_s): the colour scaled without dividing by L.
            let ls = scale * luminance(c);
            let factor = scale / (1.0 + ls) * exposure;
            c.map(|v| v * factor)
        }
        ToneOperator::Filmic => c.map(|v| aces(v * scale * exposure)),
        ToneOperator::Clip => c.map(|v| v * scale * exposure),
    };
    let inv_gamma = 1.0 / settings.gamma;
    display.map(|v| clean(v).min(1.0).powf(inv_gamma))
}

/// A whole image to 8-bit RGBA (alpha 255), with its adaptation level: the
/// settings' fixed one, or the image's log-average luminance.
pub fn tone_map_image(radiance: &[[f32; 3]], settings: &ToneMapSettings) -> (Vec<u8>, f32) {
    let l_a = settings
        .adaptation
        .unwrap_or_else(|| log_average_luminance(radiance));
    let mut out = Vec::with_capacity(4 * radiance.len());
    for c in radiance {
        let d = tone_map(*c, l_a, settings);
        out.extend(d.map(|v| (v * 255.0 + 0.5) as u8));
        out.push(255);
    }
    (out, l_a)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn reinhard_is_the_seeds_equations() {
        let s = ToneMapSettings::default();
        // A grey of luminance L_a maps to k / (1 + k), then gamma.
        let d = tone_map([0.5; 3], 0.5, &s);
        let want = (0.18f32 / 1.18).powf(1.0 / 2.2);
        assert!((d[0] - want).abs() < 1e-6, "{d:?} vs {want}");
        // Very bright: towards 1; black: 0.
        assert!(tone_map([1e6; 3], 0.5, &s)[1] > 0.999);
        assert_eq!(tone_map([0.0; 3], 0.5, &s), [0.0; 3]);
        // Exposure multiplies after compression (eq. 12).
        let one_stop = ToneMapSettings {
            exposure_ev: 1.0,
            gamma: 1.0,
            ..s
        };
        let base = ToneMapSettings { gamma: 1.0, ..s };
        let (a, b) = (
            tone_map([0.2; 3], 0.5, &base),
            tone_map([0.2; 3], 0.5, &one_stop),
        );
        assert!((b[0] - 2.0 * a[0]).abs() < 1e-6);
    }

    #[test]
    fn the_log_average_is_the_geometric_mean_and_survives_black() {
        let l = log_average_luminance(&[[1.0; 3], [100.0; 3]]);
        let want = ((1.0f64 + 1e-4) * (100.0 + 1e-4)).sqrt();
        assert!((f64::from(l) / want - 1.0).abs() < 1e-5, "{l}");
        let black = log_average_luminance(&[[0.0; 3]; 4]);
        assert!((black - LOG_AVERAGE_EPSILON).abs() < 1e-9, "{black}");
        assert_eq!(log_average_luminance(&[]), 1.0);
        let nan = log_average_luminance(&[[f32::NAN, f32::INFINITY, -1.0]]);
        assert!(nan.is_finite() && nan > 0.0);
    }

    #[test]
    fn bad_settings_are_named() {
        for (s, needle) in [
            (
                ToneMapSettings {
                    gamma: 0.0,
                    ..Default::default()
                },
                "gamma = 0",
            ),
            (
                ToneMapSettings {
                    key: f32::NAN,
                    ..Default::default()
                },
                "key = NaN",
            ),
            (
                ToneMapSettings {
                    adaptation: Some(-1.0),
                    ..Default::default()
                },
                "adaptation = -1",
            ),
            (
                ToneMapSettings {
                    exposure_ev: 31.0,
                    ..Default::default()
                },
                "exposure_ev = 31",
            ),
        ] {
            let e = s.validate().unwrap_err().to_string();
            assert!(e.contains(needle), "{e}");
        }
        assert!(ToneMapSettings::default().validate().is_ok());
    }

    proptest! {
        /// Any colour (finite or not, negative or not) and any valid settings give
        /// display values in [0, 1], monotone in the radiance's scale.
        #[test]
        fn display_values_are_bounded_and_monotone(
            c in prop::array::uniform3(prop_oneof![
                -1.0f32..1e6, Just(f32::NAN), Just(f32::INFINITY), Just(0.0f32)
            ]),
            l_a in 1e-8f32..1e6,
            key in 0.01f32..1.0,
            ev in -10.0f32..10.0,
            gamma in 0.5f32..4.0,
            op in 0usize..3,
        ) {
            let s = ToneMapSettings {
                operator: ToneOperator::ALL[op],
                key,
                exposure_ev: ev,
                gamma,
                adaptation: None,
            };
            let d = tone_map(c, l_a, &s);
            for v in d {
                prop_assert!(v.is_finite() && (0.0..=1.0).contains(&v), "{d:?}");
            }
            let brighter = tone_map(c.map(|v| v * 2.0), l_a, &s);
            for (a, b) in d.iter().zip(&brighter) {
                prop_assert!(b + 1e-6 >= *a, "{d:?} then {brighter:?}");
            }
        }
    }
}
