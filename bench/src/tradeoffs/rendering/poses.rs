//! Held-out virtual camera poses: between two acquisition poses (halfway, rotation
//! slerped), and beyond them (pulled back and raised, or moved closer than the scans
//! were taken from), spread along the trajectory.

use nalgebra::{Point3, Vector3};
use texel::Pose;

/// A pose no scan was taken from.
#[derive(Debug, Clone)]
pub struct HeldOutPose {
    /// `between`, `farther` or `closer`.
    pub kind: &'static str,
    pub world_from_eo: Pose,
}

/// `count` held-out poses of a simulated trajectory: a third halfway between
/// neighbouring frames, a third pulled back by a quarter of the viewing distance and
/// raised by an eighth (aimed at the same point), a third moved forward by a third
/// of the viewing distance (closer than any scan: the range confidence matters).
pub fn held_out_poses(sim: &sims::Simulator, count: usize) -> Vec<HeldOutPose> {
    let n = sim.frame_count();
    if n < 2 || count == 0 {
        return Vec::new();
    }
    let eyes: Vec<Vector3<f64>> = (0..n)
        .map(|i| sim.true_pose(i).translation.vector)
        .collect();
    let centroid = eyes.iter().sum::<Vector3<f64>>() / n as f64;
    (0..count)
        .map(|j| {
            // Spread over the trajectory; never the last frame (it has no successor).
            let i = (j * (n - 1)) / count;
            let a = sim.true_pose(i);
            let b = sim.true_pose(i + 1);
            let mid = halfway(&a, &b);
            let eye = mid.translation.vector;
            let forward = mid.rotation * Vector3::z();
            // The viewing distance: to the point of the optical axis nearest the
            // trajectory's centroid (an orbit's centre), at least a metre.
            let dist = (centroid - eye).dot(&forward).max(1.0);
            let target = eye + forward * dist;
            match j % 3 {
                0 => HeldOutPose {
                    kind: "between",
                    world_from_eo: mid,
                },
                1 => {
                    let eye = eye - forward * (0.25 * dist) + Vector3::z() * (0.125 * dist);
                    HeldOutPose {
                        kind: "farther",
                        world_from_eo: sims::trajectory::look_at(
                            Point3::from(eye),
                            Point3::from(target),
                            Vector3::z(),
                        ),
                    }
                }
                _ => HeldOutPose {
                    kind: "closer",
                    world_from_eo: Pose::from_parts(
                        nalgebra::Translation3::from(eye + forward * (dist / 3.0)),
                        mid.rotation,
                    ),
                },
            }
        })
        .collect()
}

/// Halfway between two poses: translations averaged, rotations slerped.
fn halfway(a: &Pose, b: &Pose) -> Pose {
    let t = (a.translation.vector + b.translation.vector) * 0.5;
    let r = a
        .rotation
        .try_slerp(&b.rotation, 0.5, 1e-9)
        .unwrap_or(a.rotation);
    Pose::from_parts(nalgebra::Translation3::from(t), r)
}
