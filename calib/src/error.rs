//! Why a calibration was refused: each error names the constraint that is missing and
//! what to capture next, so no capture yields a confident wrong answer.

use thiserror::Error;

#[derive(Debug, Error)]
pub enum CalibError {
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    #[error("cannot read the capture: {0}")]
    Capture(#[from] texel::capture::CaptureError),
    #[error("{0}")]
    Input(String),
    #[error(
        "too few usable views: {usable} of {total} frames show the whole {nx}x{ny} board \
         to the EO camera, and calibration needs at least {needed}. Capture more views \
         (10-20 is good) with every inner corner of the board inside the image{reasons}"
    )]
    TooFewViews {
        usable: usize,
        total: usize,
        needed: usize,
        nx: usize,
        ny: usize,
        /// `"; frame 3: ..."` for frames that were skipped, or empty.
        reasons: String,
    },
    #[error(
        "all {views} views are nearly fronto-parallel (the largest board tilt is \
         {max_tilt_deg:.1} degrees): a board facing the camera square-on cannot separate \
         the focal length from the distance. Capture views with the board tilted by \
         20-45 degrees about its horizontal and vertical axes"
    )]
    FrontoParallel { views: usize, max_tilt_deg: f64 },
    #[error(
        "too little tilt to fix the focal length: with {views} views whose largest board \
         tilt is {max_tilt_deg:.1} degrees, its standard deviation would be \
         {relative_std_percent:.2} % of f (limit {limit_percent:.2} %). Add views with the \
         board tilted by 20-45 degrees, about both its horizontal and its vertical axis \
         (more such views if the board was already tilted that much)"
    )]
    TooLittleTilt {
        views: usize,
        relative_std_percent: f64,
        limit_percent: f64,
        max_tilt_deg: f64,
    },
    #[error(
        "the target was never fully seen by the lidar: in none of the {views} views does \
         the lidar see the whole plate ({reasons}). Capture views in which the whole \
         board, with its border, lies inside the lidar's narrower field of view, with \
         background behind it"
    )]
    LidarNeverSawTarget { views: usize, reasons: String },
    #[error(
        "the lidar views do not fix eo_from_lidar: {what}. Capture lidar views of the \
         board at several different tilts (at least three clearly different board \
         orientations)"
    )]
    ExtrinsicUnconstrained { what: String },
    #[error("the {stage} estimate did not converge to finite values ({detail})")]
    Diverged { stage: &'static str, detail: String },
}
