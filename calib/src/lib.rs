//! Estimating the texel camera's sensor model from captures of a calibration target.

pub mod config;
pub mod detect;
pub mod eo;
pub mod error;
pub mod geometry;
pub mod gray;
pub mod lm;
pub mod zhang;
pub mod extrinsic;
pub mod lidar;
pub mod capture;
pub mod pipeline;
pub mod simulate;
pub mod report;
