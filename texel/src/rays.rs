//! The lidar's per-pixel unit-ray table, computed once per sensor so that fusion and
//! the simulator never undistort a pixel per frame, and the one unit ray through a
//! pixel that every ray table (this one, the simulator's cameras') is made of.

use nalgebra::{Vector2, Vector3};

use crate::camera::PinholeCamera;

/// The unit ray through `pixel` (pixel coordinates, centres at integers) in
/// `camera`'s optical frame, in f32 as ray tables store it; `None` where the pixel
/// cannot be unprojected (outside the distortion model's valid domain, not finite).
/// `max_r2` is `camera.max_radius_squared()`, computed once by the caller.
#[inline]
pub fn pixel_ray(
    camera: &PinholeCamera,
    pixel: Vector2<f64>,
    max_r2: Option<f64>,
) -> Option<[f32; 3]> {
    let p = camera.unproject_with_domain(pixel, max_r2).ok()?;
    // The z = 1 component keeps the norm >= 1.
    let r = Vector3::new(p.x, p.y, 1.0).normalize();
    Some([r.x as f32, r.y as f32, r.z as f32])
}

/// Unit rays in the lidar optical frame, one per pixel, row-major.
///
/// A pixel whose ray cannot be computed (outside the distortion model's valid domain)
/// has `valid[i] == false` and a zero ray; such a pixel never yields a point.
#[derive(Debug, Clone, PartialEq)]
pub struct RayTable {
    pub width: u32,
    pub height: u32,
    rays: Vec<[f32; 3]>,
    valid: Vec<bool>,
}

impl RayTable {
    /// Unprojects every pixel centre of `camera`.
    pub fn new(camera: &PinholeCamera) -> Self {
        let max_r2 = camera.max_radius_squared();
        let n = camera.width as usize * camera.height as usize;
        let mut rays = Vec::with_capacity(n);
        let mut valid = Vec::with_capacity(n);
        for v in 0..camera.height {
            for u in 0..camera.width {
                let pixel = Vector2::new(f64::from(u), f64::from(v));
                match pixel_ray(camera, pixel, max_r2) {
                    Some(r) => {
                        rays.push(r);
                        valid.push(true);
                    }
                    None => {
                        rays.push([0.0; 3]);
                        valid.push(false);
                    }
                }
            }
        }
        Self {
            width: camera.width,
            height: camera.height,
            rays,
            valid,
        }
    }

    pub fn len(&self) -> usize {
        self.rays.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }

    /// The unit ray of row-major pixel `index`, or `None` for an invalid pixel.
    #[inline]
    pub fn ray(&self, index: usize) -> Option<[f32; 3]> {
        match self.valid.get(index) {
            Some(true) => Some(self.rays[index]),
            _ => None,
        }
    }

    /// All rays (zero for invalid pixels) and the validity mask, row-major.
    pub fn rays(&self) -> (&[[f32; 3]], &[bool]) {
        (&self.rays, &self.valid)
    }

    pub fn valid_count(&self) -> usize {
        self.valid.iter().filter(|&&v| v).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;

    #[test]
    fn centre_ray_is_the_optical_axis_and_all_rays_are_unit() {
        let c = PinholeCamera {
            width: 5,
            height: 3,
            fx: 10.0,
            fy: 10.0,
            cx: 2.0,
            cy: 1.0,
            skew: 0.0,
            distortion: Distortion::None,
        };
        let t = RayTable::new(&c);
        assert_eq!(t.len(), 15);
        assert_eq!(t.ray(7), Some([0.0, 0.0, 1.0]));
        for i in 0..t.len() {
            let r = t.ray(i).unwrap();
            let n = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
            assert!((n - 1.0).abs() < 1e-6);
        }
        // Corner (0,0) looks up-left: x < 0, y < 0.
        let r = t.ray(0).unwrap();
        assert!(r[0] < 0.0 && r[1] < 0.0);
    }
}
