//! Settings of the photometric term (defaults in code; `[align.photometric]` in TOML
//! overrides them, unknown keys are errors).

use serde::{Deserialize, Serialize};

use crate::config::{Check, ConfigError, first_failed};

/// Where the photometric term constrains the pose.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PhotometricMode {
    /// Geometry only.
    Off,
    /// Only in the directions the geometry leaves weak (eigenvalue ratio below
    /// `weak_ratio`), and only while it does: camera terms where and when the lidar
    /// is degenerate.
    Selective,
    /// In every direction, at every alignment (lidar and EO fused throughout).
    Full,
}

/// The direct photometric term on the EO image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PhotometricConfig {
    pub mode: PhotometricMode,
    /// Least standard deviation of a photometric residual (band-pass log
    /// luminance): what the images' own measured noise does not cover (resampling,
    /// the brightness model). A residual's sigma is the larger of this and the two
    /// images' noise at the level, which with the range noise puts both terms in
    /// units of their own information.
    pub intensity_sigma: f64,
    /// A direction whose geometric eigenvalue, over the largest, is below this is
    /// weak: the selective mode adds the photometric information there.
    pub weak_ratio: f64,
    /// Levels of the EO luminance pyramid (each half the resolution of the one
    /// below): the coarse ones widen the basin of convergence, the alignment's
    /// coarsest level reads the coarsest of them.
    pub eo_levels: u32,
    /// The EO level the alignment's finest level reads (0: full resolution). The
    /// default, half resolution, is still twice as fine as the default lidar and
    /// has a quarter of the noise in its gradients.
    pub finest_eo_level: u32,
    /// Pixels whose gradient (band-pass log luminance per level pixel) is below this
    /// many times the image's noise at the level, or below `min_gradient` over the
    /// level's scale, give no residual: a gradient at the sensor noise's level is
    /// not texture, and would claim information the image does not hold.
    pub gradient_snr: f64,
    pub min_gradient: f64,
    /// Fewer photometric residuals than this (after the gradient and outlier
    /// tests) constrain nothing: a few edges are not a texture, and a handful of
    /// pixels along a wall's corner lines would otherwise claim the corridor's axis.
    pub min_residuals: u32,
    /// Residuals beyond this many robust scales get no weight (occlusion boundaries,
    /// specular highlights, moving lights).
    pub outlier_scales: f64,
    /// Check the photometric cost along each direction it constrains for a second
    /// minimum as deep as the found one (periodic texture): such a direction is
    /// reported ambiguous and keeps the prior's uncertainty.
    pub ambiguity_check: bool,
}

impl Default for PhotometricConfig {
    fn default() -> Self {
        Self {
            mode: PhotometricMode::Selective,
            intensity_sigma: 0.01,
            weak_ratio: 0.01,
            eo_levels: 5,
            finest_eo_level: 1,
            gradient_snr: 4.0,
            min_gradient: 0.02,
            min_residuals: 100,
            outlier_scales: 5.0,
            ambiguity_check: true,
        }
    }
}

impl PhotometricConfig {
    /// True when scans need their EO pyramid.
    pub fn enabled(&self) -> bool {
        self.mode != PhotometricMode::Off
    }

    pub fn validate(&self, origin: &str) -> Result<(), ConfigError> {
        let positive = |x: f64| x.is_finite() && x > 0.0;
        let checks: [Check; 7] = [
            (
                "align.photometric.gradient_snr",
                self.gradient_snr,
                self.gradient_snr.is_finite() && self.gradient_snr >= 0.0,
                "must be finite and >= 0",
            ),
            (
                "align.photometric.finest_eo_level",
                f64::from(self.finest_eo_level),
                self.finest_eo_level < self.eo_levels,
                "must be below align.photometric.eo_levels",
            ),
            (
                "align.photometric.min_gradient",
                self.min_gradient,
                self.min_gradient.is_finite() && self.min_gradient >= 0.0,
                "must be finite and >= 0",
            ),
            (
                "align.photometric.intensity_sigma",
                self.intensity_sigma,
                positive(self.intensity_sigma),
                "must be finite and > 0",
            ),
            (
                "align.photometric.weak_ratio",
                self.weak_ratio,
                (0.0..1.0).contains(&self.weak_ratio),
                "must be in [0, 1)",
            ),
            (
                "align.photometric.eo_levels",
                f64::from(self.eo_levels),
                (1..=8).contains(&self.eo_levels),
                "must be 1..=8",
            ),
            (
                "align.photometric.outlier_scales",
                self.outlier_scales,
                positive(self.outlier_scales),
                "must be finite and > 0",
            ),
        ];
        first_failed(origin, &checks)
    }
}
