//! Lower bounds on how near a primitive can be along the rays of a cone: what lets a
//! tile of rays test its candidates nearest first and stop once the closest hit so
//! far is nearer than every candidate left.

use nalgebra::{Point3, Vector3};

use super::{Aabb, Primitive, Shape};

/// Relative and absolute slack taken off every bound, so rounding never makes a bound
/// exceed a true hit distance.
const SLACK_REL: f64 = 1.0e-9;
const SLACK_ABS_M: f64 = 1.0e-9;

impl Aabb {
    /// Euclidean distance from `p` to the box (0 inside it).
    pub fn distance_to(&self, p: &Point3<f64>) -> f64 {
        let mut d2 = 0.0;
        for a in 0..3 {
            let d = (self.min[a] - p[a]).max(p[a] - self.max[a]).max(0.0);
            d2 += d * d;
        }
        d2.sqrt()
    }
}

impl Primitive {
    /// A distance no hit of a ray from `origin` inside the convex cone spanned by the
    /// four `edges` (in order around it) can be nearer than. Bounded shapes: the
    /// distance to their box (sphere: to its surface); planar shapes whose plane every
    /// edge meets ahead: the distance to the cone's cross-section in the plane, a
    /// convex quad. Never above the true nearest hit (it is slackened for rounding);
    /// 0 when nothing better is known.
    pub fn near_bound_in_cone(&self, origin: &Point3<f64>, edges: &[Vector3<f64>; 4]) -> f64 {
        let mut near = self.bounds().map_or(0.0, |b| b.distance_to(origin));
        match &self.shape {
            Shape::Sphere { center, radius, .. } => {
                near = near.max((center - origin).norm() - radius);
            }
            Shape::Parallelogram { corner, normal, .. }
            | Shape::InfinitePlane {
                origin: corner,
                normal,
                ..
            }
            | Shape::Triangle {
                v0: corner, normal, ..
            } => {
                if let Some(d) = cross_section_distance(origin, corner, normal, edges) {
                    near = near.max(d);
                }
                if let Some(d) = plane_distance_along_cone(origin, corner, normal, edges) {
                    near = near.max(d);
                }
            }
            Shape::Cylinder { .. } => {}
        }
        let near = near * (1.0 - SLACK_REL) - SLACK_ABS_M;
        if near.is_finite() { near.max(0.0) } else { 0.0 }
    }
}

/// Distance from `origin` to the part of the plane (through `point`, normal `normal`)
/// inside the cone of `edges`, when every edge meets the plane ahead (the part is then
/// the convex quad of the four meeting points); `None` otherwise.
fn cross_section_distance(
    origin: &Point3<f64>,
    point: &Point3<f64>,
    normal: &Vector3<f64>,
    edges: &[Vector3<f64>; 4],
) -> Option<f64> {
    let height = normal.dot(&(point - origin));
    let mut quad = [Vector3::zeros(); 4];
    for (q, e) in quad.iter_mut().zip(edges) {
        let denom = normal.dot(e);
        if denom == 0.0 {
            return None;
        }
        let t = height / denom;
        if !(t > 0.0 && t.is_finite()) {
            return None;
        }
        // Relative to the origin.
        *q = e * t;
    }
    let n2 = normal.norm_squared();
    if !(n2 > 0.0 && n2.is_finite()) {
        return None;
    }
    // The foot of the perpendicular from the origin; inside the quad, the plane's
    // distance is the answer.
    let foot = normal * (height / n2);
    let side = |k: usize| {
        let (a, b) = (quad[k], quad[(k + 1) % 4]);
        (b - a).cross(&(foot - a)).dot(normal)
    };
    let sides = [side(0), side(1), side(2), side(3)];
    if sides.iter().all(|s| *s >= 0.0) || sides.iter().all(|s| *s <= 0.0) {
        return Some(height.abs() / n2.sqrt());
    }
    // Outside: the nearest point is on the boundary.
    let mut best = f64::INFINITY;
    for k in 0..4 {
        best = best.min(segment_distance(&quad[k], &quad[(k + 1) % 4]));
    }
    best.is_finite().then_some(best)
}

/// A bound on the distance along any ray of the cone to the plane (through `point`,
/// normal `normal`): `|h| / max cos`, with `h` the plane's signed distance and `max cos`
/// the largest cosine between a ray of the cone and the normal turned towards the
/// plane. Holds also where only part of the cone meets the plane.
fn plane_distance_along_cone(
    origin: &Point3<f64>,
    point: &Point3<f64>,
    normal: &Vector3<f64>,
    edges: &[Vector3<f64>; 4],
) -> Option<f64> {
    let len = normal.norm();
    if !(len > 0.0 && len.is_finite()) {
        return None;
    }
    let n = normal / len;
    let height = n.dot(&(point - origin));
    let towards = if height >= 0.0 { n } else { -n };
    // Rounding in the cosine must only ever lower the bound.
    let cos = max_cos_in_cone(&towards, edges)? + 1.0e-7;
    (cos > 0.0).then(|| height.abs() / cos.min(1.0))
}

