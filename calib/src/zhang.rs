//! Zhang's closed-form initialisation (Zhang 2000, "A flexible new technique for
//! camera calibration", §3.1): each board homography `H = [h1 h2 h3] ~ K [r1 r2 t]`
//! gives two linear constraints on `B = K⁻ᵀK⁻¹` (eq. 8-9); `K` follows from `B`
//! (Appendix B) and each view's pose from `K⁻¹H` (eq. 2). Skew is taken as zero (one
//! more linear row), as for every modern sensor.

use nalgebra::{DMatrix, Matrix3, SymmetricEigen, Vector3, Vector6};
use texel::Pose;

use crate::geometry::nearest_rotation;

/// `v_ij` of Zhang's eq. 8 for homography columns `i`, `j`.
fn v(h: &Matrix3<f64>, i: usize, j: usize) -> Vector6<f64> {
    let hi = h.column(i);
    let hj = h.column(j);
    Vector6::new(
        hi[0] * hj[0],
        hi[0] * hj[1] + hi[1] * hj[0],
        hi[1] * hj[1],
        hi[2] * hj[0] + hi[0] * hj[2],
        hi[2] * hj[1] + hi[1] * hj[2],
        hi[2] * hj[2],
    )
}

/// Intrinsics `(fx, fy, cx, cy)` from at least three homographies, or from two
/// with the principal point at `centre`. `None` when the views do not fix them (too
/// little tilt, parallel boards) or the solution is not a real camera.
pub fn intrinsics(homographies: &[Matrix3<f64>], centre: (f64, f64)) -> Option<[f64; 4]> {
    full(homographies).or_else(|| with_centre(homographies, centre))
}

/// Zhang's method with the principal point free.
fn full(homographies: &[Matrix3<f64>]) -> Option<[f64; 4]> {
    if homographies.len() < 3 {
        return None;
    }
    // Normalise each homography (scale is arbitrary) for conditioning.
    let rows = 2 * homographies.len() + 1;
    let mut a = DMatrix::zeros(rows, 6);
    for (k, h) in homographies.iter().enumerate() {
        let h = h / h.norm();
        let v12 = v(&h, 0, 1);
        let d = v(&h, 0, 0) - v(&h, 1, 1);
        for c in 0..6 {
            a[(2 * k, c)] = v12[c];
            a[(2 * k + 1, c)] = d[c];
        }
    }
    // Zero skew: B12 = 0, weighted like one view's row.
    a[(rows - 1, 1)] = 1.0;
    let eig = SymmetricEigen::new(a.transpose() * &a);
    let mut order: Vec<usize> = (0..6).collect();
    order.sort_by(|&x, &y| eig.eigenvalues[x].total_cmp(&eig.eigenvalues[y]));
    // A near-double smallest eigenvalue means the views do not fix B.
    if !(eig.eigenvalues[order[1]] > 1.0e-9 * eig.eigenvalues[order[5]]) {
        return None;
    }
    let b = eig.eigenvectors.column(order[0]);
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let den = b11 * b22 - b12 * b12;
    if !(den.abs() > 0.0) || b11 == 0.0 {
        return None;
    }
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    let alpha2 = lambda / b11;
    let beta2 = lambda * b11 / den;
    if !(alpha2 > 0.0 && beta2 > 0.0) {
        return None;
    }
    let (alpha, beta) = (alpha2.sqrt(), beta2.sqrt());
    let gamma = -b12 * alpha2 * beta / lambda;
    let u0 = gamma * v0 / beta - b13 * alpha2 / lambda;
    let k = [alpha, beta, u0, v0];
    k.iter().all(|x| x.is_finite()).then_some(k)
}

/// The two-unknown variant: principal point known, `B = diag(1/fx², 1/fy²)` in
/// centred coordinates.
fn with_centre(homographies: &[Matrix3<f64>], centre: (f64, f64)) -> Option<[f64; 4]> {
    if homographies.len() < 2 {
        return None;
    }
    let shift = Matrix3::new(1.0, 0.0, -centre.0, 0.0, 1.0, -centre.1, 0.0, 0.0, 1.0);
    let mut a = DMatrix::zeros(2 * homographies.len(), 2);
    let mut rhs = nalgebra::DVector::zeros(2 * homographies.len());
    for (k, h) in homographies.iter().enumerate() {
        let h = shift * h;
        let h = h / h.norm();
        // h1ᵀ B h2 = 0 and h1ᵀ B h1 = h2ᵀ B h2 with B = diag(a, b, 1).
        a[(2 * k, 0)] = h[(0, 0)] * h[(0, 1)];
        a[(2 * k, 1)] = h[(1, 0)] * h[(1, 1)];
        rhs[2 * k] = -h[(2, 0)] * h[(2, 1)];
        a[(2 * k + 1, 0)] = h[(0, 0)].powi(2) - h[(0, 1)].powi(2);
        a[(2 * k + 1, 1)] = h[(1, 0)].powi(2) - h[(1, 1)].powi(2);
        rhs[2 * k + 1] = -(h[(2, 0)].powi(2) - h[(2, 1)].powi(2));
    }
    let ata = a.transpose() * &a;
    let eig = SymmetricEigen::new(ata.clone());
    let (lo, hi) = (eig.eigenvalues.min(), eig.eigenvalues.max());
    if !(lo > 1.0e-12 * hi && hi > 0.0) {
        return None;
    }
    let sol = ata.try_inverse()? * (a.transpose() * rhs);
    if !(sol[0] > 0.0 && sol[1] > 0.0) {
        return None;
    }
    let k = [1.0 / sol[0].sqrt(), 1.0 / sol[1].sqrt(), centre.0, centre.1];
    k.iter().all(|x| x.is_finite()).then_some(k)
}

/// The board's pose in the camera (`camera_from_board`) from its homography and `K`.
pub fn pose_from_homography(h: &Matrix3<f64>, k: [f64; 4]) -> Option<Pose> {
    let kinv = Matrix3::new(k[0], 0.0, k[2], 0.0, k[1], k[3], 0.0, 0.0, 1.0).try_inverse()?;
    let m = kinv * h;
    let scale = m.column(0).norm();
    if !(scale > 1.0e-12) {
        return None;
    }
    let mut lambda = 1.0 / scale;
    // The board is in front of the camera.
    if m[(2, 2)] * lambda < 0.0 {
        lambda = -lambda;
    }
    let r1: Vector3<f64> = m.column(0) * lambda;
    let r2: Vector3<f64> = m.column(1) * lambda;
    let t: Vector3<f64> = m.column(2) * lambda;
    let r3 = r1.cross(&r2);
    let r = nearest_rotation(&Matrix3::from_columns(&[r1, r2, r3]))?;
    Some(Pose::from_parts(t.into(), r.into()))
}

/// Angle between the board's normal and the optical axis, degrees, from a
/// homography and an assumed focal length (the centre at the image centre): used to
/// judge tilt before the intrinsics are known.
pub fn tilt_deg(h: &Matrix3<f64>, focal: f64, centre: (f64, f64)) -> Option<f64> {
    let pose = pose_from_homography(h, [focal, focal, centre.0, centre.1])?;
    let n = pose.rotation * Vector3::z();
    Some(n.z.abs().clamp(0.0, 1.0).acos().to_degrees())
}
