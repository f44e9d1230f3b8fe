//! Scene geometry in world coordinates (f64): the primitives a scene is made of, their
//! exact ray intersections, and the hit record (distance, point, normal, texture
//! coordinates in metres, object and material ids).

pub mod bvh;
pub mod mesh;
mod near;

use nalgebra::{Point3, Vector3};

pub use bvh::Bvh;

/// Intersections closer than this to the ray origin are ignored (metres), so a
/// shadow ray leaving a surface does not hit that surface again.
pub const MIN_HIT_DISTANCE: f64 = 1.0e-9;

/// A ray in world coordinates; `dir` is a unit vector, so hit distances are metres
/// along the ray (radial ranges).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: Point3<f64>,
    pub dir: Vector3<f64>,
}

impl Ray {
    #[inline]
    pub fn at(&self, t: f64) -> Point3<f64> {
        self.origin + self.dir * t
    }
}

/// The closest intersection of a ray with the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray, metres.
    pub distance_m: f64,
    /// Unit geometric normal as the primitive defines it (not flipped towards the ray).
    pub normal: Vector3<f64>,
    /// Texture coordinates in metres on the surface (see each primitive).
    pub uv_m: [f64; 2],
    /// Index of the scene object (`[[objects]]` order).
    pub object: u32,
    /// Index of the material in the scene's material table.
    pub material: u32,
}

/// Axis-aligned bounding box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl Aabb {
    pub const EMPTY: Self = Self {
        min: [f64::INFINITY; 3],
        max: [f64::NEG_INFINITY; 3],
    };

    pub fn grow_point(&mut self, p: &Point3<f64>) {
        for a in 0..3 {
            self.min[a] = self.min[a].min(p[a]);
            self.max[a] = self.max[a].max(p[a]);
        }
    }

    pub fn grow(&mut self, b: &Aabb) {
        for a in 0..3 {
            self.min[a] = self.min[a].min(b.min[a]);
            self.max[a] = self.max[a].max(b.max[a]);
        }
    }

    pub fn centroid(&self, axis: usize) -> f64 {
        0.5 * (self.min[axis] + self.max[axis])
    }

    /// Half the surface area (the SAH only needs ratios); 0 for an empty box.
    pub fn half_area(&self) -> f64 {
        let d = [0, 1, 2].map(|a| (self.max[a] - self.min[a]).max(0.0));
        d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
    }
}

/// What a primitive is.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    /// A parallelogram `corner + a·edge_u + b·edge_v`, `a, b` in [0, 1]; uv is metres
    /// from its centre along the (unit) edge directions. Planes and box faces.
    Parallelogram {
        corner: Point3<f64>,
        edge_u: Vector3<f64>,
        edge_v: Vector3<f64>,
        normal: Vector3<f64>,
        /// Dual basis: `a = (p - corner)·dual_u`, `b = (p - corner)·dual_v`.
        dual_u: Vector3<f64>,
        dual_v: Vector3<f64>,
        /// `|edge_u|`, `|edge_v|`: metres per unit of `a`, `b` (kept, not recomputed
        /// per hit).
        edge_lengths_m: [f64; 2],
    },
    /// An unbounded plane through `origin`; uv is metres along `axis_u`, `axis_v`.
    InfinitePlane {
        origin: Point3<f64>,
        axis_u: Vector3<f64>,
        axis_v: Vector3<f64>,
        normal: Vector3<f64>,
    },
    /// A sphere; uv is (radius × longitude, radius × polar angle) around `axis_z`.
    Sphere {
        center: Point3<f64>,
        radius: f64,
        axis_x: Vector3<f64>,
        axis_y: Vector3<f64>,
        axis_z: Vector3<f64>,
    },
    /// A capped cylinder around `axis_z` through `center`, from `-half_height` to
    /// `+half_height`; uv on the side is (radius × angle, height), on the caps the
    /// local (x, y).
    Cylinder {
        center: Point3<f64>,
        radius: f64,
        half_height: f64,
        axis_x: Vector3<f64>,
        axis_y: Vector3<f64>,
        axis_z: Vector3<f64>,
    },
    /// A triangle with per-vertex uv (metres or texture units, as the mesh gives).
    Triangle {
        v0: Point3<f64>,
        e1: Vector3<f64>,
        e2: Vector3<f64>,
        normal: Vector3<f64>,
        uv: [[f64; 2]; 3],
    },
}