/// The largest cosine between the unit vector `n` and a direction of the cone spanned
/// by `edges`: 1 when `n` is inside it, else the largest on its four faces (each a
/// great-circle arc between two edges: at `n`'s projection onto the arc's plane when
/// that falls between them, else at an end).
fn max_cos_in_cone(n: &Vector3<f64>, edges: &[Vector3<f64>; 4]) -> Option<f64> {
    let mut unit = [Vector3::zeros(); 4];
    for (u, e) in unit.iter_mut().zip(edges) {
        let len = e.norm();
        if !(len > 0.0 && len.is_finite()) {
            return None;
        }
        *u = e / len;
    }
    let centre = unit.iter().fold(Vector3::zeros(), |a, u| a + u);
    let mut inside = true;
    let mut best = f64::NEG_INFINITY;
    for k in 0..4 {
        let (a, b) = (unit[k], unit[(k + 1) % 4]);
        let mut m = a.cross(&b);
        // The face's normal, turned into the cone.
        if m.dot(&centre) < 0.0 {
            m = -m;
        }
        if m.dot(n) < 0.0 {
            inside = false;
        }
        best = best.max(n.dot(&a)).max(n.dot(&b));
        let m2 = m.norm_squared();
        if m2 > 0.0 {
            let p = n - m * (m.dot(n) / m2);
            // Between a and b on the arc: on the same side of each as the other end.
            let ab = a.cross(&b);
            if a.cross(&p).dot(&ab) >= 0.0 && p.cross(&b).dot(&ab) >= 0.0 {
                best = best.max(p.norm());
            }
        }
    }
    if inside {
        return Some(1.0);
    }
    best.is_finite().then_some(best)
}

/// Distance from the origin to the segment `a`-`b`.
fn segment_distance(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    let ab = b - a;
    let len2 = ab.norm_squared();
    let s = if len2 > 0.0 {
        (-a.dot(&ab) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (a + ab * s).norm()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use proptest::prelude::*;

    use super::*;
    use crate::geometry::{Ray, parallelogram};

    fn unit(v: [f64; 3]) -> Vector3<f64> {
        Vector3::from(v).normalize()
    }

    proptest! {
        /// Every ray of the cone that hits the primitive does so no nearer than the
        /// bound.
        #[test]
        fn no_hit_is_nearer_than_the_bound(
            o in prop::array::uniform3(-2.0f64..2.0),
            centre in prop::array::uniform3(-0.3f64..0.3),
            half in 0.01f64..0.3,
            corner in prop::array::uniform3(-3.0f64..3.0),
            eu in prop::array::uniform3(-2.0f64..2.0),
            ev in prop::array::uniform3(-2.0f64..2.0),
            radius in 0.05f64..1.0,
            weights in prop::collection::vec(prop::array::uniform4(0.0f64..1.0), 32),
        ) {
            let origin = Point3::from(o);
            let axis = unit([centre[0], centre[1], 1.0]);
            // A square cone around `axis`.
            let side = unit([1.0, 0.0, -axis.x / axis.z.max(1e-3)]);
            let up = axis.cross(&side);
            let edges = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
                .map(|(a, b)| axis + side * (a * half) + up * (b * half));
            let mut shapes = Vec::new();
            if let Some(p) = parallelogram(Point3::from(corner), eu.into(), ev.into(), 0, 0) {
                shapes.push(p);
            }
            shapes.push(Primitive {
                shape: Shape::Sphere {
                    center: Point3::from(corner),
                    radius,
                    axis_x: Vector3::x(),
                    axis_y: Vector3::y(),
                    axis_z: Vector3::z(),
                },
                object: 0,
                material: 0,
            });
            for p in &shapes {
                let near = p.near_bound_in_cone(&origin, &edges);
                prop_assert!(near.is_finite() && near >= 0.0);
                for w in &weights {
                    let d = edges[0] * w[0] + edges[1] * w[1] + edges[2] * w[2] + edges[3] * w[3];
                    if d.norm() < 1e-6 {
                        continue;
                    }
                    let ray = Ray { origin, dir: d.normalize() };
                    if let Some(h) = p.intersect(&ray, f64::INFINITY) {
                        prop_assert!(h.distance_m >= near, "hit {} < bound {}", h.distance_m, near);
                    }
                }
            }
        }
    }

    /// A wall straight ahead: the bound is its distance, not 0.
    #[test]
    fn a_wall_ahead_is_bounded_by_its_distance() {
        let wall = parallelogram(
            Point3::new(-5.0, -5.0, 4.0),
            Vector3::new(10.0, 0.0, 0.0),
            Vector3::new(0.0, 10.0, 0.0),
            0,
            0,
        )
        .unwrap();
        let h = 0.05;
        let edges = [(-h, -h), (h, -h), (h, h), (-h, h)].map(|(x, y)| Vector3::new(x, y, 1.0));
        let near = wall.near_bound_in_cone(&Point3::origin(), &edges);
        assert!((near - 4.0).abs() < 1e-6, "{near}");
        // Off to the side, the quad's nearest corner decides.
        let edges =
            [(1.0, 1.0), (1.2, 1.0), (1.2, 1.2), (1.0, 1.2)].map(|(x, y)| Vector3::new(x, y, 1.0));
        let near = wall.near_bound_in_cone(&Point3::origin(), &edges);
        let expected: f64 = 4.0 * Vector3::new(1.0, 1.0, 1.0).norm();
        assert!((near - expected).abs() < 1e-6, "{near} vs {expected}");
    }

    /// A wall behind the cone is no candidate; one ahead is.
    #[test]
    fn a_plane_behind_the_cone_is_culled() {
        let wall = parallelogram(
            Point3::new(-5.0, -5.0, -4.0),
            Vector3::new(10.0, 0.0, 0.0),
            Vector3::new(0.0, 10.0, 0.0),
            0,
            0,
        )
        .unwrap();
        let h = 0.05;
        let ahead = [(-h, -h), (h, -h), (h, h), (-h, h)].map(|(x, y)| Vector3::new(x, y, -1.0));
        let behind = ahead.map(|e| -e);
        assert!(wall.may_meet_cone(&Point3::origin(), &ahead));
        assert!(!wall.may_meet_cone(&Point3::origin(), &behind));
    }
}
