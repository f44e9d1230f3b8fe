//! What fusion computes once per sensor rather than per frame: the angles between
//! neighbouring lidar rays (for the stretched-triangle rule), the lidar rays turned
//! into the EO frame, and the EO camera's projection constants.
//!
//! A module of its own below both [`crate::sensor`], whose [`crate::Sensor`] carries
//! these tables, and [`crate::fuse`](mod@crate::fuse), which reads them; it takes the
//! cameras and the extrinsic rather than a sensor model so that it depends on
//! neither.

use crate::camera::{Distortion, MIN_PROJECT_DEPTH, PinholeCamera};
use crate::pose::Pose;
use crate::rays::RayTable;

/// Angles in radians between each lidar pixel's ray and its neighbours' (right,
/// down, down-right, and from the right neighbour to the down neighbour), row-major;
/// 0 where a neighbour is missing or a ray is invalid. Computed once per sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct LidarPitch {
    pub right: Vec<f32>,
    pub down: Vec<f32>,
    pub down_right: Vec<f32>,
    /// Between `(u + 1, v)` and `(u, v + 1)`.
    pub right_to_down: Vec<f32>,
}

/// The angle between two unit rays, `2 asin(|a - b| / 2)`: accurate for the tiny
/// angles between neighbouring pixels, where `acos(a·b)` loses half its digits.
fn ray_angle(a: [f32; 3], b: [f32; 3]) -> f32 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let half_chord = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() * 0.5;
    2.0 * half_chord.clamp(0.0, 1.0).asin()
}

impl LidarPitch {
    pub fn new(rays: &RayTable) -> Self {
        let (w, h) = (rays.width as usize, rays.height as usize);
        let angle = |u0: usize, v0: usize, u1: usize, v1: usize| -> f32 {
            if u1 >= w || v1 >= h {
                return 0.0;
            }
            match (rays.ray(v0 * w + u0), rays.ray(v1 * w + u1)) {
                (Some(a), Some(b)) => ray_angle(a, b),
                _ => 0.0,
            }
        };
        let mut pitch = Self {
            right: Vec::with_capacity(w * h),
            down: Vec::with_capacity(w * h),
            down_right: Vec::with_capacity(w * h),
            right_to_down: Vec::with_capacity(w * h),
        };
        for v in 0..h {
            for u in 0..w {
                pitch.right.push(angle(u, v, u + 1, v));
                pitch.down.push(angle(u, v, u, v + 1));
                pitch.down_right.push(angle(u, v, u + 1, v + 1));
                pitch.right_to_down.push(if u + 1 < w && v + 1 < h {
                    angle(u + 1, v, u, v + 1)
                } else {
                    0.0
                });
            }
        }
        pitch
    }
}

/// The lidar's rays in the EO frame and the EO projection, computed once per sensor:
/// a return at range `r` on pixel `i` is the EO-frame point `ray_i · r + t`, then one
/// evaluation of [`EoProjection::project`]. Per frame, fusion does arithmetic only.
///
/// The rays are stored as three arrays (x, y, z) so that a row of pixels is three
/// contiguous runs the placement loop reads with vector loads. The fields are
/// crate-visible because that loop (`fuse::rows`) reads them directly.
#[derive(Debug, Clone, PartialEq)]
pub struct FusionTables {
    /// Unit lidar rays turned by `eo_from_lidar`'s rotation (f64, from the f32 ray
    /// table), row-major; zero where the lidar pixel has no ray.
    pub(crate) ray_x: Vec<f64>,
    pub(crate) ray_y: Vec<f64>,
    pub(crate) ray_z: Vec<f64>,
    /// False where the lidar pixel has no ray (outside its distortion domain).
    pub(crate) ray_valid: Vec<bool>,
    /// `eo_from_lidar`'s translation: the lidar's centre in the EO frame.
    pub(crate) translation: [f64; 3],
    pub(crate) projection: EoProjection,
}

