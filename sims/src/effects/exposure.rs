//! `exposure`: exposure, saturation and the camera response curve.
//!
//! Model: the linear scene value is scaled by `2^ev`, clipped at 1 (the sensor
//! saturates), and encoded by the camera response curve `response`:
//! `srgb` (IEC 61966-2-1), `gamma` (`x^(1/gamma)`), `linear`, or `s_curve` (gamma
//! `gamma`, then a smoothstep contrast curve blended in by `contrast`, as consumer
//! cameras' tone curves do). Without this effect a frame is exposed at 0 EV and
//! encoded with the sRGB curve (the clean render).
//!
//! Exposure brackets: with `bracket_ev = [-2, 0, 2]` frame `i` is exposed at
//! `ev + bracket_ev[i % 3]`, as a camera that cycles its shutter time frame by frame
//! does. A frame exposed at `ev` had a shutter time of `exposure_time_s × 2^ev` at
//! unit gain; the frame carries it (and a capture records it on `/eo/exposure`), so
//! the images can be turned back into radiance.

use serde::{Deserialize, Serialize};

use super::{EffectParams, ParamDoc, Target, check_range};
use crate::material::linear_to_srgb;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Response {
    Srgb,
    Gamma,
    Linear,
    SCurve,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Exposure {
    pub ev: f64,
    pub response: Response,
    pub gamma: f64,
    pub contrast: f64,
    /// Per-frame offsets (stops) cycled frame by frame; empty: every frame at `ev`.
    pub bracket_ev: Vec<f64>,
    /// Shutter time (s) of a frame exposed at 0 EV.
    pub exposure_time_s: f64,
}

/// Most exposures in one bracket (cameras' auto-bracketing offers 3 to 9).
pub const MAX_BRACKET: usize = 16;

impl Default for Exposure {
    fn default() -> Self {
        Self {
            ev: 0.5,
            response: Response::SCurve,
            gamma: 2.2,
            contrast: 0.3,
            bracket_ev: Vec::new(),
            exposure_time_s: DEFAULT_EXPOSURE_TIME_S,
        }
    }
}

/// Shutter time of a frame at 0 EV: 1/100 s, a daylight handheld exposure.
pub const DEFAULT_EXPOSURE_TIME_S: f64 = 0.01;

impl EffectParams for Exposure {
    const NAME: &'static str = "exposure";
    const TARGET: Target = Target::Eo;
    const MODEL: &'static str = "Linear value × 2^ev, clipped at 1 (saturation), encoded \
        by the response curve: srgb, gamma (x^(1/gamma)), linear, or s_curve (gamma then \
        a smoothstep contrast blend). Brackets: frame i at ev + bracket_ev[i mod n], \
        shutter exposure_time_s × 2^ev, recorded with the frame. Without it: 0 EV and \
        sRGB, no exposure recorded.";
    const PARAMS: &'static [ParamDoc] = &[
        ParamDoc {
            name: "ev",
            unit: "stops",
            what: "exposure relative to the clean render (+1 doubles the light)",
        },
        ParamDoc {
            name: "response",
            unit: "srgb|gamma|linear|s_curve",
            what: "camera response curve",
        },
        ParamDoc {
            name: "gamma",
            unit: "1",
            what: "encoding gamma of the gamma and s_curve responses",
        },
        ParamDoc {
            name: "contrast",
            unit: "1",
            what: "s_curve: blend of the smoothstep contrast curve, 0..1",
        },
        ParamDoc {
            name: "bracket_ev",
            unit: "stops",
            what: "exposure offsets cycled frame by frame (e.g. [-2, 0, 2]); empty: none",
        },
        ParamDoc {
            name: "exposure_time_s",
            unit: "s",
            what: "shutter time of a frame at 0 EV",
        },
    ];

    fn validate(&self) -> Result<(), String> {
        check_range("ev", self.ev, -20.0..=20.0)?;
        check_range("gamma", self.gamma, 0.1..=10.0)?;
        check_range("contrast", self.contrast, 0.0..=1.0)?;
        check_range("exposure_time_s", self.exposure_time_s, 1.0e-6..=1.0)?;
        if self.bracket_ev.len() > MAX_BRACKET {
            return Err(format!(
                "bracket_ev has {} exposures, at most {MAX_BRACKET} are allowed",
                self.bracket_ev.len()
            ));
        }
        for (i, offset) in self.bracket_ev.iter().enumerate() {
            check_range(&format!("bracket_ev[{i}]"), *offset, -10.0..=10.0)?;
            check_range(
                &format!("ev + bracket_ev[{i}]"),
                self.ev + offset,
                -20.0..=20.0,
            )?;
        }
        Ok(())
    }
}

/// The clean render's exposure: 0 EV, sRGB.
pub const CLEAN: Exposure = Exposure {
    ev: 0.0,
    response: Response::Srgb,
    gamma: 2.2,
    contrast: 0.0,
    bracket_ev: Vec::new(),
    exposure_time_s: DEFAULT_EXPOSURE_TIME_S,
};

impl Exposure {
    /// Scale applied to linear values before saturation (at the base `ev`).
    #[inline]
    pub fn gain(&self) -> f32 {
        2f64.powf(self.ev) as f32
    }

