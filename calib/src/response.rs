//! The EO camera's response curve from exposure brackets (Debevec & Malik 1997, the
//! recovery Lechelek et al. 2019 §3 build their HDR textures on): the inverse log
//! response `g(z) = ln E + ln Δt` of each 8-bit value `z`, recovered per channel from
//! pixels seen at several known exposure times, and the merge of one pixel's bracket
//! into its log radiance.
//!
//! The recipe ([`recover_response`]):
//! 1. **Check the bracket**: at least two distinct, finite, positive exposure times,
//!    and samples that hold information (a value neither black nor saturated).
//! 2. **The linear system** (the paper's §2.1, eq. 3): one row per sample and exposure
//!    `w(z) [g(z) - ln E_i] = w(z) ln Δt_j`, the hat weighting `w` (zero at 0 and 255);
//!    `λ w(z) g''(z) = 0` for z in 1..=254 (smoothness); `g(128) = 0` (the scale).
//! 3. **Least squares** by SVD, so values no sample reached take the curve the
//!    smoothness term draws through them.
//!
//! Pure and I/O-free; a bad bracket is an error naming what is wrong.

use nalgebra::{DMatrix, DVector};
use thiserror::Error;

/// The values of an 8-bit channel.
pub const LEVELS: usize = 256;

/// The value whose `g` is fixed at 0 (the middle of the range, as in the paper).
const MIDDLE: usize = 128;

/// At most this many samples: the system has one unknown per sample, and the paper's
/// rule (N (P - 1) > 255) needs about 50 for a bracket of a few exposures.
pub const MAX_SAMPLES: usize = 1024;

/// At most this many exposures: brackets have a handful, and the system's rows grow
/// with samples times exposures.
pub const MAX_EXPOSURES: usize = 32;

/// Why a bracket gives no response curve.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ResponseError {
    #[error("exposure time {index} is {value} s: exposure times must be finite and positive")]
    BadExposureTime { index: usize, value: f64 },
    #[error(
        "the bracket has {distinct} distinct exposure time(s): recovering a response needs at least 2"
    )]
    TooFewExposures { distinct: usize },
    #[error("sample {sample} has {got} values for {expected} exposures")]
    RaggedSample {
        sample: usize,
        got: usize,
        expected: usize,
    },
    #[error("{images} images for {times} exposure times")]
    ImageCount { images: usize, times: usize },
    #[error(
        "image {image} is {got} bytes, the first is {expected} (and RGB needs a multiple of 3)"
    )]
    ImageSize {
        image: usize,
        got: usize,
        expected: usize,
    },
    #[error("{0} exposures, more than the {MAX_EXPOSURES} a recovery takes")]
    TooManyExposures(usize),
    #[error("{0} samples, more than the {MAX_SAMPLES} a recovery takes")]
    TooManySamples(usize),
    #[error(
        "no sample holds information: every value is black (0) or saturated (255), which the hat weighting ignores"
    )]
    NoInformation,
    #[error("smoothness lambda must be finite and positive, got {0}")]
    BadSmoothness(f64),
    #[error("the least-squares solve failed: {0}")]
    Solve(&'static str),
}

/// A recovered response: `g(z)` for every 8-bit value, in natural log units of
/// exposure (radiance times seconds), with `g(128) = 0`.
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseCurve {
    pub log_exposure: Vec<f64>,
}

pub use texel::radiance::hat_weight;

/// The three channels' curves as the sensor model carries them (the sensor file's
/// `[eo_response]`), checked as every curve a sensor file holds is.
pub fn to_eo_response(
    curves: &[ResponseCurve; 3],
) -> Result<texel::radiance::EoResponse, texel::radiance::ResponseError> {
    texel::radiance::EoResponse::new(curves.clone().map(|c| c.log_exposure))
}