/// A shape with the ids of what it belongs to.
#[derive(Debug, Clone, PartialEq)]
pub struct Primitive {
    pub shape: Shape,
    pub object: u32,
    pub material: u32,
}

/// Distance and local data of an intersection, before ids are attached.
struct LocalHit {
    t: f64,
    normal: Vector3<f64>,
    uv: [f64; 2],
}

#[inline]
fn in_range(t: f64, t_max: f64) -> bool {
    t > MIN_HIT_DISTANCE && t < t_max
}

/// Whether `num / denom` (`denom` non-zero) is certainly outside the range
/// [`in_range`] accepts, decided without the division: a hit behind the origin
/// (`num / denom <= 0`: the sign alone, exact) or beyond `t_max` by more than rounding
/// can explain (`|num| > |denom| · t_max · (1 + 1e-6)`: the product's rounding is
/// below 1e-15 relative, so the exact quotient exceeds `t_max` and its rounding cannot
/// come back below it). Anything else, NaN included, is left to the division and
/// [`in_range`], so a ray meets exactly what it met before. Most candidates a ray
/// tests lie behind its hit so far: this skips their division, the slowest step.
#[inline]
fn surely_out_of_range(num: f64, denom: f64, t_max: f64) -> bool {
    let (num, denom) = if denom < 0.0 {
        (-num, -denom)
    } else {
        (num, denom)
    };
    num <= 0.0 || num > denom * t_max * (1.0 + 1.0e-6)
}

impl Primitive {
    /// The primitive's bounds; `None` for unbounded shapes.
    pub fn bounds(&self) -> Option<Aabb> {
        let mut b = Aabb::EMPTY;
        match &self.shape {
            Shape::Parallelogram {
                corner,
                edge_u,
                edge_v,
                ..
            } => {
                for p in [
                    *corner,
                    corner + edge_u,
                    corner + edge_v,
                    corner + edge_u + edge_v,
                ] {
                    b.grow_point(&p);
                }
            }
            Shape::InfinitePlane { .. } => return None,
            Shape::Sphere { center, radius, .. } => {
                for a in 0..3 {
                    b.min[a] = center[a] - radius;
                    b.max[a] = center[a] + radius;
                }
            }
            Shape::Cylinder {
                center,
                radius,
                half_height,
                axis_z,
                ..
            } => {
                // Bounds of the two cap discs: per axis, the disc's extent is
                // radius · sqrt(1 - axis_z[a]²).
                for a in 0..3 {
                    let disc = radius * (1.0 - axis_z[a] * axis_z[a]).max(0.0).sqrt();
                    let h = (half_height * axis_z[a]).abs();
                    b.min[a] = center[a] - h - disc;
                    b.max[a] = center[a] + h + disc;
                }
            }
            Shape::Triangle { v0, e1, e2, .. } => {
                b.grow_point(v0);
                b.grow_point(&(v0 + e1));
                b.grow_point(&(v0 + e2));
            }
        }
        // Pad flat boxes so slab tests never divide a zero-width box into NaN.
        for a in 0..3 {
            let pad = 1.0e-9 * (1.0 + b.max[a].abs().max(b.min[a].abs()));
            b.min[a] -= pad;
            b.max[a] += pad;
        }
        Some(b)
    }

