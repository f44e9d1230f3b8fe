//! Camera trajectories: the true `world_from_eo` pose as a continuous function of
//! time (motion blur samples it inside an exposure), and the frame clock.
//!
//! - `poses`: explicit poses, one per frame; between frames the pose is interpolated
//!   (linear position, slerp rotation).
//! - `orbit`: a circle around a centre at a fixed height, looking at a point.
//! - `handheld`: a walk along waypoints at a constant speed, looking at a point or
//!   along the path, with smooth seeded jitter in position and rotation (a sum of
//!   three sinusoids per axis with seeded frequencies in 0.3-2 Hz and phases).

use nalgebra::{Point3, UnitQuaternion, Vector3};
use texel::Pose;

use crate::rng::{PixelRng, Stream};

/// The path's shape.
#[derive(Debug, Clone, PartialEq)]
pub enum Path {
    Poses(Vec<Pose>),
    Orbit {
        center: Point3<f64>,
        radius_m: f64,
        height_m: f64,
        look_at: Point3<f64>,
        start_deg: f64,
        arc_deg: f64,
        /// Frames over which the arc is covered (frame `frames` would be the end).
        period_frames: usize,
    },
    Handheld {
        waypoints: Vec<Point3<f64>>,
        look_at: Option<Point3<f64>>,
        speed_m_per_s: f64,
        jitter_position_m: f64,
        jitter_rotation_deg: f64,
        seed: u64,
        /// A sweep of the view about world +z:
        /// `amplitude · sin(2π t / period + phase)`.
        pan_amplitude_deg: f64,
        pan_period_s: f64,
        pan_phase_deg: f64,
        /// Without `look_at`: the view's elevation above the path's direction, degrees
        /// (negative looks down).
        pitch_deg: f64,
    },
}

/// A trajectory and its frame clock.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    pub path: Path,
    pub rate_hz: f64,
    pub frames: usize,
    pub start_time_ns: u64,
}

/// Poses looking at a point are part of the shared vocabulary.
pub use texel::pose::look_at;

impl Trajectory {
    /// Seconds after the first frame of frame `i`.
    pub fn frame_time_s(&self, i: usize) -> f64 {
        i as f64 / self.rate_hz
    }

    /// Timestamp of frame `i` in nanoseconds.
    pub fn timestamp_ns(&self, i: usize) -> u64 {
        let offset = (i as f64 * 1.0e9 / self.rate_hz).round();
        self.start_time_ns
            .saturating_add(if offset.is_finite() && offset > 0.0 {
                offset as u64
            } else {
                0
            })
    }

    /// The true pose of frame `i`.
    pub fn frame_pose(&self, i: usize) -> Pose {
        self.pose_at(self.frame_time_s(i))
    }

