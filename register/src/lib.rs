//! Registration: every scan into the common `world` frame. Scan-to-model alignment
//! against a window of keyframes (projective association on range-image pyramids,
//! robust point-to-plane, degeneracy-aware Gauss-Newton / Levenberg-Marquardt on
//! SE(3)), and global refinement by a pose graph with loop closures. Synchronous,
//! pure and I/O-free: the daemon runs it on a blocking thread. The public API is
//! small: a [`Registrar`] takes scans one by one ([`Registrar::register`]), or
//! [`align_pair`] aligns two, under a [`RegistrationConfig`]; [`capture`] registers a
//! whole recorded capture offline.

// Negated comparisons (`!(x > 0.0)`) are deliberate throughout: a NaN takes the
// degenerate branch with them, where `x <= 0.0` would let it through.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod align;
pub mod associate;
pub mod capture;
pub mod clock;
pub mod config;
pub mod envelope;
pub mod graph;
pub mod kernel;
pub mod motion;
pub mod normal_eq;
pub mod photometric;
pub mod placement;
pub mod pyramid;
pub mod registrar;
pub mod result;
pub mod scan_table;
pub mod se3;

pub use align::{AlignTarget, align, align_pair};
pub use capture::{RegisterCommandError, RegisterReport, default_anchor, register_capture};
pub use config::{AlignConfig, ConfigError, RegistrationConfig, RobustKernel, Solver};
pub use normal_eq::DegenerateDirection;
pub use photometric::{PhotometricConfig, PhotometricMode};
pub use pyramid::{PyramidOptions, ScanPyramid};
pub use registrar::{Registrar, RegistrarMemory, RegistrarStats, ScanAnchor};
pub use result::{
    Alignment, FailureReason, Fitness, PhotometricSummary, RegistrationResult, RegistrationStatus,
};