    /// False only when no ray from `origin` inside the convex cone spanned by the four
    /// `edges` (in order around it) can meet this primitive. Exact culling for planar
    /// shapes (the cone's cross-section in the plane against the shape), no culling
    /// for the others.
    pub fn may_meet_cone(&self, origin: &Point3<f64>, edges: &[Vector3<f64>; 4]) -> bool {
        let (point, normal) = match &self.shape {
            Shape::Parallelogram { corner, normal, .. } => (corner, normal),
            Shape::InfinitePlane {
                origin: o, normal, ..
            } => (o, normal),
            _ => return true,
        };
        let height = normal.dot(&(point - origin));
        // Distance along each edge to the plane; the cone meets the plane in front
        // only where some edge does (convex combinations of the edges keep the sign).
        let mut ts = [0.0; 4];
        let mut ahead = 0;
        for (t, e) in ts.iter_mut().zip(edges) {
            let denom = normal.dot(e);
            *t = if denom != 0.0 {
                height / denom
            } else {
                f64::INFINITY
            };
            if *t > 0.0 && t.is_finite() {
                ahead += 1;
            }
        }
        if ahead == 0 {
            // No edge meets the plane ahead: only an edge parallel to it leaves doubt.
            return ts.iter().any(|t| t.is_infinite());
        }
        if ahead < 4 {
            return true;
        }
        let Shape::Parallelogram {
            corner,
            dual_u,
            dual_v,
            ..
        } = &self.shape
        else {
            return true;
        };
        // The cone's cross-section: a convex quad; in the parallelogram's (a, b)
        // coordinates the parallelogram is the unit square. Separating axes: the
        // square's two, then the quad's four edge normals.
        let quad: Vec<[f64; 2]> = ts
            .iter()
            .zip(edges)
            .map(|(t, e)| {
                let q = origin + e * *t - corner;
                [q.dot(dual_u), q.dot(dual_v)]
            })
            .collect();
        for axis in 0..2 {
            let (lo, hi) = quad
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), q| {
                    (l.min(q[axis]), h.max(q[axis]))
                });
            if hi < 0.0 || lo > 1.0 {
                return false;
            }
        }
        let square = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        for k in 0..4 {
            let (a, b) = (quad[k], quad[(k + 1) % 4]);
            let n = [-(b[1] - a[1]), b[0] - a[0]];
            let proj = |p: &[f64; 2]| n[0] * p[0] + n[1] * p[1];
            let (ql, qh) = quad
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), q| {
                    (l.min(proj(q)), h.max(proj(q)))
                });
            let (sl, sh) = square
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), q| {
                    (l.min(proj(q)), h.max(proj(q)))
                });
            // A small tolerance keeps grazing contacts (never cull on rounding).
            let tol = 1.0e-9 * (1.0 + ql.abs().max(qh.abs()));
            if sh < ql - tol || sl > qh + tol {
                return false;
            }
        }
        true
    }

    /// The closest intersection with `t` in (`MIN_HIT_DISTANCE`, `t_max`).
    #[inline]
    pub fn intersect(&self, ray: &Ray, t_max: f64) -> Option<Hit> {
        let local = self.intersect_local::<true>(ray, t_max)?;
        Some(Hit {
            distance_m: local.t,
            normal: local.normal,
            uv_m: local.uv,
            object: self.object,
            material: self.material,
        })
    }

    /// Only the distance of [`Self::intersect`]: the traversal's inner loop, which
    /// skips the normal and texture coordinates of hits that may not be the closest.
    #[inline]
    pub fn distance(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        self.intersect_local::<false>(ray, t_max).map(|l| l.t)
    }

    /// The distance of a hit with `t` in (`MIN_HIT_DISTANCE`, `t_max`), and the hit
    /// itself for flat shapes, whose normal and texture coordinates cost next to
    /// nothing once the distance is known (a traversal keeps the winner's instead of
    /// intersecting it again); curved shapes leave them to [`Self::intersect`].
    #[inline]
    pub fn probe(&self, ray: &Ray, t_max: f64) -> Option<(f64, Option<Hit>)> {
        match &self.shape {
            Shape::Parallelogram { .. } | Shape::InfinitePlane { .. } | Shape::Triangle { .. } => {
                self.intersect(ray, t_max).map(|h| (h.distance_m, Some(h)))
            }
            Shape::Sphere { .. } | Shape::Cylinder { .. } => {
                self.distance(ray, t_max).map(|t| (t, None))
            }
        }
    }

    #[inline]
    fn intersect_local<const DETAILS: bool>(&self, ray: &Ray, t_max: f64) -> Option<LocalHit> {
        match &self.shape {
            Shape::Parallelogram {
                corner,
                normal,
                dual_u,
                dual_v,
                edge_lengths_m,
                ..
            } => {
                let denom = normal.dot(&ray.dir);
                let num = normal.dot(&(corner - ray.origin));
                if denom == 0.0 || surely_out_of_range(num, denom, t_max) {
                    return None;
                }
                let t = num / denom;
                if !in_range(t, t_max) {
                    return None;
                }
                let local = ray.at(t) - corner;
                let a = local.dot(dual_u);
                let b = local.dot(dual_v);
                if !(0.0..=1.0).contains(&a) || !(0.0..=1.0).contains(&b) {
                    return None;
                }
                Some(LocalHit {
                    t,
                    normal: *normal,
                    uv: if DETAILS {
                        [(a - 0.5) * edge_lengths_m[0], (b - 0.5) * edge_lengths_m[1]]
                    } else {
                        [0.0; 2]
                    },
                })
            }
            Shape::InfinitePlane {
                origin,
                axis_u,
                axis_v,
                normal,
            } => {
                let denom = normal.dot(&ray.dir);
                let num = normal.dot(&(origin - ray.origin));
                if denom == 0.0 || surely_out_of_range(num, denom, t_max) {
                    return None;
                }
                let t = num / denom;
                if !in_range(t, t_max) {
                    return None;
                }
                let local = ray.at(t) - origin;
                Some(LocalHit {
                    t,
                    normal: *normal,
                    uv: [local.dot(axis_u), local.dot(axis_v)],
                })
            }
            Shape::Sphere {
                center,
                radius,
                axis_x,
                axis_y,
                axis_z,
            } => {
                // |o + t d - c|² = r² with |d| = 1: t² + 2 b t + c = 0. The
                // "b² - c" form with the centre-relative closest approach keeps the
                // discriminant accurate for far spheres.
                let oc = ray.origin - center;
                let b = oc.dot(&ray.dir);
                let closest = oc - ray.dir * b;
                let disc = radius * radius - closest.norm_squared();
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                // Numerically stable roots: q = -b - sign(b) s.
                let q = if b > 0.0 { -b - s } else { -b + s };
                // The second root is NaN where it is certainly out of range (see
                // `surely_out_of_range`): it would fail `in_range` either way.
                let far = oc.norm_squared() - radius * radius;
                let (mut t0, mut t1) = (
                    q,
                    if q == 0.0 {
                        q
                    } else if surely_out_of_range(far, q, t_max) {
                        f64::NAN
                    } else {
                        far / q
                    },
                );
                if t0 > t1 {
                    std::mem::swap(&mut t0, &mut t1);
                }
                let t = if in_range(t0, t_max) {
                    t0
                } else if in_range(t1, t_max) {
                    t1
                } else {
                    return None;
                };
                if !DETAILS {
                    return Some(LocalHit {
                        t,
                        normal: Vector3::zeros(),
                        uv: [0.0; 2],
                    });
                }
                // radius > 0 by construction.
                let n = (ray.at(t) - center) / *radius;
                let (x, y, z) = (n.dot(axis_x), n.dot(axis_y), n.dot(axis_z));
                let longitude = y.atan2(x);
                let polar = z.clamp(-1.0, 1.0).acos();
                Some(LocalHit {
                    t,
                    normal: n,
                    uv: [radius * longitude, radius * polar],
                })
            }
            Shape::Cylinder {
                center,
                radius,
                half_height,
                axis_x,
                axis_y,
                axis_z,
            } => intersect_cylinder::<DETAILS>(
                ray,
                t_max,
                center,
                *radius,
                *half_height,
                [axis_x, axis_y, axis_z],
            ),
            Shape::Triangle {
                v0,
                e1,
                e2,
                normal,
                uv,
            } => {
                // Möller-Trumbore.
                let p = ray.dir.cross(e2);
                let det = e1.dot(&p);
                if det == 0.0 {
                    return None;
                }
                let inv = 1.0 / det;
                let s = ray.origin - v0;
                let b1 = s.dot(&p) * inv;
                if !(0.0..=1.0).contains(&b1) {
                    return None;
                }
                let q = s.cross(e1);
                let b2 = ray.dir.dot(&q) * inv;
                if b2 < 0.0 || b1 + b2 > 1.0 {
                    return None;
                }
                let t = e2.dot(&q) * inv;
                if !in_range(t, t_max) {
                    return None;
                }
                if !DETAILS {
                    return Some(LocalHit {
                        t,
                        normal: Vector3::zeros(),
                        uv: [0.0; 2],
                    });
                }
                let b0 = 1.0 - b1 - b2;
                Some(LocalHit {
                    t,
                    normal: *normal,
                    uv: [
                        b0 * uv[0][0] + b1 * uv[1][0] + b2 * uv[2][0],
                        b0 * uv[0][1] + b1 * uv[1][1] + b2 * uv[2][1],
                    ],
                })
            }
        }
    }
}

