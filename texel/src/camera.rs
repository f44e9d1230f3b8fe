//! The pinhole camera model with optional `plumb_bob` distortion: projection of points
//! in the camera's optical frame to pixels and back.
//!
//! Conventions follow the capture format: optical frame +x right, +y down, +z forward;
//! integer pixel coordinates are pixel centres, so pixel (0,0) is centred at (0,0).

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::distortion::{PlumbBob, UndistortFailure};

/// Largest image side the project accepts anywhere (also the limit for frames read
/// from captures and the wire), so sizes can be checked before allocating.
pub const MAX_IMAGE_SIDE: u32 = 16_384;

/// Iteration budget for undistortion; Newton converges in < 10 iterations inside
/// the domain, the rest is headroom for points near the fold.
pub const UNDISTORT_MAX_ITERATIONS: u32 = 50;

/// Nearest depth in front of the camera a point may have and still be projected.
pub(crate) const MIN_PROJECT_DEPTH: f64 = 1.0e-9;

/// Lens distortion of a camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "model", rename_all = "snake_case", deny_unknown_fields)]
pub enum Distortion {
    /// An ideal pinhole (`distortion_model` empty or `none`).
    #[default]
    None,
    /// `plumb_bob` with `D = [k1, k2, p1, p2, k3]`.
    PlumbBob(PlumbBob),
}

/// A pinhole camera with `K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]` and distortion.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PinholeCamera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub skew: f64,
    #[serde(default)]
    pub distortion: Distortion,
}

/// A camera whose parameters cannot describe a real pinhole camera.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum CameraError {
    #[error("image size {width}x{height} is outside 1..={MAX_IMAGE_SIDE} per side")]
    BadSize { width: u32, height: u32 },
    #[error("focal lengths must be finite and positive (fx = {fx}, fy = {fy})")]
    BadFocalLength { fx: f64, fy: f64 },
    #[error("vertical field of view {0} degrees is outside (0, 179)")]
    BadFieldOfView(f64),
    #[error("principal point and skew must be finite")]
    NonFiniteIntrinsics,
    #[error("distortion coefficients must be finite")]
    NonFiniteDistortion,
    #[error("K must be 9 numbers [fx, skew, cx, 0, fy, cy, 0, 0, 1], got {0:?}")]
    BadK(Vec<f64>),
    #[error("unknown distortion model {0:?} (expected plumb_bob or none)")]
    UnknownDistortionModel(String),
    #[error("plumb_bob needs D = [k1, k2, p1, p2, k3] (4 or 5 numbers), got {0} numbers")]
    BadDistortionLength(usize),
    #[error("distortion model none must have an empty D, got {0} numbers")]
    UnexpectedDistortion(usize),
}

/// Why a 3D point has no pixel.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
pub enum ProjectError {
    #[error("point is not finite")]
    NonFinite,
    #[error("point is behind the camera (z = {z})")]
    Behind { z: f64 },
    #[error("point lies outside the distortion model's valid domain")]
    OutsideDistortionDomain,
}

/// Why a pixel has no ray.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
pub enum UnprojectError {
    #[error("pixel ({u}, {v}) is not finite")]
    NonFinite { u: f64, v: f64 },
    #[error("pixel ({u}, {v}) lies outside the distortion model's valid domain")]
    OutsideDistortionDomain { u: f64, v: f64 },
    #[error("undistortion of pixel ({u}, {v}) did not converge (residual {residual:e})")]
    NotConverged { u: f64, v: f64, residual: f64 },
}

impl PinholeCamera {
    /// An ideal pinhole with the principal point at the image centre and the given
    /// vertical field of view.
    pub fn from_vertical_fov(width: u32, height: u32, fov_y_deg: f64) -> Result<Self, CameraError> {
        if !(fov_y_deg > 0.0 && fov_y_deg < 179.0) {
            return Err(CameraError::BadFieldOfView(fov_y_deg));
        }
        let half = (fov_y_deg.to_radians() * 0.5).tan();
        let f = 0.5 * f64::from(height) / half;
        let camera = Self {
            width,
            height,
            fx: f,
            fy: f,
            cx: (f64::from(width) - 1.0) * 0.5,
            cy: (f64::from(height) - 1.0) * 0.5,
            skew: 0.0,
            distortion: Distortion::None,
        };
        camera.validate()?;
        Ok(camera)
    }