impl FusionTables {
    /// The tables of a sensor whose lidar (ray table `rays`) sits at `eo_from_lidar`
    /// in the frame of the EO camera `eo`.
    pub fn new(eo_from_lidar: &Pose, eo: &PinholeCamera, rays: &RayTable) -> Self {
        let rotation = eo_from_lidar.rotation.to_rotation_matrix();
        let m = rotation.matrix();
        let (table, valid) = rays.rays();
        let turned: Vec<[f64; 3]> = table
            .iter()
            .zip(valid)
            .map(|(r, &ok)| {
                if !ok {
                    return [0.0; 3];
                }
                let r = r.map(f64::from);
                [0, 1, 2].map(|row| m[(row, 0)] * r[0] + m[(row, 1)] * r[1] + m[(row, 2)] * r[2])
            })
            .collect();
        let t = eo_from_lidar.translation.vector;
        Self {
            ray_x: turned.iter().map(|r| r[0]).collect(),
            ray_y: turned.iter().map(|r| r[1]).collect(),
            ray_z: turned.iter().map(|r| r[2]).collect(),
            ray_valid: valid.to_vec(),
            translation: [t.x, t.y, t.z],
            projection: EoProjection::new(eo),
        }
    }

    /// Number of lidar pixels.
    pub fn len(&self) -> usize {
        self.ray_valid.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ray_valid.is_empty()
    }

    /// False where the lidar pixel has no ray, row-major.
    pub fn ray_valid(&self) -> &[bool] {
        &self.ray_valid
    }

    pub fn projection(&self) -> &EoProjection {
        &self.projection
    }
}

/// The EO camera's projection from its optical frame to texture coordinates, with
/// every constant taken out of the camera model once: the same arithmetic as
/// [`PinholeCamera::project`] followed by [`PinholeCamera::contains_pixel`], in the
/// same order (so the same results to the last bit), without branches.
#[derive(Debug, Clone, PartialEq)]
pub struct EoProjection {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    skew: f64,
    /// `plumb_bob` coefficients; all zero for an ideal pinhole, which makes the
    /// distortion polynomial the identity exactly (`x · 1 + 0 + 0`).
    k1: f64,
    k2: f64,
    k3: f64,
    two_p1: f64,
    two_p2: f64,
    p1: f64,
    p2: f64,
    /// The distortion's valid domain `r² < max_r2`; infinity when unbounded.
    max_r2: f64,
    /// The image spans `[-0.5, right) x [-0.5, bottom)` in pixels.
    right: f64,
    bottom: f64,
    inv_width: f64,
    inv_height: f64,
}

impl EoProjection {
    pub fn new(camera: &PinholeCamera) -> Self {
        let d = match camera.distortion {
            Distortion::None => [0.0; 5],
            Distortion::PlumbBob(b) => b.to_array(),
        };
        let [k1, k2, p1, p2, k3] = d;
        Self {
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            skew: camera.skew,
            k1,
            k2,
            k3,
            two_p1: 2.0 * p1,
            two_p2: 2.0 * p2,
            p1,
            p2,
            max_r2: camera.max_radius_squared().unwrap_or(f64::INFINITY),
            right: f64::from(camera.width) - 0.5,
            bottom: f64::from(camera.height) - 0.5,
            inv_width: 1.0 / f64::from(camera.width),
            inv_height: 1.0 / f64::from(camera.height),
        }
    }

    /// The texture coordinate of EO-frame point `p` (pixel centre `x` maps to
    /// `(x + 0.5) / width`), and whether `p` has one: false when it is behind the
    /// camera, outside the distortion's domain, off the image or not finite (the
    /// coordinate is then meaningless).
    ///
    /// Every test is a comparison that a NaN or an infinity fails, so a non-finite
    /// value anywhere along the way is refused by the last one; everything is computed
    /// unconditionally and the verdict taken at the end, so loops over pixels
    /// vectorise.
    #[inline(always)]
    pub fn project(&self, p: [f64; 3]) -> ([f32; 2], bool) {
        let in_front = p[2] >= MIN_PROJECT_DEPTH;
        let (x, y) = (p[0] / p[2], p[1] / p[2]);
        let r2 = x * x + y * y;
        let in_domain = r2 < self.max_r2;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xy = x * y;
        let xd = x * radial + self.two_p1 * xy + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + self.two_p2 * xy;
        let px = self.fx * xd + self.skew * yd + self.cx;
        let py = self.fy * yd + self.cy;
        let on_image = (px >= -0.5) & (py >= -0.5) & (px < self.right) & (py < self.bottom);
        let uv = [
            ((px + 0.5) * self.inv_width) as f32,
            ((py + 0.5) * self.inv_height) as f32,
        ];
        (uv, in_front & in_domain & on_image)
    }
}
