//! Estimating the texel camera's sensor model from captures of a calibration target
//! (a planar checkerboard seen by both sensors, as in Budge & Badamkar 2013).
//!
//! # The recipe ([`pipeline::calibrate`])
//!
//! 1. **Detect** the board in every view from pixels alone ([`detect`]: saddle-point
//!    X-corners, grid growing, board indexing, sub-pixel refinement; [`lidar`]:
//!    range segmentation, robust plane, plate outline, intensity corners).
//! 2. **EO intrinsics** ([`eo`]): Zhang's closed form ([`zhang`]), then
//!    Levenberg-Marquardt ([`lm`]) over intrinsics, `plumb_bob` distortion and one
//!    pose per view; refusals for too few views, fronto-parallel views, too little tilt.
//! 3. **Joint EO-lidar refinement** ([`extrinsic`]): `eo_from_lidar` and the range
//!    bias initialised from plane pairs, then refined together with everything else;
//!    the lidar's intrinsics too when asked.
//! 4. **Uncertainty**: RMS and per-view residuals, standard deviations from the
//!    covariance at the solution.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let input = calib::capture::read_capture(std::path::Path::new("target.mcap"))?;
//! let config = calib::config::CalibConfig::default(); // 9 x 6 corners, 5 cm squares
//! let result = calib::pipeline::calibrate(&input, &config, &mut |_stage, _done, _total| {})?;
//! std::fs::write("sensor.toml", result.sensor_file_text("target.mcap"))?;
//! # Ok(()) }
//! ```
//!
//! [`simulate`] measures a calibration against the simulator's truth (tests, the
//! `accuracy` and `tradeoffs` commands); [`lab_check`] registers a `lab` capture with
//! the daemon's offline path using a calibrated and the true sensor model;
//! [`report`] writes the Markdown report.

// NaN-safe guards: `!(x > 0.0)` is true for NaN as well, which is the point of
// writing them that way.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod capture;
pub mod config;
pub mod detect;
pub mod eo;
pub mod error;
pub mod extrinsic;
pub mod geometry;
pub mod gray;
pub mod lidar;
pub mod lm;
pub mod pipeline;
pub mod report;
pub mod response;
pub mod zhang;
