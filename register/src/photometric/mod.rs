//! The direct photometric term: where the geometry leaves a direction of motion weak
//! (a corridor's axis, a wall's plane), the EO image pins it. Each lidar point the
//! geometry paired is projected into the target scan's EO image (through the EO
//! camera's distortion) and its luminance there compared with the luminance the
//! source scan saw at it, after an affine brightness compensation between the two
//! frames (exposure and gain changes). As in FAST-LIVO2 (Zheng et al. 2024) the
//! residuals live on image pixels attached to lidar points; as in COIN-LIO (Pfreundschuh
//! et al. 2024) and selective-update schemes they are admitted only where the
//! geometry is weak, weighted by their own noise, not a global weight
//! (docs/registration.md, "The photometric term").

pub mod ambiguity;
pub mod config;
pub mod eo_pyramid;

use nalgebra::{Matrix3, Vector3};

pub use config::{PhotometricConfig, PhotometricMode};
pub use eo_pyramid::{EoProjection, EoPyramid, EoSample};

/// Gains outside this range are not an exposure change but a mismatch.
const MIN_GAIN: f64 = 0.5;
const MAX_GAIN: f64 = 2.0;
/// Spreads (MAD) below this do not determine a gain: keep gain 1.
const MIN_SPREAD: f64 = 1.0e-3;

/// `I_target ≈ gain · I_source + bias` between two frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Brightness {
    pub gain: f64,
    pub bias: f64,
}

impl Default for Brightness {
    fn default() -> Self {
        Self {
            gain: 1.0,
            bias: 0.0,
        }
    }
}

/// Fits the brightness change by matching the pairs' medians and spreads (MAD) of
/// the two frames' intensities. Moment matching, not regression: a regression of one
/// on the other shrinks the gain towards 0 while the pose is still off (regression
/// dilution), matching the distributions does not. Degenerate cases (no pairs, no
/// spread) keep gain 1; the gain is clamped to a plausible exposure change.
pub fn fit_brightness(source: &mut [f64], target: &mut [f64]) -> Brightness {
    let (Some((ms, ss)), Some((mt, st))) = (median_and_mad(source), median_and_mad(target)) else {
        return Brightness::default();
    };
    let gain = if ss > MIN_SPREAD && st > MIN_SPREAD {
        (st / ss).clamp(MIN_GAIN, MAX_GAIN)
    } else {
        1.0
    };
    let bias = mt - gain * ms;
    if gain.is_finite() && bias.is_finite() {
        Brightness { gain, bias }
    } else {
        Brightness::default()
    }
}

fn median_of(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, f64::total_cmp);
    Some(*m)
}

fn median_and_mad(values: &mut [f64]) -> Option<(f64, f64)> {
    let median = median_of(values)?;
    let mut deviations: Vec<f64> = values.iter().map(|v| (v - median).abs()).collect();
    let mad = median_of(&mut deviations)?;
    Some((median, mad))
}

/// One photometric observation of a paired source point in a target's EO image.
#[derive(Debug, Clone, Copy)]
pub struct Observation {
    pub target: u8,
    pub source_intensity: f64,
    pub target_intensity: f64,
    /// Jacobian row of the target intensity with respect to a right perturbation
    /// `(ω, v)` of the source pose: `[p × m, m]` with `m = Rᵀ Jπᵀ ∇I`.
    pub jacobian: [f64; 6],
}

/// Observes source point `p_source` (source scan frame) in a target's EO image at
/// `level`, the point moved into the target frame by `rotation`, `translation`
/// (`target_from_source`). `None` where it does not project onto valid pixels, or
/// where the image gradient is below `min_gradient` per level pixel: there the
/// gradient is the sensor's noise, not the scene's texture, and would claim
/// information about the motion that the image does not hold.
#[inline]
#[allow(clippy::too_many_arguments)]
pub fn observe(
    target_eo: &EoPyramid,
    level: usize,
    min_gradient: f64,
    target: u8,
    p_source: &Vector3<f64>,
    source_intensity: f64,
    rotation: &Matrix3<f64>,
    translation: &Vector3<f64>,
) -> Option<Observation> {
    let q = rotation * p_source + translation;
    let projection = target_eo.project(&q)?;
    let sample = target_eo.sample(level, &projection.pixel)?;
    // `sample.gradient` is per full-resolution pixel; per level pixel it is `scale`
    // times that.
    let level_scale = f64::from(1u32 << level.min(16));
    if !(sample.gradient.norm() * level_scale >= min_gradient) {
        return None;
    }
    // dI/dq = ∇Iᵀ Jπ (a row), carried back to the source frame.
    let g = projection.jacobian.transpose() * sample.gradient;
    let m = rotation.tr_mul(&g);
    let c = p_source.cross(&m);
    Some(Observation {
        target,
        source_intensity,
        target_intensity: sample.intensity,
        jacobian: [c.x, c.y, c.z, m.x, m.y, m.z],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn brightness_recovers_an_exposure_change() {
        let mut source: Vec<f64> = (0..200).map(|i| 0.2 + 0.003 * f64::from(i % 97)).collect();
        let mut target: Vec<f64> = source.iter().map(|s| 1.3 * s + 0.05).collect();
        let b = fit_brightness(&mut source, &mut target);
        assert!((b.gain - 1.3).abs() < 1e-9, "{b:?}");
        assert!((b.bias - 0.05).abs() < 1e-9, "{b:?}");
    }

    #[test]
    fn brightness_without_spread_or_pairs_keeps_gain_one() {
        let mut flat = vec![0.4; 10];
        let mut other = vec![0.5; 10];
        let b = fit_brightness(&mut flat, &mut other);
        assert_eq!(b.gain, 1.0);
        assert!((b.bias - 0.1).abs() < 1e-12);
        assert_eq!(fit_brightness(&mut [], &mut []), Brightness::default());
        // A wild ratio is clamped, never infinite.
        let mut a: Vec<f64> = (0..50).map(|i| 0.5 + 0.01 * f64::from(i % 3)).collect();
        let mut b: Vec<f64> = (0..50).map(|i| 0.5 * f64::from(i % 2)).collect();
        let fit = fit_brightness(&mut a, &mut b);
        assert!(fit.gain <= MAX_GAIN && fit.gain.is_finite());
    }
}
