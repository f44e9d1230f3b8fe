//! SE(3) on nalgebra isometries: the exponential and logarithm maps and the adjoint,
//! with tangent vectors ordered `(ω, v)` (rotation first, radians; then metres).
//!
//! Conventions: a pose is perturbed on the right, `T · exp(δ)`, so `δ` lives in the
//! frame the pose maps *from* (for `world_from_scan`, the scan's own frame).

use nalgebra::{Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use texel::Pose;

/// Below this rotation angle (radians) the series forms of the `V` matrices are used;
/// the closed forms divide by powers of the angle.
const SMALL_ANGLE_RAD: f64 = 1.0e-5;

/// `[a]×`, the matrix of `a × ·`.
pub fn skew(a: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -a.z, a.y, a.z, 0.0, -a.x, -a.y, a.x, 0.0)
}

/// The `V` matrix of SE(3) (left Jacobian of SO(3)): `t = V(ω) v`.
fn left_jacobian_so3(omega: &Vector3<f64>) -> Matrix3<f64> {
    let theta = omega.norm();
    let k = skew(omega);
    let k2 = k * k;
    let (a, b) = if theta < SMALL_ANGLE_RAD {
        // (1 - cos θ)/θ² and (θ - sin θ)/θ³ by their Taylor series.
        (
            0.5 - theta * theta / 24.0,
            1.0 / 6.0 - theta * theta / 120.0,
        )
    } else {
        let t2 = theta * theta;
        (
            (1.0 - theta.cos()) / t2,
            (theta - theta.sin()) / (t2 * theta),
        )
    };
    Matrix3::identity() + k * a + k2 * b
}

/// `V⁻¹`, the inverse of [`left_jacobian_so3`].
fn left_jacobian_so3_inverse(omega: &Vector3<f64>) -> Matrix3<f64> {
    let theta = omega.norm();
    let k = skew(omega);
    let k2 = k * k;
    let c = if theta < SMALL_ANGLE_RAD {
        1.0 / 12.0 + theta * theta / 720.0
    } else {
        let half = 0.5 * theta;
        // (1 - (θ/2) cot(θ/2)) / θ²; sin(θ/2) > 0 for θ in (0, 2π), and the
        // logarithm returns θ ≤ π.
        (1.0 - half * half.cos() / half.sin()) / (theta * theta)
    };
    Matrix3::identity() - k * 0.5 + k2 * c
}

/// `exp(δ)` for `δ = (ω, v)`.
pub fn exp(delta: &Vector6<f64>) -> Pose {
    let omega = Vector3::new(delta[0], delta[1], delta[2]);
    let v = Vector3::new(delta[3], delta[4], delta[5]);
    let rotation = UnitQuaternion::from_scaled_axis(omega);
    let t = left_jacobian_so3(&omega) * v;
    Pose::from_parts(Translation3::from(t), rotation)
}

/// `log(T)` as `(ω, v)`, with the rotation angle in [0, π].
pub fn log(pose: &Pose) -> Vector6<f64> {
    let omega = pose.rotation.scaled_axis();
    let v = left_jacobian_so3_inverse(&omega) * pose.translation.vector;
    Vector6::new(omega.x, omega.y, omega.z, v.x, v.y, v.z)
}

/// The adjoint of `T` for `(ω, v)` tangents: `T exp(δ) T⁻¹ = exp(Ad(T) δ)`.
pub fn adjoint(pose: &Pose) -> Matrix6<f64> {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let t = skew(&pose.translation.vector) * r;
    let mut ad = Matrix6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(3, 0).copy_from(&t);
    ad
}

/// `ad(δ)`, the small adjoint (Lie bracket matrix) of a tangent `(ω, v)`.
pub fn small_adjoint(delta: &Vector6<f64>) -> Matrix6<f64> {
    let w = skew(&Vector3::new(delta[0], delta[1], delta[2]));
    let v = skew(&Vector3::new(delta[3], delta[4], delta[5]));
    let mut ad = Matrix6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&w);
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&w);
    ad.fixed_view_mut::<3, 3>(3, 0).copy_from(&v);
    ad
}

/// Rotation angle (radians) and translation length (metres) of a tangent.
pub fn tangent_size(delta: &Vector6<f64>) -> (f64, f64) {
    (
        Vector3::new(delta[0], delta[1], delta[2]).norm(),
        Vector3::new(delta[3], delta[4], delta[5]).norm(),
    )
}

/// True when every component of the pose is finite.
pub fn is_finite(pose: &Pose) -> bool {
    let q = pose.rotation.quaternion();
    pose.translation.vector.iter().all(|c| c.is_finite())
        && [q.i, q.j, q.k, q.w].iter().all(|c| c.is_finite())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use proptest::prelude::*;

    fn v6(a: [f64; 6]) -> Vector6<f64> {
        Vector6::from_column_slice(&a)
    }

    proptest! {
        #[test]
        fn log_inverts_exp(a in prop::array::uniform6(-1.5f64..1.5)) {
            let d = v6(a);
            let back = log(&exp(&d));
            prop_assert!((back - d).norm() < 1e-9, "{d:?} -> {back:?}");
        }

        #[test]
        fn adjoint_moves_perturbations(a in prop::array::uniform6(-1.0f64..1.0),
                                       b in prop::array::uniform6(-0.3f64..0.3)) {
            let t = exp(&v6(a));
            let d = v6(b);
            let lhs = t * exp(&d) * t.inverse();
            let rhs = exp(&(adjoint(&t) * d));
            let (angle, dist) = texel::pose::pose_difference(&lhs, &rhs);
            prop_assert!(angle < 1e-9 && dist < 1e-9);
        }
    }

    #[test]
    fn tiny_angles_use_the_series() {
        let d = v6([1e-9, -2e-9, 3e-9, 0.1, 0.2, 0.3]);
        let p = exp(&d);
        assert!((p.translation.vector - Vector3::new(0.1, 0.2, 0.3)).norm() < 1e-9);
        assert!((log(&p) - d).norm() < 1e-15);
        assert_eq!(log(&Pose::identity()), Vector6::zeros());
    }
}
