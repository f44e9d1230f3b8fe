//! Registration settings: defaults live here in code; a TOML file overrides any of
//! them, and a key this file does not know is an error that names it.

use std::path::Path;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::photometric::PhotometricConfig;

/// The robust kernel applied to normalised residuals (iteratively reweighted least
/// squares; each variant's weight function `w(e) = ρ'(e)/e` is in `kernel.rs`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RobustKernel {
    /// Quadratic inside the threshold, linear outside (Huber 1964).
    Huber,
    /// Tukey's biweight: residuals beyond the threshold get no weight.
    Tukey,
    /// Geman-McClure: weights fall off as `1/e⁴` far out.
    GemanMcclure,
}

impl RobustKernel {
    /// The usual tuning constant (95 % efficiency for Gaussian noise for Huber and
    /// Tukey), in units of the residual scale.
    pub fn default_threshold(self) -> f64 {
        match self {
            Self::Huber => 1.345,
            Self::Tukey => 4.685,
            Self::GemanMcclure => 2.0,
        }
    }
}

/// How each step is solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Solver {
    GaussNewton,
    /// Gauss-Newton with a damping term that grows when a step raises the cost.
    LevenbergMarquardt,
}

/// Pairwise (scan-to-scans) alignment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AlignConfig {
    /// Range-image pyramid levels, each half the resolution of the one below (1 = the
    /// full-resolution grid only).
    pub pyramid_levels: u32,
    /// Iterations at most per pyramid level.
    pub max_iterations: u32,
    /// Use every n-th source pixel in each direction; coarser levels too, as long as
    /// that leaves them 1024 sample positions (else a smaller stride).
    pub point_stride: u32,
    pub kernel: RobustKernel,
    /// Kernel threshold in units of the residual scale; the kernel's usual constant
    /// when absent.
    pub kernel_threshold: Option<f64>,
    /// The direct photometric term on the EO image (`[align.photometric]`).
    pub photometric: PhotometricConfig,
    pub solver: Solver,
    /// Correspondences farther apart than this are rejected at the finest level; the
    /// gate doubles per coarser level.
    pub max_correspondence_distance_m: f64,
    /// Correspondences whose normals differ by more than this are rejected.
    pub max_normal_angle_deg: f64,
    /// The finest level stops when a step rotates less than this (a coarser level `ℓ`
    /// when it rotates less than `2^ℓ` times this)...
    pub convergence_rotation_rad: f64,
    /// ... and translates less than this.
    pub convergence_translation_m: f64,
    /// An eigen-direction of the (scaled) normal matrix whose eigenvalue is below this
    /// fraction of the largest is unobservable: the solution keeps the prior there.
    pub degeneracy_threshold: f64,
    /// Fewer correspondences than this at the finest level is a failure.
    pub min_correspondences: u32,
    /// Fewer than this fraction of source samples landing on a target return is a
    /// failure (too little overlap).
    pub min_overlap: f64,
    /// Fewer than this fraction of the overlapping samples being inliers is a
    /// failure (poor fit).
    pub min_inlier_ratio: f64,
    /// An inlier's residual is within this many noise sigmas.
    pub inlier_sigmas: f64,
    /// A result moved further than this from its initial guess has diverged.
    pub max_rotation_change_deg: f64,
    pub max_translation_change_m: f64,
    /// Uncertainty of the initial guess: the covariance the result keeps in
    /// unobservable directions.
    pub prior_sigma_rotation_deg: f64,
    pub prior_sigma_translation_m: f64,
    /// Reduce chunks on the rayon pool (results are bit-identical either way). Off by
    /// default: a 128x128 scan is too little work to split, and in the daemon the
    /// pool is shared with fusion and encoding (measured: the registration stage at
    /// 30 Hz took 19.3 ms median wall time with it on, 8.7 ms with it off).
    pub parallel: bool,
}

