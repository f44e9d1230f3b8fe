//! What a calibration is told: the target's geometry and the estimation settings.
//! Defaults live here; a TOML file only overrides them, and unknown keys are errors.

use std::path::Path;

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// A planar checkerboard on a plate.
///
/// The board has `inner_corners[0] x inner_corners[1]` inner (X-)corners, so
/// `inner_corners + 1` squares per side, and a plain light border out to the plate's
/// edge. The two counts must differ in parity-sum (`nx + ny` odd, e.g. 9 x 6): the
/// corner squares then tell the board's 180° turns apart, and the unequal counts tell
/// its axes apart.
///
/// **Board frame.** The square in the board's corner next to inner corner `(0, 0)` is
/// dark; `x` runs along the `nx` corners, `y` along the `ny` corners, and `z = x × y`
/// points from the front face into the board (away from a camera that sees it).
/// Inner corner `(i, j)` is at `(i·square_m, j·square_m, 0)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TargetConfig {
    /// Inner corners along the board's x and y axes.
    pub inner_corners: [u32; 2],
    /// Side of one square, metres.
    pub square_m: f64,
    /// The plate's outer size (checkerboard plus border), metres, along x and y;
    /// the lidar finds the board by this extent.
    pub plate_m: [f64; 2],
}

impl Default for TargetConfig {
    fn default() -> Self {
        Self {
            inner_corners: [9, 6],
            square_m: 0.05,
            plate_m: [0.6, 0.45],
        }
    }
}

impl TargetConfig {
    pub fn nx(&self) -> usize {
        self.inner_corners[0] as usize
    }

    pub fn ny(&self) -> usize {
        self.inner_corners[1] as usize
    }

    pub fn corner_count(&self) -> usize {
        self.nx() * self.ny()
    }

    /// Board-frame position of inner corner `(i, j)`, metres.
    pub fn corner_point(&self, i: usize, j: usize) -> [f64; 3] {
        [i as f64 * self.square_m, j as f64 * self.square_m, 0.0]
    }

    /// Board-frame centre of the plate (the checkerboard is centred on it).
    pub fn plate_centre(&self) -> [f64; 3] {
        [
            (self.nx() as f64 - 1.0) * 0.5 * self.square_m,
            (self.ny() as f64 - 1.0) * 0.5 * self.square_m,
            0.0,
        ]
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        let [nx, ny] = self.inner_corners;
        if !(2..=64).contains(&nx) || !(2..=64).contains(&ny) {
            return Err(ConfigError::Invalid(format!(
                "target.inner_corners = [{nx}, {ny}]: each count must be in 2..=64"
            )));
        }
        if (nx + ny) % 2 == 0 {
            return Err(ConfigError::Invalid(format!(
                "target.inner_corners = [{nx}, {ny}]: nx + ny must be odd (e.g. 9 x 6), \
                 or the board looks the same turned by 180 degrees"
            )));
        }
        if !(self.square_m.is_finite() && self.square_m > 0.0 && self.square_m < 10.0) {
            return Err(ConfigError::Invalid(format!(
                "target.square_m = {} must be in (0, 10) metres",
                self.square_m
            )));
        }
        let checker = [
            f64::from(nx + 1) * self.square_m,
            f64::from(ny + 1) * self.square_m,
        ];
        for (k, (&p, &c)) in self.plate_m.iter().zip(&checker).enumerate() {
            if !(p.is_finite() && p >= c && p < 100.0) {
                return Err(ConfigError::Invalid(format!(
                    "target.plate_m[{k}] = {p} must be finite and at least the \
                     checkerboard's {c} m"
                )));
            }
        }
        Ok(())
    }
}

/// How the estimation runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SolverConfig {
    /// Levenberg-Marquardt iteration limit of every stage.
    pub max_iterations: usize,
    /// Estimate the sixth-order radial term `k3` (off: `k3 = 0`, the usual choice
    /// for fields of view below ~90 degrees).
    pub estimate_k3: bool,
    /// Estimate the tangential terms `p1, p2`.
    pub estimate_tangential: bool,
    /// Estimate the lidar's `fx, fy, cx, cy` from its intensity corners even when the
    /// capture carries a lidar calibration (its distortion is kept).
    pub estimate_lidar_intrinsics: bool,
    /// Estimate a constant range bias together with `eo_from_lidar`.
    pub estimate_range_bias: bool,
    /// At most this many board pixels per lidar view enter the plane residuals.
    pub max_lidar_points_per_view: usize,
    /// A view's focal length is called fixed when its relative standard deviation is
    /// below this.
    pub max_focal_relative_std: f64,
}

impl Default for SolverConfig {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            estimate_k3: false,
            estimate_tangential: true,
            estimate_lidar_intrinsics: false,
            estimate_range_bias: true,
            max_lidar_points_per_view: 400,
            max_focal_relative_std: 0.002,
        }
    }
}

/// A calibration's whole configuration (`[target]`, `[solver]`).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CalibConfig {
    pub target: TargetConfig,
    pub solver: SolverConfig,
}

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read calibration config {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("calibration config {path}: {message}")]
    Parse { path: String, message: String },
    #[error("invalid calibration config: {0}")]
    Invalid(String),
}

impl CalibConfig {
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let config: Self = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: origin.to_string(),
            message: e.to_string(),
        })?;
        config.validate()?;
        Ok(config)
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        self.target.validate()?;
        let s = &self.solver;
        if !(1..=10_000).contains(&s.max_iterations) {
            return Err(ConfigError::Invalid(format!(
                "solver.max_iterations = {} must be in 1..=10000",
                s.max_iterations
            )));
        }
        if !(10..=100_000).contains(&s.max_lidar_points_per_view) {
            return Err(ConfigError::Invalid(format!(
                "solver.max_lidar_points_per_view = {} must be in 10..=100000",
                s.max_lidar_points_per_view
            )));
        }
        if !(s.max_focal_relative_std.is_finite() && s.max_focal_relative_std > 0.0) {
            return Err(ConfigError::Invalid(
                "solver.max_focal_relative_std must be finite and positive".into(),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_overrides_apply() {
        CalibConfig::default().validate().unwrap();
        let c = CalibConfig::from_toml_str(
            "[target]\ninner_corners = [7, 4]\nsquare_m = 0.03\nplate_m = [0.3, 0.2]\n",
            "t.toml",
        )
        .unwrap();
        assert_eq!(c.target.inner_corners, [7, 4]);
        assert_eq!(c.solver, SolverConfig::default());
    }

    #[test]
    fn unknown_keys_and_symmetric_boards_are_refused() {
        let e = CalibConfig::from_toml_str("[target]\nsquares = 3\n", "u.toml").unwrap_err();
        assert!(e.to_string().contains("squares"), "{e}");
        let e =
            CalibConfig::from_toml_str("[target]\ninner_corners = [8, 6]\n", "s.toml").unwrap_err();
        assert!(e.to_string().contains("odd"), "{e}");
        let e =
            CalibConfig::from_toml_str("[target]\nplate_m = [0.1, 0.1]\n", "p.toml").unwrap_err();
        assert!(e.to_string().contains("plate_m"), "{e}");
    }
}