    /// The true `world_from_eo` at `t_s` seconds after the first frame.
    pub fn pose_at(&self, t_s: f64) -> Pose {
        let frame = t_s * self.rate_hz;
        match &self.path {
            Path::Poses(poses) => {
                let last = poses.len().saturating_sub(1);
                let f = if frame.is_finite() {
                    frame.clamp(0.0, last as f64)
                } else {
                    0.0
                };
                let i = (f.floor() as usize).min(last);
                let j = (i + 1).min(last);
                let a = (f - i as f64).clamp(0.0, 1.0);
                match (poses.get(i), poses.get(j)) {
                    (Some(p), Some(q)) if a > 0.0 => p.lerp_slerp(q, a),
                    (Some(p), _) => *p,
                    _ => Pose::identity(),
                }
            }
            Path::Orbit {
                center,
                radius_m,
                height_m,
                look_at: target,
                start_deg,
                arc_deg,
                period_frames,
            } => {
                let fraction = frame / (*period_frames).max(1) as f64;
                let angle = (start_deg + arc_deg * fraction).to_radians();
                let eye = center
                    + Vector3::new(radius_m * angle.cos(), radius_m * angle.sin(), *height_m);
                look_at(eye, *target, Vector3::z())
            }
            Path::Handheld {
                waypoints,
                look_at: target,
                speed_m_per_s,
                jitter_position_m,
                jitter_rotation_deg,
                seed,
                pan_amplitude_deg,
                pan_period_s,
                pan_phase_deg,
                pitch_deg,
            } => {
                let s = speed_m_per_s * t_s;
                let eye = point_along(waypoints, s);
                let nominal = match target {
                    Some(t) => look_at(eye, *t, Vector3::z()),
                    None => {
                        let ahead = point_along(waypoints, s + 0.5);
                        let behind = point_along(waypoints, s - 0.5);
                        let mut ahead = ahead - behind;
                        // Tilted about the horizontal axis across the path.
                        let across = ahead.cross(&Vector3::z());
                        if *pitch_deg != 0.0 && across.norm() > 1.0e-12 {
                            let axis = nalgebra::Unit::new_normalize(across);
                            ahead = UnitQuaternion::from_axis_angle(&axis, pitch_deg.to_radians())
                                * ahead;
                        }
                        look_at(eye, eye + ahead, Vector3::z())
                    }
                };
                // The sweep turns the view about the vertical through the eye. Guard:
                // the period is validated positive; a zero one would pan not at all.
                let pan = if *pan_period_s > 0.0 {
                    pan_amplitude_deg.to_radians()
                        * (std::f64::consts::TAU * t_s / pan_period_s + pan_phase_deg.to_radians())
                            .sin()
                } else {
                    0.0
                };
                let nominal = Pose::from_parts(
                    nominal.translation,
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), pan) * nominal.rotation,
                );
                let dp = jitter(*seed, 0, t_s) * *jitter_position_m;
                let dr = jitter(*seed, 3, t_s) * jitter_rotation_deg.to_radians();
                let mut pose = nominal * UnitQuaternion::from_scaled_axis(dr);
                pose.translation.vector += dp;
                pose
            }
        }
    }
}

/// The point `s` metres along the polyline (clamped to its ends).
fn point_along(waypoints: &[Point3<f64>], s: f64) -> Point3<f64> {
    let Some(first) = waypoints.first() else {
        return Point3::origin();
    };
    if s.is_nan() || s <= 0.0 {
        return *first;
    }
    let mut left = s;
    for w in waypoints.windows(2) {
        let seg = w[1] - w[0];
        let len = seg.norm();
        if left <= len && len > 0.0 {
            return w[0] + seg * (left / len);
        }
        left -= len;
    }
    *waypoints.last().unwrap_or(first)
}

/// Total length of a polyline in metres.
pub fn path_length(waypoints: &[Point3<f64>]) -> f64 {
    waypoints.windows(2).map(|w| (w[1] - w[0]).norm()).sum()
}