impl Default for AlignConfig {
    fn default() -> Self {
        Self {
            pyramid_levels: 3,
            max_iterations: 10,
            point_stride: 2,
            kernel: RobustKernel::Huber,
            kernel_threshold: None,
            photometric: PhotometricConfig::default(),
            solver: Solver::GaussNewton,
            max_correspondence_distance_m: 0.1,
            max_normal_angle_deg: 45.0,
            convergence_rotation_rad: 1.0e-4,
            convergence_translation_m: 1.0e-4,
            degeneracy_threshold: 0.001,
            min_correspondences: 50,
            min_overlap: 0.15,
            min_inlier_ratio: 0.5,
            inlier_sigmas: 3.0,
            max_rotation_change_deg: 30.0,
            max_translation_change_m: 1.0,
            prior_sigma_rotation_deg: 5.0,
            prior_sigma_translation_m: 0.2,
            parallel: false,
        }
    }
}

impl AlignConfig {
    pub fn kernel_threshold(&self) -> f64 {
        self.kernel_threshold
            .unwrap_or_else(|| self.kernel.default_threshold())
    }
}

/// Which earlier scans a new scan is registered against.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct KeyframeConfig {
    /// Keyframes in the model-side window (the most recent ones).
    pub window: u32,
    /// A registered scan becomes a keyframe when it has moved this far from the
    /// newest keyframe...
    pub translation_m: f64,
    /// ... or turned this much ...
    pub rotation_deg: f64,
    /// ... or when less than this fraction of it overlaps the window.
    pub min_overlap: f64,
    /// Keyframe pyramids held in memory at most; beyond it the pyramids of the
    /// keyframes least recently used by the window or loop closure are dropped (their
    /// graph node and pose stay; they are no longer loop-closure candidates).
    pub max_resident: u32,
}

impl Default for KeyframeConfig {
    fn default() -> Self {
        Self {
            window: 3,
            translation_m: 0.2,
            rotation_deg: 10.0,
            min_overlap: 0.6,
            max_resident: 512,
        }
    }
}

/// Loop closure and the pose graph.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GlobalConfig {
    /// Global refinement on or off (off: poses are never revised).
    pub enabled: bool,
    /// Keyframes within this distance of a new keyframe are loop-closure candidates...
    pub loop_radius_m: f64,
    /// ... if their viewing directions differ by less than this ...
    pub loop_max_angle_deg: f64,
    /// ... and they are at least this many keyframes older.
    pub loop_min_gap_keyframes: u32,
    /// Candidates verified by registration per new keyframe, nearest first.
    pub loop_max_candidates: u32,
    /// After an accepted loop closure, this many keyframes pass before candidates
    /// are verified again (1: at every keyframe). A larger interval closes a loop
    /// every few keyframes along mapped ground instead of at each one (each closure
    /// costs registrations and a graph optimisation), at some cost in drift; a first
    /// revisit is always verified at once.
    pub loop_interval_keyframes: u32,
    /// A loop-closure registration must reach this inlier ratio (of overlapping
    /// samples) to be accepted.
    pub loop_min_inlier_ratio: f64,
    /// Gauss-Newton iterations of the pose graph per optimisation.
    pub max_iterations: u32,
    /// Keyframes one optimisation moves at most: those of the loop being closed, the
    /// newest of them when the loop is longer; older ones are held fixed.
    pub max_optimised_keyframes: u32,
    /// A scan's pose is sent again (`PoseRevised`) only when it moved more than this
    /// from the pose last sent for it...
    pub revision_translation_m: f64,
    /// ... or turned more than this.
    pub revision_rotation_deg: f64,
}

impl Default for GlobalConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            loop_radius_m: 1.0,
            loop_max_angle_deg: 45.0,
            loop_min_gap_keyframes: 8,
            loop_max_candidates: 2,
            loop_interval_keyframes: 1,
            loop_min_inlier_ratio: 0.7,
            max_iterations: 10,
            max_optimised_keyframes: 100,
            revision_translation_m: 0.002,
            revision_rotation_deg: 0.05,
        }
    }
}

/// Failed scans kept for another try.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RetryConfig {
    /// Failed scans held at most (the oldest is dropped first).
    pub max_pending: u32,
    /// Tries per failed scan against later keyframes before it is given up.
    pub max_retries: u32,
}

impl Default for RetryConfig {
    fn default() -> Self {
        Self {
            max_pending: 8,
            max_retries: 3,
        }
    }
}

