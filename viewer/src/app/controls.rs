//! Camera control for the window: orbit about a pivot in front of the camera, pan,
//! zoom towards the pivot, and fly (keys), all on the f64 pose.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use texel::Pose;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraControls {
    pub world_from_eo: Pose,
    /// Distance from the camera to the orbit pivot along its forward axis, metres.
    pub pivot_distance_m: f64,
}

/// Radians of orbit per pixel of drag.
const ORBIT_RAD_PER_PX: f64 = 0.005;
const MIN_PIVOT_M: f64 = 0.05;

impl CameraControls {
    pub fn new(world_from_eo: Pose, pivot_distance_m: f64) -> Self {
        Self {
            world_from_eo,
            pivot_distance_m: pivot_distance_m.max(MIN_PIVOT_M),
        }
    }

    fn axis(&self, a: Vector3<f64>) -> Vector3<f64> {
        self.world_from_eo.rotation * a
    }

    pub fn pivot(&self) -> Vector3<f64> {
        self.world_from_eo.translation.vector + self.axis(Vector3::z()) * self.pivot_distance_m
    }

    /// Orbits about the pivot: horizontal drag about the camera's y axis, vertical
    /// about its x axis.
    pub fn orbit(&mut self, dx_px: f64, dy_px: f64) {
        let pivot = self.pivot();
        let yaw = UnitQuaternion::from_axis_angle(
            &nalgebra::Unit::new_normalize(self.axis(Vector3::y())),
            -dx_px * ORBIT_RAD_PER_PX,
        );
        let pitch = UnitQuaternion::from_axis_angle(
            &nalgebra::Unit::new_normalize(self.axis(Vector3::x())),
            dy_px * ORBIT_RAD_PER_PX,
        );
        let r = yaw * pitch;
        let rotation = r * self.world_from_eo.rotation;
        let eye = pivot + r * (self.world_from_eo.translation.vector - pivot);
        self.world_from_eo = Pose::from_parts(Translation3::from(eye), rotation);
    }

    /// Moves the camera in its image plane, scaled so the pivot follows the cursor.
    pub fn pan(&mut self, dx_px: f64, dy_px: f64, focal_px: f64) {
        let scale = self.pivot_distance_m / focal_px.max(1.0);
        let shift =
            self.axis(Vector3::x()) * (-dx_px * scale) + self.axis(Vector3::y()) * (-dy_px * scale);
        self.world_from_eo.translation.vector += shift;
    }

    /// Moves towards the pivot by a factor per wheel step.
    pub fn zoom(&mut self, steps: f64) {
        let pivot = self.pivot();
        let new_distance = (self.pivot_distance_m * 0.85f64.powf(steps)).max(MIN_PIVOT_M);
        self.world_from_eo.translation.vector = pivot - self.axis(Vector3::z()) * new_distance;
        self.pivot_distance_m = new_distance;
    }

    /// Flies along the camera's axes (x right, y down, z forward), metres.
    pub fn fly(&mut self, delta_m: Vector3<f64>) {
        self.world_from_eo.translation.vector += self.axis(delta_m);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orbit_keeps_the_pivot_and_zoom_approaches_it() {
        let mut c = CameraControls::new(Pose::translation(5.0e6, 0.0, 0.0), 4.0);
        let pivot = c.pivot();
        c.orbit(120.0, -40.0);
        assert!((c.pivot() - pivot).norm() < 1e-6);
        c.zoom(2.0);
        assert!((c.pivot() - pivot).norm() < 1e-6);
        assert!((c.pivot_distance_m - 4.0 * 0.85 * 0.85).abs() < 1e-9);
        c.pan(10.0, 0.0, 100.0);
        assert!((c.pivot() - pivot).norm() > 0.1);
    }
}
