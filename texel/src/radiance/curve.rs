//! The EO camera's response curve as Debevec & Malik's inverse log response: for each
//! channel and 8-bit value `z`, `g(z) = ln(E · Δt · gain)`, the log of the exposure
//! that produces it. Recovered by `texel-calib response`, carried by the sensor file
//! and `/texel/sensor`; [`EoResponse::srgb`] stands in for cameras without one.

use serde::{Deserialize, Serialize};

/// The values of an 8-bit channel.
pub const LEVELS: usize = 256;

/// Why numbers are not a response curve.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ResponseError {
    #[error("eo_response.{channel} has {got} values, a curve has one per 8-bit value ({LEVELS})")]
    Length { channel: &'static str, got: usize },
    #[error("eo_response.{channel}[{z}] is {value}: a curve's values are finite")]
    NotFinite {
        channel: &'static str,
        z: usize,
        value: f64,
    },
    #[error(
        "eo_response.{channel} falls from {from} at {z} to {to} at {next}: a response \
         curve never decreases"
    )]
    Decreasing {
        channel: &'static str,
        z: usize,
        from: f64,
        next: usize,
        to: f64,
    },
}

/// The inverse log response of the three channels (red, green, blue).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "ResponseFile", into = "ResponseFile")]
pub struct EoResponse {
    log_exposure: [Vec<f64>; 3],
}

/// The layout in sensor files and `/texel/sensor`: `r`, `g`, `b`, each 256 values of
/// `ln(exposure)`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ResponseFile {
    r: Vec<f64>,
    g: Vec<f64>,
    b: Vec<f64>,
}

const CHANNELS: [&str; 3] = ["r", "g", "b"];

/// A recovered curve may dip by this much between neighbouring values (least squares
/// with a finite smoothness weight); a larger fall is not a response.
const MONOTONE_TOLERANCE: f64 = 0.25;

impl EoResponse {
    /// A curve from `ln(exposure)` per value and channel: 256 finite values each, never
    /// falling by more than a least-squares wobble.
    pub fn new(log_exposure: [Vec<f64>; 3]) -> Result<Self, ResponseError> {
        for (curve, channel) in log_exposure.iter().zip(CHANNELS) {
            if curve.len() != LEVELS {
                return Err(ResponseError::Length {
                    channel,
                    got: curve.len(),
                });
            }
            if let Some((z, &value)) = curve.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(ResponseError::NotFinite { channel, z, value });
            }
            for z in 0..LEVELS - 1 {
                let (from, to) = (curve[z], curve[z + 1]);
                if to < from - MONOTONE_TOLERANCE {
                    return Err(ResponseError::Decreasing {
                        channel,
                        z,
                        from,
                        next: z + 1,
                        to,
                    });
                }
            }
        }
        Ok(Self { log_exposure })
    }

    /// A curve from a function mapping a value's position in `[0, 1]` (`z / 255`) to
    /// the linear exposure that produces it, the same for every channel. Values whose
    /// exposure is not a positive finite number take their neighbour's log (no log of
    /// zero): value 0 takes value 1's.
    pub fn from_linear(linear_of: impl Fn(f64) -> f64) -> Self {
        let mut curve = vec![0.0f64; LEVELS];
        let mut last: Option<f64> = None;
        for (z, g) in curve.iter_mut().enumerate() {
            let x = linear_of(z as f64 / (LEVELS - 1) as f64);
            let log = (x.is_finite() && x > 0.0).then(|| x.ln());
            *g = match (log, last) {
                (Some(l), Some(prev)) => l.max(prev),
                (Some(l), None) => l,
                (None, prev) => prev.unwrap_or(f64::NAN),
            };
            if g.is_finite() {
                last = Some(*g);
            }
        }
        // Leading values without a log take the first one that has it.
        let first = curve.iter().copied().find(|g| g.is_finite()).unwrap_or(0.0);
        for g in curve.iter_mut() {
            if !g.is_finite() {
                *g = first;
            }
        }
        Self {
            log_exposure: [curve.clone(), curve.clone(), curve],
        }
    }

    /// The sRGB curve (IEC 61966-2-1), the nominal response of a camera that reports
    /// none: value 1 is the darkest value with a log, and value 0 takes it too.
    pub fn srgb() -> Self {
        Self::from_linear(|v| {
            if v <= 0.04045 {
                v / 12.92
            } else {
                ((v + 0.055) / 1.055).powf(2.4)
            }
        })
    }

    /// `g(z)` of `channel` (0 red, 1 green, 2 blue; others read as blue).
    #[inline]
    pub fn log_exposure(&self, channel: usize, z: u8) -> f64 {
        self.log_exposure[channel.min(2)]
            .get(usize::from(z))
            .copied()
            .unwrap_or(0.0)
    }

    /// The three curves, red, green, blue.
    pub fn curves(&self) -> &[Vec<f64>; 3] {
        &self.log_exposure
    }
}

impl TryFrom<ResponseFile> for EoResponse {
    type Error = ResponseError;
    fn try_from(file: ResponseFile) -> Result<Self, Self::Error> {
        Self::new([file.r, file.g, file.b])
    }
}

impl From<EoResponse> for ResponseFile {
    fn from(response: EoResponse) -> Self {
        let [r, g, b] = response.log_exposure;
        Self { r, g, b }
    }
}