    /// Builds a camera from the capture format's fields (`K` row-major, `D`,
    /// `distortion_model`), validating them.
    pub fn from_calibration(
        width: u32,
        height: u32,
        k: &[f64],
        distortion_model: &str,
        d: &[f64],
    ) -> Result<Self, CameraError> {
        if k.len() != 9 || k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || (k[8] - 1.0).abs() > 1e-12 {
            return Err(CameraError::BadK(k.to_vec()));
        }
        let distortion = match distortion_model {
            "" | "none" => {
                if d.iter().any(|&c| c != 0.0) {
                    return Err(CameraError::UnexpectedDistortion(d.len()));
                }
                Distortion::None
            }
            "plumb_bob" => Distortion::PlumbBob(
                PlumbBob::from_slice(d).ok_or(CameraError::BadDistortionLength(d.len()))?,
            ),
            other => return Err(CameraError::UnknownDistortionModel(other.to_string())),
        };
        let camera = Self {
            width,
            height,
            fx: k[0],
            skew: k[1],
            cx: k[2],
            fy: k[4],
            cy: k[5],
            distortion,
        };
        camera.validate()?;
        Ok(camera)
    }

    /// Checks that the parameters describe a camera; every constructor from input
    /// (files, captures, the wire) calls this.
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width == 0
            || self.height == 0
            || self.width > MAX_IMAGE_SIDE
            || self.height > MAX_IMAGE_SIDE
        {
            return Err(CameraError::BadSize {
                width: self.width,
                height: self.height,
            });
        }
        if !(self.fx.is_finite() && self.fy.is_finite() && self.fx > 0.0 && self.fy > 0.0) {
            return Err(CameraError::BadFocalLength {
                fx: self.fx,
                fy: self.fy,
            });
        }
        if !(self.cx.is_finite() && self.cy.is_finite() && self.skew.is_finite()) {
            return Err(CameraError::NonFiniteIntrinsics);
        }
        if let Distortion::PlumbBob(d) = &self.distortion
            && !d.is_finite()
        {
            return Err(CameraError::NonFiniteDistortion);
        }
        Ok(())
    }

    /// `K` row-major, as the capture format stores it.
    pub fn k_row_major(&self) -> [f64; 9] {
        [
            self.fx, self.skew, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0,
        ]
    }

    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::from_row_slice(&self.k_row_major())
    }

    /// `(distortion_model, D)` as the capture format stores them.
    pub fn distortion_fields(&self) -> (&'static str, Vec<f64>) {
        match &self.distortion {
            Distortion::None => ("", Vec::new()),
            Distortion::PlumbBob(d) => ("plumb_bob", d.to_array().to_vec()),
        }
    }

    /// The distortion's valid-domain bound (see [`PlumbBob::max_radius_squared`]).
    pub fn max_radius_squared(&self) -> Option<f64> {
        match &self.distortion {
            Distortion::None => None,
            Distortion::PlumbBob(d) => d.max_radius_squared(),
        }
    }

    /// Normalised (undistorted, z = 1) coordinates to pixels. Inlined: registration
    /// projects every point of every iteration through it.
    #[inline]
    pub fn normalized_to_pixel(&self, p: Vector2<f64>) -> Vector2<f64> {
        let d = match &self.distortion {
            Distortion::None => p,
            Distortion::PlumbBob(b) => b.distort(p),
        };
        Vector2::new(
            self.fx * d.x + self.skew * d.y + self.cx,
            self.fy * d.y + self.cy,
        )
    }

    /// Projects a point in the camera's optical frame to a pixel.
    pub fn project(&self, p: &Vector3<f64>) -> Result<Vector2<f64>, ProjectError> {
        self.project_with_domain(p, self.max_radius_squared())
    }

    /// [`Self::project`] with the domain bound computed once by the caller, for loops.
    pub fn project_with_domain(
        &self,
        p: &Vector3<f64>,
        max_r2: Option<f64>,
    ) -> Result<Vector2<f64>, ProjectError> {
        if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
            return Err(ProjectError::NonFinite);
        }
        if p.z < MIN_PROJECT_DEPTH {
            return Err(ProjectError::Behind { z: p.z });
        }
        let n = Vector2::new(p.x / p.z, p.y / p.z);
        if !(n.x.is_finite() && n.y.is_finite()) {
            return Err(ProjectError::NonFinite);
        }
        if max_r2.is_some_and(|m| n.norm_squared() >= m) {
            return Err(ProjectError::OutsideDistortionDomain);
        }
        Ok(self.normalized_to_pixel(n))
    }

    /// Pixel to normalised undistorted coordinates (the point on the z = 1 plane).
    pub fn unproject(&self, pixel: Vector2<f64>) -> Result<Vector2<f64>, UnprojectError> {
        self.unproject_with_domain(pixel, self.max_radius_squared())
    }

    /// [`Self::unproject`] with the domain bound computed once by the caller.
    pub fn unproject_with_domain(
        &self,
        pixel: Vector2<f64>,
        max_r2: Option<f64>,
    ) -> Result<Vector2<f64>, UnprojectError> {
        let (u, v) = (pixel.x, pixel.y);
        if !(u.is_finite() && v.is_finite()) {
            return Err(UnprojectError::NonFinite { u, v });
        }
        // fx, fy > 0 by validation, so the divisions are safe.
        let yd = (v - self.cy) / self.fy;
        let xd = (u - self.cx - self.skew * yd) / self.fx;
        let distorted = Vector2::new(xd, yd);
        match &self.distortion {
            Distortion::None => Ok(distorted),
            Distortion::PlumbBob(b) => b
                .undistort(distorted, max_r2, UNDISTORT_MAX_ITERATIONS)
                .map_err(|failure| match failure {
                    UndistortFailure::OutsideDomain => {
                        UnprojectError::OutsideDistortionDomain { u, v }
                    }
                    UndistortFailure::NotConverged { residual } => {
                        UnprojectError::NotConverged { u, v, residual }
                    }
                }),
        }
    }

    /// Pixel to the unit ray through it, in the optical frame.
    pub fn unproject_ray(&self, pixel: Vector2<f64>) -> Result<Vector3<f64>, UnprojectError> {
        let n = self.unproject(pixel)?;
        // The z = 1 component keeps the norm >= 1, so normalising is safe.
        Ok(Vector3::new(n.x, n.y, 1.0).normalize())
    }

    /// True when the pixel coordinate lies on the image (pixel centres at integers,
    /// so the image spans [-0.5, W - 0.5) x [-0.5, H - 0.5)).
    pub fn contains_pixel(&self, pixel: Vector2<f64>) -> bool {
        pixel.x >= -0.5
            && pixel.y >= -0.5
            && pixel.x < f64::from(self.width) - 0.5
            && pixel.y < f64::from(self.height) - 0.5
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(distortion: Distortion) -> PinholeCamera {
        PinholeCamera {
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 505.0,
            cx: 319.5,
            cy: 241.0,
            skew: 0.0,
            distortion,
        }
    }

    #[test]
    fn ideal_projection_matches_k() {
        let c = camera(Distortion::None);
        let px = c.project(&Vector3::new(1.0, -0.5, 4.0)).unwrap();
        assert!((px.x - (500.0 * 0.25 + 319.5)).abs() < 1e-12);
        assert!((px.y - (505.0 * -0.125 + 241.0)).abs() < 1e-12);
    }

    #[test]
    fn behind_and_non_finite_are_refused() {
        let c = camera(Distortion::None);
        assert!(matches!(
            c.project(&Vector3::new(0.0, 0.0, -1.0)),
            Err(ProjectError::Behind { .. })
        ));
        assert!(matches!(
            c.project(&Vector3::new(0.0, 0.0, 0.0)),
            Err(ProjectError::Behind { .. })
        ));
        assert_eq!(
            c.project(&Vector3::new(f64::NAN, 0.0, 1.0)),
            Err(ProjectError::NonFinite)
        );
        assert!(c.unproject(Vector2::new(f64::INFINITY, 0.0)).is_err());
    }

    #[test]
    fn calibration_fields_round_trip() {
        let c = camera(Distortion::PlumbBob(PlumbBob {
            k1: -0.2,
            k2: 0.05,
            p1: 0.001,
            p2: 0.002,
            k3: -0.01,
        }));
        let (model, d) = c.distortion_fields();
        let back = PinholeCamera::from_calibration(c.width, c.height, &c.k_row_major(), model, &d)
            .unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn invalid_calibrations_are_named() {
        let k = camera(Distortion::None).k_row_major();
        assert!(matches!(
            PinholeCamera::from_calibration(640, 480, &k[..8], "", &[]),
            Err(CameraError::BadK(_))
        ));
        assert!(matches!(
            PinholeCamera::from_calibration(640, 480, &k, "fisheye", &[]),
            Err(CameraError::UnknownDistortionModel(_))
        ));
        assert!(matches!(
            PinholeCamera::from_calibration(640, 480, &k, "plumb_bob", &[0.1]),
            Err(CameraError::BadDistortionLength(1))
        ));
        assert!(matches!(
            PinholeCamera::from_calibration(0, 480, &k, "", &[]),
            Err(CameraError::BadSize { .. })
        ));
        let mut bad = k;
        bad[0] = f64::NAN;
        assert!(matches!(
            PinholeCamera::from_calibration(640, 480, &bad, "", &[]),
            Err(CameraError::BadFocalLength { .. })
        ));
    }

    #[test]
    fn vertical_fov_gives_the_expected_focal_length() {
        let c = PinholeCamera::from_vertical_fov(640, 480, 90.0).unwrap();
        assert!((c.fy - 240.0).abs() < 1e-9);
        assert!(PinholeCamera::from_vertical_fov(640, 480, 180.0).is_err());
        assert!(PinholeCamera::from_vertical_fov(640, 480, 0.0).is_err());
    }
}