/// Recovers `g` for one channel from `samples` (each the values of one pixel at every
/// exposure, in the order of `exposure_times_s`), with smoothness `lambda` (the
/// paper's λ; tens to a hundred for 8-bit data).
pub fn recover_response(
    samples: &[Vec<u8>],
    exposure_times_s: &[f64],
    lambda: f64,
) -> Result<ResponseCurve, ResponseError> {
    // 1. The bracket.
    let log_times = check_bracket(samples, exposure_times_s, lambda)?;
    // 2. The linear system, eq. 3 of the paper.
    let (a, b) = linear_system(samples, &log_times, lambda);
    // 3. Least squares.
    let x = least_squares(a, &b)?;
    let log_exposure: Vec<f64> = (0..LEVELS).map(|z| x[z]).collect();
    if log_exposure.iter().any(|g| !g.is_finite()) {
        return Err(ResponseError::Solve("a non-finite curve"));
    }
    Ok(ResponseCurve { log_exposure })
}

/// The least-squares solution of `a x = b`: by Householder QR (`R x = Qᵀ b`), which
/// keeps the accuracy of the system's own conditioning; by SVD only where R is
/// singular (a sample that no weighted value reaches leaves its radiance free).
/// (nalgebra's SVD alone was measured to miss the optimum on a 1255 x 456 system of a
/// simulated bracket: a residual of 85.8 where QR and the normal equations reach
/// 80.3, with the whole curve shifted 30 log units off its `g(128) = 0`.)
fn least_squares(a: DMatrix<f64>, b: &DVector<f64>) -> Result<DVector<f64>, ResponseError> {
    let qr = a.clone().qr();
    let qtb = qr.q().transpose() * b;
    let r = qr.r();
    let regular = r.diagonal().iter().all(|d| d.abs() > 1e-9);
    if regular && let Some(x) = r.solve_upper_triangular(&qtb) {
        return Ok(x);
    }
    a.svd(true, true)
        .solve(b, 1e-10)
        .map_err(ResponseError::Solve)
}

/// The three channels' curves from a bracket of aligned RGB images (interleaved
/// 8-bit, one per exposure time, all the same size, the camera still): `samples`
/// pixels chosen so their values in the middle exposure spread over the range (the
/// paper picks pixels "with a reasonably even distribution of values"), then
/// [`recover_response`] per channel.
pub fn recover_rgb_response(
    images: &[&[u8]],
    exposure_times_s: &[f64],
    samples: usize,
    lambda: f64,
) -> Result<[ResponseCurve; 3], ResponseError> {
    if images.len() != exposure_times_s.len() {
        return Err(ResponseError::ImageCount {
            images: images.len(),
            times: exposure_times_s.len(),
        });
    }
    let pixels = chosen_pixels(images, exposure_times_s, samples.min(MAX_SAMPLES))?;
    let channel = |c: usize| -> Result<ResponseCurve, ResponseError> {
        let values: Vec<Vec<u8>> = pixels
            .iter()
            .map(|&p| images.iter().map(|img| img[3 * p + c]).collect())
            .collect();
        recover_response(&values, exposure_times_s, lambda)
    };
    Ok([channel(0)?, channel(1)?, channel(2)?])
}

/// Pixel indices whose green value in the middle exposure falls in `samples` bins
/// spread over 0..=255, the first pixel of each bin in raster order (deterministic);
/// bins no pixel falls in are skipped.
fn chosen_pixels(
    images: &[&[u8]],
    exposure_times_s: &[f64],
    samples: usize,
) -> Result<Vec<usize>, ResponseError> {
    let len = images.first().map_or(0, |i| i.len());
    for (index, img) in images.iter().enumerate() {
        if img.len() != len || !img.len().is_multiple_of(3) {
            return Err(ResponseError::ImageSize {
                image: index,
                got: img.len(),
                expected: len,
            });
        }
    }
    // The middle exposure by time (the one most pixels are best exposed in).
    let mut order: Vec<usize> = (0..exposure_times_s.len()).collect();
    order.sort_by(|&a, &b| exposure_times_s[a].total_cmp(&exposure_times_s[b]));
    let Some(&middle) = order.get(order.len() / 2) else {
        return Err(ResponseError::TooFewExposures { distinct: 0 });
    };
    let bins = samples.max(1);
    let mut chosen: Vec<Option<usize>> = vec![None; bins];
    for p in 0..len / 3 {
        let g = usize::from(images[middle][3 * p + 1]);
        let bin = (g * bins / LEVELS).min(bins - 1);
        chosen[bin].get_or_insert(p);
    }
    Ok(chosen.into_iter().flatten().collect())
}

