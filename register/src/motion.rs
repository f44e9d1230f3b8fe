//! The constant-velocity motion model that gives each scan its initial guess: the
//! last registered motion, in SE(3), scaled to the time since the last scan.

use texel::Pose;

use super::se3;

/// Extrapolate at most this many inter-scan intervals ahead (a long gap says
/// nothing about the velocity now).
const MAX_EXTRAPOLATION: f64 = 3.0;

#[derive(Debug, Clone, Default)]
pub struct MotionModel {
    /// The last two registered `(timestamp_ns, world_from_scan)`, newest last.
    last: Option<(u64, Pose)>,
    previous: Option<(u64, Pose)>,
}

impl MotionModel {
    pub fn new() -> Self {
        Self::default()
    }

    /// Records a registered pose.
    pub fn update(&mut self, timestamp_ns: u64, pose: Pose) {
        match self.last {
            // A scan older than the newest one (a retried scan) does not move the model.
            Some((t, _)) if timestamp_ns <= t => {}
            _ => {
                self.previous = self.last;
                self.last = Some((timestamp_ns, pose));
            }
        }
    }

    /// Replaces the recorded poses after global refinement moved them.
    pub fn revise(&mut self, revise: impl Fn(u64) -> Option<Pose>) {
        for slot in [&mut self.last, &mut self.previous].into_iter().flatten() {
            if let Some(p) = revise(slot.0) {
                slot.1 = p;
            }
        }
    }

    /// Moves the last recorded pose to `last` (global refinement or re-localisation
    /// moved it) and the one before with it, so the velocity stays the measured one: a
    /// correction of the map is not a motion of the camera.
    pub fn rebase(&mut self, last: Pose) {
        if let Some((t1, p1)) = self.last {
            if let Some((t0, p0)) = self.previous {
                self.previous = Some((t0, last * (p1.inverse() * p0)));
            }
            self.last = Some((t1, last));
        }
    }

    /// The timestamp of the last recorded pose.
    pub fn last_timestamp_ns(&self) -> Option<u64> {
        self.last.map(|(t, _)| t)
    }

    /// The predicted pose at `timestamp_ns`: identity before any scan, the last pose
    /// after one, constant velocity after two.
    pub fn predict(&self, timestamp_ns: u64) -> Pose {
        match (self.previous, self.last) {
            (_, None) => Pose::identity(),
            (None, Some((_, last))) => last,
            (Some((t0, p0)), Some((t1, p1))) => {
                let dt_prev = t1.saturating_sub(t0) as f64;
                let dt = timestamp_ns.saturating_sub(t1) as f64;
                if !(dt_prev > 0.0) {
                    return p1;
                }
                let ratio = (dt / dt_prev).min(MAX_EXTRAPOLATION);
                let velocity = se3::log(&(p0.inverse() * p1));
                p1 * se3::exp(&(velocity * ratio))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn constant_motion_is_extrapolated() {
        let mut m = MotionModel::new();
        assert_eq!(m.predict(0), Pose::identity());
        let step = se3::exp(&nalgebra::Vector6::new(0.0, 0.02, 0.0, 0.05, 0.0, 0.01));
        m.update(0, Pose::identity());
        assert_eq!(m.predict(10), Pose::identity());
        m.update(10, step);
        let (a, d) = texel::pose::pose_difference(&m.predict(20), &(step * step));
        assert!(a < 1e-12 && d < 1e-12);
        // Half the interval: half the motion.
        let half = se3::exp(&(se3::log(&step) * 0.5));
        let (a, d) = texel::pose::pose_difference(&m.predict(15), &(step * half));
        assert!(a < 1e-12 && d < 1e-12);
        // A correction of the last pose carries the one before along: same velocity.
        let mut moved = m.clone();
        let shift = Pose::translation(0.3, -0.1, 0.05);
        moved.rebase(shift * step);
        let (a, d) = texel::pose::pose_difference(&moved.predict(20), &(shift * step * step));
        assert!(a < 1e-12 && d < 1e-12);
        // Same timestamp again (identical frames): no extrapolation, no NaN.
        m.update(10, step);
        assert!(se3::is_finite(&m.predict(10)));
    }
}