/// Everything registration can be told.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RegistrationConfig {
    pub align: AlignConfig,
    pub keyframes: KeyframeConfig,
    pub global: GlobalConfig,
    pub retry: RetryConfig,
}

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read registration config {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("registration config {origin}: {message}")]
    Parse { origin: String, message: String },
    #[error("registration config {origin}: {key} = {value}: {rule}")]
    Invalid {
        origin: String,
        key: &'static str,
        value: String,
        rule: &'static str,
    },
}

impl RegistrationConfig {
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    /// Parses TOML overrides of the defaults; `origin` names the text in errors.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let config: Self = toml::from_str(text).map_err(|e| ConfigError::Parse {
            origin: origin.to_string(),
            message: e.to_string(),
        })?;
        config.validate(origin)?;
        Ok(config)
    }

    /// Checks every value against the range it is meaningful in.
    pub fn validate(&self, origin: &str) -> Result<(), ConfigError> {
        let a = &self.align;
        let k = &self.keyframes;
        let g = &self.global;
        let positive = "must be finite and > 0";
        let fraction = "must be in [0, 1]";
        let checks: [Check; 24] = [
            (
                "align.pyramid_levels",
                f64::from(a.pyramid_levels),
                (1..=6).contains(&a.pyramid_levels),
                "must be 1..=6",
            ),
            (
                "align.max_iterations",
                f64::from(a.max_iterations),
                (1..=1000).contains(&a.max_iterations),
                "must be 1..=1000",
            ),
            (
                "align.point_stride",
                f64::from(a.point_stride),
                (1..=64).contains(&a.point_stride),
                "must be 1..=64",
            ),
            (
                "align.kernel_threshold",
                a.kernel_threshold(),
                is_positive(a.kernel_threshold()),
                positive,
            ),
            (
                "align.max_correspondence_distance_m",
                a.max_correspondence_distance_m,
                is_positive(a.max_correspondence_distance_m),
                positive,
            ),
            (
                "align.max_normal_angle_deg",
                a.max_normal_angle_deg,
                a.max_normal_angle_deg > 0.0 && a.max_normal_angle_deg <= 180.0,
                "must be in (0, 180]",
            ),
            (
                "align.convergence_rotation_rad",
                a.convergence_rotation_rad,
                is_positive(a.convergence_rotation_rad),
                positive,
            ),
            (
                "align.convergence_translation_m",
                a.convergence_translation_m,
                is_positive(a.convergence_translation_m),
                positive,
            ),
            (
                "align.degeneracy_threshold",
                a.degeneracy_threshold,
                (0.0..1.0).contains(&a.degeneracy_threshold),
                "must be in [0, 1)",
            ),
            (
                "align.min_overlap",
                a.min_overlap,
                (0.0..=1.0).contains(&a.min_overlap),
                fraction,
            ),
            (
                "align.min_inlier_ratio",
                a.min_inlier_ratio,
                (0.0..=1.0).contains(&a.min_inlier_ratio),
                fraction,
            ),
            (
                "align.inlier_sigmas",
                a.inlier_sigmas,
                is_positive(a.inlier_sigmas),
                positive,
            ),
            (
                "align.max_rotation_change_deg",
                a.max_rotation_change_deg,
                is_positive(a.max_rotation_change_deg),
                positive,
            ),
            (
                "align.max_translation_change_m",
                a.max_translation_change_m,
                is_positive(a.max_translation_change_m),
                positive,
            ),
            (
                "align.prior_sigma_rotation_deg",
                a.prior_sigma_rotation_deg,
                is_positive(a.prior_sigma_rotation_deg),
                positive,
            ),
            (
                "align.prior_sigma_translation_m",
                a.prior_sigma_translation_m,
                is_positive(a.prior_sigma_translation_m),
                positive,
            ),
            (
                "keyframes.window",
                f64::from(k.window),
                (1..=16).contains(&k.window),
                "must be 1..=16",
            ),
            (
                "keyframes.min_overlap",
                k.min_overlap,
                (0.0..=1.0).contains(&k.min_overlap),
                fraction,
            ),
            (
                "keyframes.max_resident",
                f64::from(k.max_resident),
                (k.window.saturating_add(1)..=1_000_000).contains(&k.max_resident),
                "must be above keyframes.window and at most 1000000",
            ),
            (
                "global.max_optimised_keyframes",
                f64::from(g.max_optimised_keyframes),
                (2..=100_000).contains(&g.max_optimised_keyframes),
                "must be 2..=100000",
            ),
            (
                "global.revision_translation_m",
                g.revision_translation_m,
                g.revision_translation_m.is_finite() && g.revision_translation_m >= 0.0,
                "must be finite and >= 0",
            ),
            (
                "global.revision_rotation_deg",
                g.revision_rotation_deg,
                g.revision_rotation_deg.is_finite() && g.revision_rotation_deg >= 0.0,
                "must be finite and >= 0",
            ),
            (
                "global.loop_radius_m",
                g.loop_radius_m,
                is_positive(g.loop_radius_m),
                positive,
            ),
            (
                "global.loop_min_inlier_ratio",
                g.loop_min_inlier_ratio,
                (0.0..=1.0).contains(&g.loop_min_inlier_ratio),
                fraction,
            ),
        ];
        first_failed(origin, &checks)?;
        a.photometric.validate(origin)?;
        let more: [Check; 4] = [
            (
                "global.loop_interval_keyframes",
                f64::from(g.loop_interval_keyframes),
                (1..=10_000).contains(&g.loop_interval_keyframes),
                "must be 1..=10000",
            ),
            (
                "keyframes.translation_m",
                k.translation_m,
                is_positive(k.translation_m),
                positive,
            ),
            (
                "keyframes.rotation_deg",
                k.rotation_deg,
                is_positive(k.rotation_deg),
                positive,
            ),
            (
                "global.max_iterations",
                f64::from(g.max_iterations),
                (1..=100).contains(&g.max_iterations),
                "must be 1..=100",
            ),
        ];
        first_failed(origin, &more)
    }
}

