//! The virtual camera: an f64 pose `world_from_eo` (EO optical frame: x right, y down,
//! z forward) and an undistorted pinhole with the principal point at the image centre.
//! The GPU only ever sees coordinates relative to this camera (see `docs/rendering.md`).

use glam::{DMat4, DVec4, Mat4};
use nalgebra::{Point3, Vector3};
use texel::{PinholeCamera, Pose};

/// Vertical fields of view outside this range (degrees) are refused.
pub const MIN_FOV_DEG: f64 = 1.0;
pub const MAX_FOV_DEG: f64 = 170.0;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VirtualCamera {
    pub world_from_eo: Pose,
    /// Vertical field of view, radians.
    pub fov_y_rad: f64,
    pub width: u32,
    pub height: u32,
    /// Near clipping distance, metres (the far plane is at infinity, reverse z).
    pub near_m: f64,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    #[error("vertical field of view {0} deg is outside [{MIN_FOV_DEG}, {MAX_FOV_DEG}]")]
    Fov(f64),
    #[error("image size {0}x{1} is empty or larger than 16384")]
    Size(u32, u32),
}

impl VirtualCamera {
    pub fn new(
        world_from_eo: Pose,
        fov_y_deg: f64,
        width: u32,
        height: u32,
    ) -> Result<Self, CameraError> {
        if !(fov_y_deg.is_finite() && (MIN_FOV_DEG..=MAX_FOV_DEG).contains(&fov_y_deg)) {
            return Err(CameraError::Fov(fov_y_deg));
        }
        if width == 0 || height == 0 || width > 16384 || height > 16384 {
            return Err(CameraError::Size(width, height));
        }
        Ok(Self {
            world_from_eo,
            fov_y_rad: fov_y_deg.to_radians(),
            width,
            height,
            near_m: 0.05,
        })
    }

    /// The vertical field of view of a (possibly distorted) camera model, degrees:
    /// `2 atan(h / (2 fy))`; what `--fov-deg` defaults to.
    pub fn fov_y_deg_of(camera: &PinholeCamera) -> f64 {
        let fy = if camera.fy.is_finite() && camera.fy > 0.0 {
            camera.fy
        } else {
            f64::from(camera.height.max(1))
        };
        (2.0 * (f64::from(camera.height) / (2.0 * fy)).atan()).to_degrees()
    }

    pub fn aspect(&self) -> f64 {
        f64::from(self.width) / f64::from(self.height.max(1))
    }

    pub fn tan_half_fov_y(&self) -> f64 {
        (self.fov_y_rad * 0.5).tan()
    }

    /// Focal length in pixels.
    pub fn focal_px(&self) -> f64 {
        f64::from(self.height) / (2.0 * self.tan_half_fov_y())
    }

    pub fn view_from_world(&self) -> Pose {
        self.world_from_eo.inverse()
    }

    pub fn centre_world(&self) -> Point3<f64> {
        Point3::from(self.world_from_eo.translation.vector)
    }

    /// Forward (+z of the optical frame) in world coordinates.
    pub fn forward_world(&self) -> Vector3<f64> {
        self.world_from_eo.rotation * Vector3::z()
    }

    /// Clip-from-view matrix: view x right, y down, z forward; clip y up; reverse z with
    /// an infinite far plane (depth = near / z, compare Greater). Built in f64 from the
    /// intrinsics: they hold no position, so their rounding to f32 does not grow with the
    /// distance from the world origin.
    pub fn clip_from_view(&self) -> Mat4 {
        let fy = 1.0 / self.tan_half_fov_y();
        let fx = fy / self.aspect();
        DMat4::from_cols(
            DVec4::new(fx, 0.0, 0.0, 0.0),
            DVec4::new(0.0, -fy, 0.0, 0.0),
            DVec4::new(0.0, 0.0, 0.0, 1.0),
            DVec4::new(0.0, 0.0, self.near_m, 0.0),
        )
        .as_mat4()
    }

    /// The pixel (x right, y down, origin at the top-left corner) a view-frame point
    /// projects to; `None` behind the camera.
    pub fn project_view(&self, p: &Vector3<f64>) -> Option<[f64; 2]> {
        if p.z <= 0.0 {
            return None;
        }
        let f = self.focal_px();
        Some([
            f64::from(self.width) * 0.5 + f * p.x / p.z,
            f64::from(self.height) * 0.5 + f * p.y / p.z,
        ])
    }

    /// The unit ray through pixel centre `(x + 0.5, y + 0.5)`, view frame.
    pub fn pixel_ray_view(&self, x: u32, y: u32) -> Vector3<f64> {
        let f = self.focal_px();
        let d = Vector3::new(
            (f64::from(x) + 0.5 - f64::from(self.width) * 0.5) / f,
            (f64::from(y) + 0.5 - f64::from(self.height) * 0.5) / f,
            1.0,
        );
        d / d.norm()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn projection_matches_the_pinhole() {
        let cam = VirtualCamera::new(Pose::identity(), 60.0, 160, 120).unwrap();
        let clip = cam.clip_from_view() * glam::Vec4::new(0.3, -0.2, 2.0, 1.0);
        let ndc = clip.truncate() / clip.w;
        let px = cam.project_view(&Vector3::new(0.3, -0.2, 2.0)).unwrap();
        assert!((f64::from(ndc[0] + 1.0) * 80.0 - px[0]).abs() < 1e-3);
        assert!((f64::from(1.0 - ndc[1]) * 60.0 - px[1]).abs() < 1e-3);
        assert!((ndc[2] - 0.05 / 2.0).abs() < 1e-7);
        assert!(VirtualCamera::new(Pose::identity(), 0.0, 10, 10).is_err());
        assert!(VirtualCamera::new(Pose::identity(), 60.0, 0, 10).is_err());
    }
}
