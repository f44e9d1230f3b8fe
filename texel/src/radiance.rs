//! Radiance from exposed EO frames: the camera's response curve (Debevec & Malik 1997:
//! the inverse log response `g(z) = ln(E · Δt · gain)` of each 8-bit value, per
//! channel), the paper's hat weighting, and the merge of one or more exposures of the
//! same view into linear radiance (eq. 6), which Lechelek et al. 2019 (§3) texture
//! their models with. Pure and I/O-free; every log, exp and division guards its
//! degenerate case, so radiance is finite and non-negative for any input.

mod curve;
pub mod exr;
#[cfg(test)]
mod tests;

pub use curve::{EoResponse, LEVELS, ResponseError};

use crate::frames::EoFrame;

/// At most this many exposures are merged at once (brackets have a handful).
pub const MAX_MERGED_EXPOSURES: usize = 32;

/// The hat weighting of the paper's eq. 4: 0 at black and at saturation, where a
/// value only bounds the radiance, largest in the middle of the range.
#[inline]
pub fn hat_weight(z: u8) -> f64 {
    f64::from(z.min(255 - z))
}

/// Linear radiance per pixel and channel, in the units of the response curve
/// (`exp(g(z)) / (exposure_time_s · gain)`), with the hat weight that went into each
/// value: 0 where every exposure was black or saturated (the value is then a bound:
/// 0 for black, the least radiance that saturates the shortest exposure for
/// saturated).
#[derive(Debug, Clone, PartialEq)]
pub struct RadianceImage {
    pub width: u32,
    pub height: u32,
    /// Row-major, row 0 at the top, `[r, g, b]`.
    pub rgb: Vec<[f32; 3]>,
    /// Summed hat weight per pixel and channel (0..=127 per exposure).
    pub weight: Vec<[f32; 3]>,
}

impl RadianceImage {
    /// Share of channel values no exposure measured (weight 0), in 0..=1.
    pub fn unmeasured_share(&self) -> f64 {
        let total = 3 * self.weight.len();
        if total == 0 {
            return 0.0;
        }
        let unmeasured = self
            .weight
            .iter()
            .flat_map(|w| w.iter())
            .filter(|&&w| w <= 0.0)
            .count();
        unmeasured as f64 / total as f64
    }
}

/// Why exposures cannot be merged.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MergeError {
    #[error("no exposure to merge")]
    Empty,
    #[error("{count} exposures: at most {MAX_MERGED_EXPOSURES} are merged at once")]
    TooMany { count: usize },
    #[error(
        "EO frame {index} (at {timestamp_ns} ns) says nothing of its exposure: its pixels \
         are colours, not measurements of radiance"
    )]
    MissingExposure { index: usize, timestamp_ns: u64 },
    #[error("EO frame {index} (at {timestamp_ns} ns): {message}")]
    BadExposure {
        index: usize,
        timestamp_ns: u64,
        message: String,
    },
    #[error("EO frame {index} is {got_width}x{got_height}, the first is {width}x{height}")]
    Size {
        index: usize,
        width: u32,
        height: u32,
        got_width: u32,
        got_height: u32,
    },
    #[error("EO frame {index} has {bytes} bytes for its {width}x{height} RGB pixels")]
    Inconsistent {
        index: usize,
        width: u32,
        height: u32,
        bytes: usize,
    },
}