fn intersect_cylinder<const DETAILS: bool>(
    ray: &Ray,
    t_max: f64,
    center: &Point3<f64>,
    radius: f64,
    half_height: f64,
    axes: [&Vector3<f64>; 3],
) -> Option<LocalHit> {
    let [ax, ay, az] = axes;
    let oc = ray.origin - center;
    let (ox, oy, oz) = (oc.dot(ax), oc.dot(ay), oc.dot(az));
    let (dx, dy, dz) = (ray.dir.dot(ax), ray.dir.dot(ay), ray.dir.dot(az));
    let mut best: Option<LocalHit> = None;
    let mut limit = t_max;
    // Side: (ox + t dx)² + (oy + t dy)² = r².
    let a = dx * dx + dy * dy;
    if a > 0.0 {
        let b = ox * dx + oy * dy;
        let c = ox * ox + oy * oy - radius * radius;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let s = disc.sqrt();
            let q = if b > 0.0 { -b - s } else { -b + s };
            // A root certainly out of range is NaN rather than divided out: it would
            // fail `in_range` either way, and NaN never wins the ordering below.
            let root = |num: f64, denom: f64| {
                if surely_out_of_range(num, denom, limit) {
                    f64::NAN
                } else {
                    num / denom
                }
            };
            let mut roots = [root(q, a), if q != 0.0 { root(c, q) } else { root(q, a) }];
            if roots[0] > roots[1] {
                roots.swap(0, 1);
            }
            for t in roots {
                if in_range(t, limit) {
                    let z = oz + t * dz;
                    if z.abs() <= half_height {
                        let (x, y) = (ox + t * dx, oy + t * dy);
                        best = Some(if DETAILS {
                            LocalHit {
                                t,
                                normal: (ax * x + ay * y) / radius,
                                uv: [radius * y.atan2(x), z],
                            }
                        } else {
                            LocalHit {
                                t,
                                normal: Vector3::zeros(),
                                uv: [0.0; 2],
                            }
                        });
                        limit = t;
                        break;
                    }
                }
            }
        }
    }
    // Caps: z = ±half_height.
    if dz != 0.0 {
        for sign in [-1.0, 1.0] {
            let num = sign * half_height - oz;
            if surely_out_of_range(num, dz, limit) {
                continue;
            }
            let t = num / dz;
            if in_range(t, limit) {
                let (x, y) = (ox + t * dx, oy + t * dy);
                if x * x + y * y <= radius * radius {
                    best = Some(LocalHit {
                        t,
                        normal: az * sign,
                        uv: [x, y],
                    });
                    limit = t;
                }
            }
        }
    }
    best
}

