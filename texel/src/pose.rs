//! Rigid poses in f64, named by what they map: `world_from_eo` takes EO-frame
//! coordinates to world coordinates.

use nalgebra::{Isometry3, Point3, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3};
use thiserror::Error;

/// A rigid transform `a_from_b` in f64.
pub type Pose = Isometry3<f64>;

/// Quaternions shorter than this are not rotations (a zero quaternion from a
/// default-initialised message, for instance).
const MIN_QUATERNION_NORM: f64 = 1.0e-9;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum PoseError {
    #[error("pose has a non-finite component")]
    NonFinite,
    #[error("quaternion ({x}, {y}, {z}, {w}) has near-zero length and is not a rotation")]
    ZeroQuaternion { x: f64, y: f64, z: f64, w: f64 },
    #[error("expected 7 numbers \"x y z qx qy qz qw\", got {0:?}")]
    BadText(String),
}

/// Builds a pose from a translation and an `(x, y, z, w)` quaternion, normalising the
/// quaternion and refusing one that is not a rotation.
pub fn pose_from_parts(translation: [f64; 3], q_xyzw: [f64; 4]) -> Result<Pose, PoseError> {
    if translation
        .iter()
        .chain(q_xyzw.iter())
        .any(|c| !c.is_finite())
    {
        return Err(PoseError::NonFinite);
    }
    let [x, y, z, w] = q_xyzw;
    let q = Quaternion::new(w, x, y, z);
    let norm = q.norm();
    // Components above about 1e154 overflow the norm: such a quaternion is scaled by
    // its largest component first (the scaled norm lies in [1, 2]). Others keep the
    // direct division, so a unit quaternion read back is bit-for-bit what was written.
    let (q, norm) = if norm.is_finite() {
        (q, norm)
    } else {
        let largest = q_xyzw.iter().fold(0.0_f64, |m, c| m.max(c.abs()));
        let scaled = q / largest;
        (scaled, scaled.norm())
    };
    if norm < MIN_QUATERNION_NORM {
        return Err(PoseError::ZeroQuaternion { x, y, z, w });
    }
    Ok(Isometry3::from_parts(
        Translation3::new(translation[0], translation[1], translation[2]),
        UnitQuaternion::new_unchecked(q / norm),
    ))
}

/// Translation and `(x, y, z, w)` quaternion of a pose.
pub fn pose_to_parts(pose: &Pose) -> ([f64; 3], [f64; 4]) {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    ([t.x, t.y, t.z], [q.i, q.j, q.k, q.w])
}

/// Parses `"x y z qx qy qz qw"` (whitespace or commas between numbers).
pub fn parse_pose(text: &str) -> Result<Pose, PoseError> {
    let numbers: Result<Vec<f64>, _> = text
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|s| !s.is_empty())
        .map(str::parse::<f64>)
        .collect();
    match numbers {
        Ok(n) if n.len() == 7 => pose_from_parts([n[0], n[1], n[2]], [n[3], n[4], n[5], n[6]]),
        _ => Err(PoseError::BadText(text.to_string())),
    }
}

/// Rotation angle of a pose in radians, in [0, pi]; well conditioned for tiny angles.
pub fn rotation_angle(pose: &Pose) -> f64 {
    pose.rotation.angle()
}

/// Translation length in metres.
pub fn translation_norm(pose: &Pose) -> f64 {
    pose.translation.vector.norm()
}

/// The rotation and translation difference `a⁻¹ b` between two poses: angle in
/// radians, distance in metres.
pub fn pose_difference(a: &Pose, b: &Pose) -> (f64, f64) {
    let d = a.inverse() * b;
    (rotation_angle(&d), translation_norm(&d))
}

/// A pose from a rotation vector (axis × angle, radians) and a translation.
pub fn pose_from_rotation_vector(rotation: Vector3<f64>, translation: Vector3<f64>) -> Pose {
    Isometry3::from_parts(
        Translation3::from(translation),
        UnitQuaternion::from_scaled_axis(rotation),
    )
}

