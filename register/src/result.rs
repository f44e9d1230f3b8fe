//! What registration answers: a pose with its covariance, fitness and degenerate
//! directions, or a failure with its reason.

use nalgebra::Matrix6;
use serde::Serialize;
use texel::Pose;
use texel::model::ScanId;

use super::normal_eq::DegenerateDirection;

/// How well a scan fits its targets at the final pose.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct Fitness {
    /// Source samples used at the finest level.
    pub samples: usize,
    /// Fraction of samples that land on a target return.
    pub overlap: f64,
    /// Pairs that passed the distance and normal gates.
    pub correspondences: usize,
    /// Inliers (residual within `inlier_sigmas` of the range noise) over samples, as
    /// Open3D's `fitness`.
    pub inlier_ratio: f64,
    /// Inliers over overlapping samples.
    pub inlier_ratio_of_overlap: f64,
    /// RMS point-to-plane residual of the inliers, metres.
    pub rms_residual_m: f64,
}

/// What the photometric term did in an alignment.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PhotometricSummary {
    /// Photometric residuals at the final evaluation (0: the term did not run).
    pub residuals: usize,
    /// Smallest eigenvalue of the information (scaled coordinates: rotations in
    /// metres at the scene's scale; units 1/m² of the noise-normalised residuals)
    /// of the geometry alone, and with the photometric term where it was admitted.
    pub geometry_min_eigenvalue: f64,
    pub min_eigenvalue: f64,
    /// Directions the term was admitted in (the geometry's weak ones, or six).
    pub admitted_directions: usize,
    /// The brightness change to the first target, `I_t = gain · I_s + bias`.
    pub brightness_gain: f64,
    pub brightness_bias: f64,
}

impl Default for PhotometricSummary {
    fn default() -> Self {
        Self {
            residuals: 0,
            geometry_min_eigenvalue: 0.0,
            min_eigenvalue: 0.0,
            admitted_directions: 0,
            brightness_gain: 1.0,
            brightness_bias: 0.0,
        }
    }
}

/// Why a registration failed. A failed scan never enters the model with this pose.
#[derive(Debug, Clone, PartialEq, Serialize, thiserror::Error)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum FailureReason {
    #[error("the {side} has {count} usable points, fewer than the {needed} needed")]
    NoPoints {
        side: &'static str,
        count: usize,
        needed: usize,
    },
    #[error(
        "too little overlap: {correspondences} correspondences, {overlap_percent:.1} % of samples on a target (need {needed_correspondences} and {needed_percent:.1} %)"
    )]
    TooLittleOverlap {
        correspondences: usize,
        overlap_percent: f64,
        needed_correspondences: usize,
        needed_percent: f64,
    },
    #[error(
        "diverged: moved {rotation_deg:.2} deg and {translation_m:.3} m from the initial guess (limits {max_rotation_deg} deg, {max_translation_m} m)"
    )]
    Diverged {
        rotation_deg: f64,
        translation_m: f64,
        max_rotation_deg: f64,
        max_translation_m: f64,
    },
    #[error("diverged: the estimate is not finite")]
    NonFinite,
    #[error(
        "poor fit: {inlier_percent:.1} % of overlapping samples are inliers (need {needed_percent:.1} %), RMS residual {rms_residual_m:.4} m"
    )]
    PoorFit {
        inlier_percent: f64,
        needed_percent: f64,
        rms_residual_m: f64,
    },
    #[error("no earlier scan to register against")]
    NoTargets,
}

/// Pairwise or scan-to-scans alignment.
#[derive(Debug, Clone)]
pub struct Alignment {
    /// The estimate (for a failure: where the iterations ended, never to be used).
    pub world_from_source: Pose,
    pub initial: Pose,
    pub status: Result<(), FailureReason>,
    /// Covariance of a right perturbation `(ω, v)` of `world_from_source`.
    pub covariance: Matrix6<f64>,
    /// Its inverse, for pose-graph edges.
    pub information: Matrix6<f64>,
    /// Information contributed by each target's correspondences alone (same order as
    /// the targets given).
    pub target_information: Vec<Matrix6<f64>>,
    /// Correspondences per target.
    pub target_correspondences: Vec<usize>,
    pub fitness: Fitness,
    pub degenerate: Vec<DegenerateDirection>,
    pub iterations: u32,
    pub photometric: PhotometricSummary,
}

impl Alignment {
    pub fn is_ok(&self) -> bool {
        self.status.is_ok()
    }
}

/// The outcome of registering one scan.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum RegistrationStatus {
    /// The first scan: it defines the common frame.
    Anchor,
    Registered,
    Failed {
        reason: FailureReason,
    },
}

impl RegistrationStatus {
    pub fn is_registered(&self) -> bool {
        !matches!(self, Self::Failed { .. })
    }
}

/// What [`super::Registrar::register`] answers for one scan.
#[derive(Debug, Clone)]
pub struct RegistrationResult {
    pub timestamp_ns: u64,
    pub seq: u32,
    pub status: RegistrationStatus,
    /// The model id the scan got, when it was registered.
    pub scan_id: Option<ScanId>,
    /// The pose, when registered; for a failure, the estimate that was refused.
    pub world_from_scan: Pose,
    pub covariance: Matrix6<f64>,
    pub fitness: Fitness,
    pub degenerate: Vec<DegenerateDirection>,
    pub iterations: u32,
    /// The scan joined the keyframe window.
    pub keyframe: bool,
    /// Loop closures accepted while registering this scan.
    pub loop_closures: u32,
    pub photometric: PhotometricSummary,
}