/// Builds a parallelogram primitive; `None` when the edges are degenerate.
pub fn parallelogram(
    corner: Point3<f64>,
    edge_u: Vector3<f64>,
    edge_v: Vector3<f64>,
    object: u32,
    material: u32,
) -> Option<Primitive> {
    let n = edge_u.cross(&edge_v);
    let area = n.norm();
    if !(area > 0.0 && area.is_finite()) {
        return None;
    }
    let normal = n / area;
    // Dual basis of (edge_u, edge_v) within the plane.
    let dual_u = edge_v.cross(&normal) / area;
    let dual_v = normal.cross(&edge_u) / area;
    Some(Primitive {
        shape: Shape::Parallelogram {
            corner,
            edge_u,
            edge_v,
            normal,
            dual_u,
            dual_v,
            edge_lengths_m: [edge_u.norm(), edge_v.norm()],
        },
        object,
        material,
    })
}

/// Builds a triangle; `None` when it has no area.
pub fn triangle(
    v: [Point3<f64>; 3],
    uv: [[f64; 2]; 3],
    object: u32,
    material: u32,
) -> Option<Primitive> {
    let e1 = v[1] - v[0];
    let e2 = v[2] - v[0];
    let n = e1.cross(&e2);
    let len = n.norm();
    if !(len > 0.0 && len.is_finite()) {
        return None;
    }
    Some(Primitive {
        shape: Shape::Triangle {
            v0: v[0],
            e1,
            e2,
            normal: n / len,
            uv,
        },
        object,
        material,
    })
}

#[cfg(test)]
mod tests;
