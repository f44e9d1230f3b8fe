//! Small geometry: plane-to-image homographies (normalised DLT), pose parameter
//! vectors, projection through intrinsic parameter vectors, and plane fits.

use nalgebra::{DMatrix, Matrix3, Point3, Rotation3, SymmetricEigen, Vector2, Vector3};
use texel::{Distortion, PinholeCamera, PlumbBob, Pose};

/// Pixel error returned for a point that cannot be projected (behind the camera):
/// large and finite, so a solver steps away from it without meeting NaN.
pub const UNPROJECTABLE_PX: f64 = 1.0e4;

/// Nearest depth at which a point is still projected.
const MIN_DEPTH_M: f64 = 1.0e-6;

/// Intrinsic parameter vector `[fx, fy, cx, cy, k1, k2, p1, p2, k3]`.
pub type Intrinsics = [f64; 9];

pub fn intrinsics_of(camera: &PinholeCamera) -> Intrinsics {
    let d = match camera.distortion {
        Distortion::PlumbBob(d) => d.to_array(),
        Distortion::None => [0.0; 5],
    };
    [
        camera.fx, camera.fy, camera.cx, camera.cy, d[0], d[1], d[2], d[3], d[4],
    ]
}

/// A camera from an intrinsic vector (skew 0; distortion `None` when all zero).
pub fn camera_of(width: u32, height: u32, k: &[f64]) -> PinholeCamera {
    let d = PlumbBob {
        k1: k[4],
        k2: k[5],
        p1: k[6],
        p2: k[7],
        k3: k[8],
    };
    PinholeCamera {
        width,
        height,
        fx: k[0],
        fy: k[1],
        cx: k[2],
        cy: k[3],
        skew: 0.0,
        distortion: if d.is_identity() {
            Distortion::None
        } else {
            Distortion::PlumbBob(d)
        },
    }
}

/// Projects a camera-frame point through intrinsics `k` (pure arithmetic, finite
/// output for finite input; behind the camera gives `None`).
#[inline]
pub fn project(k: &[f64], p: &Vector3<f64>) -> Option<Vector2<f64>> {
    if !(p.z > MIN_DEPTH_M) || !p.x.is_finite() || !p.y.is_finite() {
        return None;
    }
    let x = p.x / p.z;
    let y = p.y / p.z;
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k[4] + r2 * (k[5] + r2 * k[8]));
    let xy = x * y;
    let xd = x * radial + 2.0 * k[6] * xy + k[7] * (r2 + 2.0 * x * x);
    let yd = y * radial + k[6] * (r2 + 2.0 * y * y) + 2.0 * k[7] * xy;
    Some(Vector2::new(k[0] * xd + k[2], k[1] * yd + k[3]))
}

/// A pose from `[rx, ry, rz, tx, ty, tz]` (rotation vector, translation).
#[inline]
pub fn pose_from_params(p: &[f64]) -> Pose {
    texel::pose::pose_from_rotation_vector(
        Vector3::new(p[0], p[1], p[2]),
        Vector3::new(p[3], p[4], p[5]),
    )
}

pub fn params_from_pose(pose: &Pose) -> [f64; 6] {
    let r = pose.rotation.scaled_axis();
    let t = pose.translation.vector;
    [r.x, r.y, r.z, t.x, t.y, t.z]
}

/// The homography `H` with `[u v 1]ᵀ ~ H [X Y 1]ᵀ`, by the normalised DLT (Hartley);
/// `None` for fewer than 4 points or a degenerate configuration.
pub fn homography(plane: &[Vector2<f64>], image: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    let n = plane.len();
    if n < 4 || image.len() != n {
        return None;
    }
    let (tp, plane_n) = normalise(plane)?;
    let (ti, image_n) = normalise(image)?;
    let mut a = DMatrix::zeros(2 * n, 9);
    for k in 0..n {
        let (x, y) = (plane_n[k].x, plane_n[k].y);
        let (u, v) = (image_n[k].x, image_n[k].y);
        let rows = [
            [-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u],
            [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v],
        ];
        for (r, row) in rows.iter().enumerate() {
            for (c, val) in row.iter().enumerate() {
                a[(2 * k + r, c)] = *val;
            }
        }
    }
    let ata = a.transpose() * &a;
    let eig = SymmetricEigen::new(ata);
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let h = eig.eigenvectors.column(imin);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let h = ti.try_inverse()? * hn * tp;
    let s = h[(2, 2)];
    let h = if s.abs() > 1.0e-12 { h / s } else { h };
    h.iter().all(|v| v.is_finite()).then_some(h)
}