impl ResponseCurve {
    /// One pixel's log exposure per unit time (its log radiance, up to the curve's
    /// scale) from its values in a bracket (eq. 6): the hat-weighted mean of
    /// `g(z_j) - ln Δt_j`. `None` when every value is black or saturated (no weight:
    /// the pixel's radiance is only bounded, and no log of zero is taken).
    pub fn log_radiance(&self, values: &[u8], exposure_times_s: &[f64]) -> Option<f64> {
        let mut sum = 0.0;
        let mut weight = 0.0;
        for (&z, &t) in values.iter().zip(exposure_times_s) {
            let w = hat_weight(z);
            // Guard: a non-positive or non-finite time has no log.
            if w <= 0.0 || !(t.is_finite() && t > 0.0) {
                continue;
            }
            sum += w * (self.log_exposure[usize::from(z)] - t.ln());
            weight += w;
        }
        (weight > 0.0).then(|| sum / weight)
    }
}

/// The log exposure times of a usable bracket, or what is wrong with it.
fn check_bracket(
    samples: &[Vec<u8>],
    exposure_times_s: &[f64],
    lambda: f64,
) -> Result<Vec<f64>, ResponseError> {
    if !(lambda.is_finite() && lambda > 0.0) {
        return Err(ResponseError::BadSmoothness(lambda));
    }
    if exposure_times_s.len() > MAX_EXPOSURES {
        return Err(ResponseError::TooManyExposures(exposure_times_s.len()));
    }
    for (index, &value) in exposure_times_s.iter().enumerate() {
        if !(value.is_finite() && value > 0.0) {
            return Err(ResponseError::BadExposureTime { index, value });
        }
    }
    let mut distinct: Vec<f64> = exposure_times_s.to_vec();
    distinct.sort_by(f64::total_cmp);
    distinct.dedup_by(|a, b| (*a / *b - 1.0).abs() < 1e-9);
    if distinct.len() < 2 {
        return Err(ResponseError::TooFewExposures {
            distinct: distinct.len(),
        });
    }
    if samples.len() > MAX_SAMPLES {
        return Err(ResponseError::TooManySamples(samples.len()));
    }
    for (sample, values) in samples.iter().enumerate() {
        if values.len() != exposure_times_s.len() {
            return Err(ResponseError::RaggedSample {
                sample,
                got: values.len(),
                expected: exposure_times_s.len(),
            });
        }
    }
    // A sample informs the curve only where two of its exposures carry weight: one
    // weighted value alone just sets that sample's own radiance.
    let informative = samples
        .iter()
        .any(|values| values.iter().filter(|&&z| hat_weight(z) > 0.0).count() >= 2);
    if !informative {
        return Err(ResponseError::NoInformation);
    }
    Ok(exposure_times_s.iter().map(|t| t.ln()).collect())
}

/// The paper's system: unknowns `g(0..=255)` then one `ln E` per sample.
fn linear_system(
    samples: &[Vec<u8>],
    log_times: &[f64],
    lambda: f64,
) -> (DMatrix<f64>, DVector<f64>) {
    let n = samples.len();
    let rows = n * log_times.len() + 1 + (LEVELS - 2);
    let mut a = DMatrix::<f64>::zeros(rows, LEVELS + n);
    let mut b = DVector::<f64>::zeros(rows);
    let mut k = 0;
    // The data: w(z) (g(z) - ln E_i) = w(z) ln Δt_j.
    for (i, values) in samples.iter().enumerate() {
        for (&z, &log_t) in values.iter().zip(log_times) {
            let w = hat_weight(z);
            a[(k, usize::from(z))] = w;
            a[(k, LEVELS + i)] = -w;
            b[k] = w * log_t;
            k += 1;
        }
    }
    // The scale: g(128) = 0.
    a[(k, MIDDLE)] = 1.0;
    k += 1;
    // Smoothness: λ w(z) (g(z - 1) - 2 g(z) + g(z + 1)) = 0.
    for z in 1..LEVELS - 1 {
        let w = lambda * hat_weight(z as u8);
        a[(k, z - 1)] = w;
        a[(k, z)] = -2.0 * w;
        a[(k, z + 1)] = w;
        k += 1;
    }
    (a, b)
}

#[cfg(test)]
mod tests;
