//! Gestures on the canvas as orbit, pan and zoom amounts, gathered between frames
//! and handed to the same [`CameraControls`] the window uses. One finger or the left
//! button orbits; two fingers pan (their midpoint) and zoom (their spread); the right
//! or middle button, or shift with the left, pans. Pure, so it is tested natively.

use crate::app::CameraControls;

/// Movement since the frame loop last took it, in physical pixels and zoom steps.
#[derive(Debug, Default)]
pub struct Gestures {
    pub orbit_px: (f64, f64),
    pub pan_px: (f64, f64),
    pub zoom_steps: f64,
    /// Any input since the last frame (the view changed by hand).
    pub touched: bool,
    /// Pointers down: id, position (CSS px), whether it pans.
    pointers: Vec<(i32, (f64, f64), bool)>,
}

impl Gestures {
    /// Applies and clears what was gathered; `focal_px` scales the pan.
    pub fn apply(&mut self, controls: &mut CameraControls, focal_px: f64) {
        if self.orbit_px != (0.0, 0.0) {
            controls.orbit(self.orbit_px.0, self.orbit_px.1);
        }
        if self.pan_px != (0.0, 0.0) {
            controls.pan(self.pan_px.0, self.pan_px.1, focal_px);
        }
        if self.zoom_steps != 0.0 {
            controls.zoom(self.zoom_steps);
        }
        self.orbit_px = (0.0, 0.0);
        self.pan_px = (0.0, 0.0);
        self.zoom_steps = 0.0;
    }

    pub fn down(&mut self, id: i32, at: (f64, f64), pans: bool) {
        self.pointers.retain(|p| p.0 != id);
        // Two pointers at most take part in a gesture.
        if self.pointers.len() < 2 {
            self.pointers.push((id, at, pans));
        }
    }

    /// Wheel steps (positive: closer).
    pub fn wheel(&mut self, steps: f64) {
        if steps.is_finite() {
            self.zoom_steps += steps;
            self.touched = true;
        }
    }

    pub fn up(&mut self, id: i32) {
        self.pointers.retain(|p| p.0 != id);
    }

    pub fn moved(&mut self, id: i32, at: (f64, f64), dpr: f64) {
        let Some(i) = self.pointers.iter().position(|p| p.0 == id) else {
            return;
        };
        let before = self.pointers.clone();
        self.pointers[i].1 = at;
        self.touched = true;
        match before.as_slice() {
            [(_, last, pans)] => {
                let d = ((at.0 - last.0) * dpr, (at.1 - last.1) * dpr);
                let sum = if *pans {
                    &mut self.pan_px
                } else {
                    &mut self.orbit_px
                };
                sum.0 += d.0;
                sum.1 += d.1;
            }
            [a, b] => {
                let (a1, b1) = (self.pointers[0].1, self.pointers[1].1);
                let mid = |p: (f64, f64), q: (f64, f64)| (0.5 * (p.0 + q.0), 0.5 * (p.1 + q.1));
                let (m0, m1) = (mid(a.1, b.1), mid(a1, b1));
                self.pan_px.0 += (m1.0 - m0.0) * dpr;
                self.pan_px.1 += (m1.1 - m0.1) * dpr;
                let spread = |p: (f64, f64), q: (f64, f64)| (p.0 - q.0).hypot(p.1 - q.1);
                let (s0, s1) = (spread(a.1, b.1), spread(a1, b1));
                // Spreading the fingers zooms in; a pinch of zero width says nothing.
                if s0 > 1.0 && s1 > 1.0 {
                    self.zoom_steps += 4.0 * (s1 / s0).ln();
                }
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_fingers_spreading_zoom_in_and_one_finger_orbits() {
        let mut g = Gestures::default();
        g.down(1, (100.0, 100.0), false);
        g.moved(1, (110.0, 100.0), 2.0);
        assert_eq!(g.orbit_px, (20.0, 0.0));
        g.down(2, (200.0, 100.0), false);
        g.moved(2, (300.0, 100.0), 1.0);
        assert!(g.zoom_steps > 0.0);
        assert!(g.pan_px.0 > 0.0);
    }
}