/// Merges exposures of one view (aligned frames, each with its exposure) into linear
/// radiance, per pixel and channel (Debevec & Malik 1997):
///
/// 1. **Check the frames**: each says how it was exposed, all the same size.
/// 2. **Log exposure scale** per frame: `ln(exposure_time_s · gain)`.
/// 3. **Weighted mean** (eq. 6): `ln E = Σ w(z_j) (g(z_j) - ln s_j) / Σ w(z_j)`, the
///    hat weight `w` zero at black and saturation, so no log of zero is taken.
/// 4. **Unmeasured values**: every exposure saturated gives the least radiance that
///    saturates the shortest of them (a lower bound); every exposure black gives 0.
///
/// A single exposure is a bracket of one: its radiance where it measured any, its
/// bounds elsewhere.
pub fn merge_exposures(
    frames: &[&EoFrame],
    response: &EoResponse,
) -> Result<RadianceImage, MergeError> {
    // 1. The frames.
    let (width, height) = check_frames(frames)?;
    // 2. ln(exposure time × gain) of each frame (finite: validated positive).
    let log_scales: Vec<f64> = frames
        .iter()
        .filter_map(|f| f.exposure.map(|e| e.scale().ln()))
        .collect();
    let pixels = width as usize * height as usize;
    let mut rgb = vec![[0.0f32; 3]; pixels];
    let mut weight = vec![[0.0f32; 3]; pixels];
    if let [frame] = frames {
        // One exposure: each channel value's radiance is one of 256, computed once by
        // the same rule (the scan's texture made radiance at table-lookup cost).
        let table: Vec<[(f32, f64); LEVELS]> = (0..3)
            .map(|c| {
                std::array::from_fn(|z| {
                    merge_value(std::iter::once(z as u8), &log_scales, response, c)
                })
            })
            .collect();
        for ((out, out_w), px) in rgb
            .iter_mut()
            .zip(weight.iter_mut())
            .zip(frame.rgb.chunks_exact(3))
        {
            for (c, t) in table.iter().enumerate() {
                let (value, w) = t[usize::from(px[c])];
                out[c] = value;
                out_w[c] = w as f32;
            }
        }
        return Ok(RadianceImage {
            width,
            height,
            rgb,
            weight,
        });
    }
    for (p, (out, out_w)) in rgb.iter_mut().zip(weight.iter_mut()).enumerate() {
        for c in 0..3 {
            let values = frames
                .iter()
                .map(|f| f.rgb.get(3 * p + c).copied().unwrap_or(0));
            let (value, w) = merge_value(values, &log_scales, response, c);
            out[c] = value;
            out_w[c] = w as f32;
        }
    }
    Ok(RadianceImage {
        width,
        height,
        rgb,
        weight,
    })
}

/// One channel value's radiance from its exposures (steps 3 and 4), and its weight.
fn merge_value(
    values: impl Iterator<Item = u8>,
    log_scales: &[f64],
    response: &EoResponse,
    channel: usize,
) -> (f32, f64) {
    let mut sum = 0.0;
    let mut sum_w = 0.0;
    // The smallest log scale among exposures that saturated: the brightest bound.
    let mut saturated_log_scale: Option<f64> = None;
    for (z, &log_scale) in values.zip(log_scales) {
        let w = hat_weight(z);
        if w > 0.0 {
            sum += w * (response.log_exposure(channel, z) - log_scale);
            sum_w += w;
        } else if z == 255 {
            saturated_log_scale =
                Some(saturated_log_scale.map_or(log_scale, |s: f64| s.min(log_scale)));
        }
    }
    let log_radiance = if sum_w > 0.0 {
        sum / sum_w
    } else if let Some(log_scale) = saturated_log_scale {
        response.log_exposure(channel, 255) - log_scale
    } else {
        // Black in every exposure: below what the longest one resolves.
        return (0.0, 0.0);
    };
    (radiance_of_log(log_radiance), sum_w)
}

/// `exp`, kept within f32 (a curve's values and validated exposures keep the argument
/// finite; the clamp keeps the result so even for extreme ones).
#[inline]
fn radiance_of_log(log_radiance: f64) -> f32 {
    let e = log_radiance.clamp(-700.0, 700.0).exp();
    (e.min(f64::from(f32::MAX)) as f32).max(0.0)
}

/// The frames' common size, or what is wrong with them.
fn check_frames(frames: &[&EoFrame]) -> Result<(u32, u32), MergeError> {
    let first = frames.first().ok_or(MergeError::Empty)?;
    if frames.len() > MAX_MERGED_EXPOSURES {
        return Err(MergeError::TooMany {
            count: frames.len(),
        });
    }
    let (width, height) = (first.width, first.height);
    for (index, f) in frames.iter().enumerate() {
        let Some(exposure) = f.exposure else {
            return Err(MergeError::MissingExposure {
                index,
                timestamp_ns: f.timestamp_ns,
            });
        };
        exposure
            .validate()
            .map_err(|message| MergeError::BadExposure {
                index,
                timestamp_ns: f.timestamp_ns,
                message,
            })?;
        if (f.width, f.height) != (width, height) {
            return Err(MergeError::Size {
                index,
                width,
                height,
                got_width: f.width,
                got_height: f.height,
            });
        }
        if !f.is_consistent() {
            return Err(MergeError::Inconsistent {
                index,
                width: f.width,
                height: f.height,
                bytes: f.rgb.len(),
            });
        }
    }
    Ok((width, height))
}