/// A value check: the key, the value, whether it holds, the rule it breaks.
pub(crate) type Check = (&'static str, f64, bool, &'static str);

/// The first check that fails, as the error naming its key, value and rule.
pub(crate) fn first_failed(origin: &str, checks: &[Check]) -> Result<(), ConfigError> {
    match checks.iter().find(|(_, _, ok, _)| !ok) {
        Some(&(key, value, _, rule)) => Err(ConfigError::Invalid {
            origin: origin.to_string(),
            key,
            value: value.to_string(),
            rule,
        }),
        None => Ok(()),
    }
}

fn is_positive(x: f64) -> bool {
    x.is_finite() && x > 0.0
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn empty_text_gives_the_defaults_and_keys_override_them() {
        let c = RegistrationConfig::from_toml_str("", "empty").unwrap();
        assert_eq!(c, RegistrationConfig::default());
        let c = RegistrationConfig::from_toml_str(
            "[align]\npyramid_levels = 2\nkernel = \"tukey\"\n[global]\nenabled = false\n",
            "x",
        )
        .unwrap();
        assert_eq!(c.align.pyramid_levels, 2);
        assert_eq!(c.align.kernel, RobustKernel::Tukey);
        assert!((c.align.kernel_threshold() - 4.685).abs() < 1e-12);
        assert!(!c.global.enabled);
        assert_eq!(
            c.align.max_iterations,
            AlignConfig::default().max_iterations
        );
    }

    #[test]
    fn unknown_keys_and_bad_values_are_named() {
        let e = RegistrationConfig::from_toml_str("[align]\npyramid_lvls = 2\n", "f.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("f.toml") && e.contains("pyramid_lvls"), "{e}");
        let e = RegistrationConfig::from_toml_str("[aligne]\n", "f.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("aligne"), "{e}");
        let e = RegistrationConfig::from_toml_str("[align]\npoint_stride = 0\n", "f.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("align.point_stride"), "{e}");
        let e = RegistrationConfig::from_toml_str("[align]\nkernel = \"cauchy\"\n", "f.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("cauchy"), "{e}");
    }
}