/// A smooth zero-mean random 3-vector of unit standard deviation per axis.
fn jitter(seed: u64, axis_base: u64, t_s: f64) -> Vector3<f64> {
    let mut out = Vector3::zeros();
    for axis in 0..3 {
        let rng = PixelRng::new(seed, 0, axis_base + axis as u64, Stream::Trajectory);
        let mut v = 0.0;
        for k in 0..3 {
            let freq_hz = 0.3 + 1.7 * rng.uniform(2 * k);
            let phase = std::f64::consts::TAU * rng.uniform(2 * k + 1);
            v += (std::f64::consts::TAU * freq_hz * t_s + phase).sin();
        }
        // Three unit sinusoids have variance 3/2: scale to unit standard deviation.
        out[axis] = v / 1.5f64.sqrt();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_puts_the_target_on_the_optical_axis() {
        let eye = Point3::new(1.0, 2.0, 1.5);
        let target = Point3::new(-2.0, 0.5, 0.3);
        let pose = look_at(eye, target, Vector3::z());
        let in_eo = pose.inverse_transform_point(&target);
        assert!(in_eo.x.abs() < 1e-12 && in_eo.y.abs() < 1e-12 && in_eo.z > 0.0);
        // A point above the target appears higher in the image (smaller y).
        let above = pose.inverse_transform_point(&(target + Vector3::z()));
        assert!(above.y < 0.0);
        // Looking straight down does not fail.
        let down = look_at(eye, eye - Vector3::z(), Vector3::z());
        assert!(down.rotation.quaternion().norm().is_finite());
    }

    #[test]
    fn orbit_frames_lie_on_the_circle_and_timestamps_follow_the_rate() {
        let t = Trajectory {
            path: Path::Orbit {
                center: Point3::new(0.0, 0.0, 1.0),
                radius_m: 3.0,
                height_m: 0.5,
                look_at: Point3::new(0.0, 0.0, 1.0),
                start_deg: 0.0,
                arc_deg: 360.0,
                period_frames: 8,
            },
            rate_hz: 10.0,
            frames: 8,
            start_time_ns: 5,
        };
        for i in 0..8 {
            let p = t.frame_pose(i).translation.vector;
            assert!(((p.x * p.x + p.y * p.y).sqrt() - 3.0).abs() < 1e-12);
            assert!((p.z - 1.5).abs() < 1e-12);
        }
        assert_eq!(t.timestamp_ns(3), 300_000_005);
    }

    #[test]
    fn handheld_jitter_is_smooth_and_seeded() {
        let make = |seed| Trajectory {
            path: Path::Handheld {
                waypoints: vec![Point3::origin(), Point3::new(4.0, 0.0, 0.0)],
                look_at: None,
                speed_m_per_s: 1.0,
                jitter_position_m: 0.01,
                jitter_rotation_deg: 0.5,
                seed,
                pan_amplitude_deg: 0.0,
                pan_period_s: 1.0,
                pan_phase_deg: 0.0,
                pitch_deg: 0.0,
            },
            rate_hz: 10.0,
            frames: 40,
            start_time_ns: 0,
        };
        let a = make(1);
        let (da, dt) = texel::pose::pose_difference(&a.pose_at(1.0), &a.pose_at(1.001));
        assert!(da < 1e-3 && dt < 2e-3, "{da} {dt}");
        assert_ne!(a.pose_at(1.0), make(2).pose_at(1.0));
        assert_eq!(a.pose_at(1.0), make(1).pose_at(1.0));
    }

    #[test]
    fn a_pan_sweeps_the_view_about_the_vertical_and_keeps_the_eye() {
        let make = |amplitude| Trajectory {
            path: Path::Handheld {
                waypoints: vec![Point3::origin(), Point3::new(40.0, 0.0, 0.0)],
                look_at: None,
                speed_m_per_s: 1.0,
                jitter_position_m: 0.0,
                jitter_rotation_deg: 0.0,
                seed: 0,
                pan_amplitude_deg: amplitude,
                pan_period_s: 8.0,
                pan_phase_deg: 0.0,
                pitch_deg: 0.0,
            },
            rate_hz: 10.0,
            frames: 40,
            start_time_ns: 0,
        };
        let (still, panned) = (make(0.0), make(30.0));
        // A quarter period in: the full amplitude, about +z, the eye unmoved.
        let (a, b) = (still.pose_at(2.0), panned.pose_at(2.0));
        assert!((a.translation.vector - b.translation.vector).norm() < 1e-12);
        let forward = |p: &Pose| p.rotation * Vector3::z();
        let (fa, fb) = (forward(&a), forward(&b));
        assert!(fa.z.abs() < 1e-12 && fb.z.abs() < 1e-12);
        let yaw = fa.y.atan2(fa.x) - fb.y.atan2(fb.x);
        assert!(
            (yaw.abs().to_degrees() - 30.0).abs() < 1e-9,
            "{}",
            yaw.to_degrees()
        );
        // Half a period in: back on the path.
        let (fa, fb) = (forward(&still.pose_at(4.0)), forward(&panned.pose_at(4.0)));
        assert!((fa - fb).norm() < 1e-9);
    }

    #[test]
    fn a_pitch_tilts_the_view_off_the_path() {
        let walk = Trajectory {
            path: Path::Handheld {
                waypoints: vec![Point3::origin(), Point3::new(0.0, 10.0, 0.0)],
                look_at: None,
                speed_m_per_s: 1.0,
                jitter_position_m: 0.0,
                jitter_rotation_deg: 0.0,
                seed: 0,
                pan_amplitude_deg: 0.0,
                pan_period_s: 1.0,
                pan_phase_deg: 0.0,
                pitch_deg: -65.0,
            },
            rate_hz: 10.0,
            frames: 40,
            start_time_ns: 0,
        };
        let forward = walk.pose_at(3.0).rotation * Vector3::z();
        let down = 65.0f64.to_radians();
        assert!((forward - Vector3::new(0.0, down.cos(), -down.sin())).norm() < 1e-9);
    }
}