/// The EO optical frame (x right, y down, z forward) at `eye` looking at `target`
/// with world `up`; falls back to another up vector when looking along `up`, and to
/// looking along +x when `target == eye`.
pub fn look_at(eye: Point3<f64>, target: Point3<f64>, up: Vector3<f64>) -> Pose {
    let forward = target - eye;
    let z = if forward.norm() > 1.0e-12 {
        forward.normalize()
    } else {
        Vector3::x()
    };
    let mut x = z.cross(&up);
    if x.norm() < 1.0e-9 {
        x = z.cross(&Vector3::y());
        if x.norm() < 1.0e-9 {
            x = z.cross(&Vector3::x());
        }
    }
    let x = x.normalize();
    let y = z.cross(&x);
    let r = Rotation3::from_basis_unchecked(&[x, y, z]);
    Pose::from_parts(
        Translation3::from(eye.coords),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_round_trip_and_quaternion_is_normalised() {
        let p = pose_from_parts([1.0, 2.0, 3.0], [0.0, 0.0, 2.0, 2.0]).unwrap();
        let (t, q) = pose_to_parts(&p);
        assert_eq!(t, [1.0, 2.0, 3.0]);
        let s = std::f64::consts::FRAC_1_SQRT_2;
        assert!((q[2] - s).abs() < 1e-15 && (q[3] - s).abs() < 1e-15);
    }

    proptest::proptest! {
        /// The rotation does not depend on the quaternion's scale, however large or
        /// small, as long as its norm is above the refusal threshold.
        #[test]
        fn rotation_is_independent_of_the_quaternion_scale(
            q in proptest::array::uniform4(-1.0f64..1.0),
            exponent in -100i32..300,
        ) {
            let Ok(unit) = pose_from_parts([0.0; 3], q) else {
                return Ok(());
            };
            let scale = 10f64.powi(exponent);
            let scaled = q.map(|c| c * scale);
            match pose_from_parts([0.0; 3], scaled) {
                Ok(p) => {
                    let (_, a) = pose_to_parts(&unit);
                    let (_, b) = pose_to_parts(&p);
                    for (x, y) in a.iter().zip(b) {
                        proptest::prop_assert!((x - y).abs() < 1e-12, "{a:?} {b:?}");
                    }
                }
                Err(PoseError::ZeroQuaternion { .. }) => {
                    let norm = scaled.iter().map(|c| c * c).sum::<f64>().sqrt();
                    proptest::prop_assert!(norm < 1e-9, "{scaled:?} refused");
                }
                Err(e) => proptest::prop_assert!(false, "{e}"),
            }
        }
    }

    #[test]
    fn zero_and_non_finite_quaternions_are_refused() {
        assert!(matches!(
            pose_from_parts([0.0; 3], [0.0; 4]),
            Err(PoseError::ZeroQuaternion { .. })
        ));
        assert_eq!(
            pose_from_parts([f64::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            Err(PoseError::NonFinite)
        );
    }

    #[test]
    fn text_poses_parse() {
        let p = parse_pose("1 2 3 0 0 0 1").unwrap();
        assert_eq!(p.translation.vector, Vector3::new(1.0, 2.0, 3.0));
        assert!(parse_pose("1 2 3").is_err());
        assert!(parse_pose("a b c d e f g").is_err());
    }

    #[test]
    fn differences_are_small_for_far_away_poses() {
        // Large coordinates keep their precision in f64.
        let a = pose_from_parts([5.0e6, 4.0e6, 100.0], [0.0, 0.0, 0.0, 1.0]).unwrap();
        let b = pose_from_parts([5.0e6 + 0.001, 4.0e6, 100.0], [0.0, 0.0, 0.0, 1.0]).unwrap();
        let (angle, dist) = pose_difference(&a, &b);
        assert!(angle.abs() < 1e-12);
        assert!((dist - 0.001).abs() < 1e-9);
    }
}