/// Hartley normalisation: centroid to the origin, mean distance √2.
fn normalise(points: &[Vector2<f64>]) -> Option<(Matrix3<f64>, Vec<Vector2<f64>>)> {
    let n = points.len() as f64;
    let c = points.iter().fold(Vector2::zeros(), |a, p| a + p) / n;
    let mean_dist = points.iter().map(|p| (p - c).norm()).sum::<f64>() / n;
    if !(mean_dist > 1.0e-12) {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean_dist;
    let t = Matrix3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0);
    Some((t, points.iter().map(|p| (p - c) * s).collect()))
}

/// Applies a homography; `None` at infinity.
pub fn apply_homography(h: &Matrix3<f64>, p: Vector2<f64>) -> Option<Vector2<f64>> {
    let v = h * Vector3::new(p.x, p.y, 1.0);
    (v.z.abs() > 1.0e-12).then(|| Vector2::new(v.x / v.z, v.y / v.z))
}

/// The rotation nearest to `m` (Frobenius), by SVD; `None` if `m` is not finite.
pub fn nearest_rotation(m: &Matrix3<f64>) -> Option<Rotation3<f64>> {
    if !m.iter().all(|v| v.is_finite()) {
        return None;
    }
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        let mut u2 = u;
        u2.column_mut(2).neg_mut();
        r = u2 * vt;
    }
    Some(Rotation3::from_matrix_unchecked(r))
}

/// A plane `n·x = d` (unit `n`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    pub normal: Vector3<f64>,
    pub d: f64,
}

impl Plane {
    pub fn distance(&self, p: &Point3<f64>) -> f64 {
        self.normal.dot(&p.coords) - self.d
    }

    /// The same plane with its normal turned to point away from the origin
    /// (`d >= 0`): for a camera-frame plane, away from the camera.
    pub fn facing_away(self) -> Self {
        if self.d < 0.0 {
            Self {
                normal: -self.normal,
                d: -self.d,
            }
        } else {
            self
        }
    }
}

/// Least-squares plane through points (smallest-eigenvalue direction of the
/// scatter); `None` for fewer than 3 points or collinear ones.
pub fn fit_plane(points: &[Point3<f64>]) -> Option<Plane> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let c = points.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mut scatter = Matrix3::zeros();
    for p in points {
        let d = p.coords - c;
        scatter += d * d.transpose();
    }
    let eig = SymmetricEigen::new(scatter);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    // Collinear points: the two smallest eigenvalues are both tiny.
    if !(eig.eigenvalues[order[1]] > 1.0e-12 * eig.eigenvalues[order[2]].max(1e-300)) {
        return None;
    }
    let normal: Vector3<f64> = eig.eigenvectors.column(order[0]).into_owned();
    let norm = normal.norm();
    if !(norm > 0.5) {
        return None;
    }
    let normal = normal / norm;
    Some(
        Plane {
            normal,
            d: normal.dot(&c),
        }
        .facing_away(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn homography_recovers_a_projective_map() {
        let h = Matrix3::new(500.0, 20.0, 300.0, -10.0, 480.0, 200.0, 0.1, -0.05, 1.0);
        let plane: Vec<Vector2<f64>> = (0..12)
            .map(|k| Vector2::new(f64::from(k % 4) * 0.1, f64::from(k / 4) * 0.1))
            .collect();
        let image: Vec<Vector2<f64>> = plane
            .iter()
            .map(|p| apply_homography(&h, *p).unwrap())
            .collect();
        let est = homography(&plane, &image).unwrap();
        for (p, q) in plane.iter().zip(&image) {
            assert!((apply_homography(&est, *p).unwrap() - q).norm() < 1e-8);
        }
        assert!(homography(&plane[..3], &image[..3]).is_none());
    }

    #[test]
    fn plane_fit_faces_away_and_refuses_collinear_points() {
        let pts: Vec<Point3<f64>> = (0..9)
            .map(|k| Point3::new(f64::from(k % 3), f64::from(k / 3), 2.0))
            .collect();
        let p = fit_plane(&pts).unwrap();
        assert!((p.normal.z - 1.0).abs() < 1e-12 && (p.d - 2.0).abs() < 1e-12);
        let line: Vec<Point3<f64>> = (0..5)
            .map(|k| Point3::new(f64::from(k), 0.0, 1.0))
            .collect();
        assert!(fit_plane(&line).is_none());
    }
}