    /// The exposure of frame `frame` (stops): `ev` plus its place in the bracket.
    pub fn frame_ev(&self, frame: u64) -> f64 {
        let n = self.bracket_ev.len() as u64;
        let offset = match n {
            0 => 0.0,
            n => self
                .bracket_ev
                .get((frame % n) as usize)
                .copied()
                .unwrap_or(0.0),
        };
        self.ev + offset
    }

    /// Scale applied to frame `frame`'s linear values before saturation.
    pub fn frame_gain(&self, frame: u64) -> f32 {
        2f64.powf(self.frame_ev(frame)) as f32
    }

    /// How frame `frame` was exposed: shutter `exposure_time_s × 2^ev` at unit gain,
    /// so a pixel value is `response(radiance × exposure_time / exposure_time_s)`.
    pub fn frame_exposure(&self, frame: u64) -> texel::EoExposure {
        texel::EoExposure {
            exposure_time_s: self.exposure_time_s * 2f64.powf(self.frame_ev(frame)),
            gain: 1.0,
        }
    }

    /// Encodes a linear value already scaled and clipped to [0, 1] into [0, 1].
    #[inline]
    pub fn encode(&self, x: f32) -> f32 {
        let x = if x.is_finite() {
            x.clamp(0.0, 1.0)
        } else {
            0.0
        };
        match self.response {
            Response::Srgb => linear_to_srgb(x),
            Response::Linear => x,
            Response::Gamma => x.powf(1.0 / self.gamma as f32),
            Response::SCurve => {
                let g = x.powf(1.0 / self.gamma as f32);
                let s = g * g * (3.0 - 2.0 * g);
                g + (s - g) * self.contrast as f32
            }
        }
    }

    /// The camera's true response as Debevec & Malik's inverse log response
    /// (`texel::radiance::EoResponse`), the same for every channel: for each 8-bit
    /// value, the log of the exposure (radiance × shutter time) at the middle of the
    /// linear interval the curve maps to it (value 255: the interval's start, the
    /// least exposure that saturates), so radiance comes out in the simulator's units
    /// (1.0 is white at 0 EV). Values the curve skips take the log-linear
    /// interpolation of their neighbours. What a recovered curve is compared with.
    pub fn true_response(
        &self,
    ) -> Result<texel::radiance::EoResponse, texel::radiance::ResponseError> {
        let lut = self.lut();
        let mut low = [f64::INFINITY; 256];
        let mut high = [f64::NEG_INFINITY; 256];
        for (i, &z) in lut.iter().enumerate() {
            let x = i as f64 / (LUT_SIZE - 1) as f64;
            let z = usize::from(z);
            low[z] = low[z].min(x);
            high[z] = high[z].max(x);
        }
        let log_time = self.exposure_time_s.ln();
        let mut known: Vec<Option<f64>> = (0..256)
            .map(|z| {
                let x = if z == 255 {
                    low[z]
                } else {
                    0.5 * (low[z] + high[z])
                };
                (x.is_finite() && x > 0.0).then(|| x.ln() + log_time)
            })
            .collect();
        fill_gaps(&mut known);
        let curve: Vec<f64> = known.into_iter().map(|g| g.unwrap_or(log_time)).collect();
        texel::radiance::EoResponse::new([curve.clone(), curve.clone(), curve])
    }

    /// A [`LUT_SIZE`]-entry table from clipped linear values to 8-bit codes.
    pub fn lut(&self) -> Vec<u8> {
        (0..LUT_SIZE)
            .map(|i| {
                let x = i as f32 / (LUT_SIZE - 1) as f32;
                (self.encode(x) * 255.0 + 0.5).clamp(0.0, 255.0) as u8
            })
            .collect()
    }
}

/// Values without a log take the linear interpolation of the nearest known ones on
/// either side (the nearest one alone at the ends).
fn fill_gaps(values: &mut [Option<f64>]) {
    let known: Vec<(usize, f64)> = values
        .iter()
        .enumerate()
        .filter_map(|(i, v)| v.map(|v| (i, v)))
        .collect();
    for (i, v) in values.iter_mut().enumerate() {
        if v.is_some() {
            continue;
        }
        let before = known.iter().rev().find(|(k, _)| *k < i);
        let after = known.iter().find(|(k, _)| *k > i);
        *v = match (before, after) {
            (Some(&(a, va)), Some(&(b, vb))) => {
                Some(va + (vb - va) * (i - a) as f64 / (b - a) as f64)
            }
            (Some(&(_, va)), None) => Some(va),
            (None, Some(&(_, vb))) => Some(vb),
            (None, None) => None,
        };
    }
}

/// Entries of [`Exposure::lut`].
pub const LUT_SIZE: usize = 16384;

/// Looks a linear value in [0, 1] up in a table from [`Exposure::lut`].
#[inline]
pub fn lut_lookup(lut: &[u8], x: f32) -> u8 {
    let x = if x.is_finite() {
        x.clamp(0.0, 1.0)
    } else {
        0.0
    };
    // In [0.5, LUT_SIZE - 0.5] here: through i32, one conversion instruction (a
    // float-to-usize cast saturates, which costs several).
    let i = (x * (LUT_SIZE - 1) as f32 + 0.5) as i32 as usize;
    lut.get(i.min(LUT_SIZE - 1)).copied().unwrap_or(0)
}
