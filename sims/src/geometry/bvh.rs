//! A bounding-volume hierarchy over the scene's primitives: binned surface-area
//! heuristic build, depth-first flat layout, closest-hit and any-hit traversal.
//! Unbounded primitives (infinite planes) are kept beside the tree and tested always.

use super::{Aabb, Hit, Primitive, Ray};

/// Leaves hold at most this many primitives.
const MAX_LEAF: usize = 4;
/// SAH bins per axis.
const BINS: usize = 16;
/// The build never recurses deeper than this (the traversal stack has room for it).
const MAX_DEPTH: usize = 60;
const STACK: usize = MAX_DEPTH + 4;

#[derive(Debug, Clone, Copy)]
struct Node {
    bounds: Aabb,
    /// Leaf: first primitive index; interior: index of the second child (the first
    /// child follows the node).
    first_or_right: u32,
    /// Number of primitives in a leaf, 0 for an interior node.
    count: u32,
    axis: u8,
}

/// A primitive a cone of rays may meet ([`Bvh::cone_candidates`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    /// Index as [`Bvh::closest_among`] takes it.
    pub index: u32,
    /// Position in the traversal's order (breaks ties in distance).
    pub order: u32,
    /// No ray of the cone meets the primitive nearer than this, metres.
    pub near_m: f64,
}

/// The scene's primitives and the tree over them.
#[derive(Debug, Clone)]
pub struct Bvh {
    nodes: Vec<Node>,
    /// Bounded primitives in leaf order.
    primitives: Vec<Primitive>,
    /// Unbounded primitives, tested for every ray.
    unbounded: Vec<Primitive>,
}

struct BuildItem {
    bounds: Aabb,
    centroid: [f64; 3],
    primitive: Primitive,
}

impl Bvh {
    pub fn new(primitives: Vec<Primitive>) -> Self {
        let mut items = Vec::with_capacity(primitives.len());
        let mut unbounded = Vec::new();
        for p in primitives {
            match p.bounds() {
                Some(b) => items.push(BuildItem {
                    centroid: [b.centroid(0), b.centroid(1), b.centroid(2)],
                    bounds: b,
                    primitive: p,
                }),
                None => unbounded.push(p),
            }
        }
        let mut nodes = Vec::with_capacity(2 * items.len() / MAX_LEAF + 1);
        if !items.is_empty() {
            let len = items.len();
            build(&mut items, 0, len, 0, &mut nodes);
        }
        Self {
            nodes,
            primitives: items.into_iter().map(|i| i.primitive).collect(),
            unbounded,
        }
    }

    /// The primitive at `index` as [`Self::closest_among`] and [`Self::overlapping`]
    /// number them.
    pub fn primitive(&self, index: u32) -> Option<&Primitive> {
        let i = index as usize;
        match i.checked_sub(self.primitives.len()) {
            None => self.primitives.get(i),
            Some(j) => self.unbounded.get(j),
        }
    }

    pub fn primitive_count(&self) -> usize {
        self.primitives.len() + self.unbounded.len()
    }

    /// Every primitive, bounded ones first (in no particular order).
    pub fn primitives(&self) -> impl Iterator<Item = &Primitive> {
        self.primitives.iter().chain(&self.unbounded)
    }

    /// The scene's bounded extent (`None` when only unbounded primitives exist).
    pub fn bounds(&self) -> Option<Aabb> {
        self.nodes.first().map(|n| n.bounds)
    }

    /// The closest hit with distance below `t_max`.
    pub fn closest_hit(&self, ray: &Ray, t_max: f64) -> Option<Hit> {
        let mut best: Option<(&Primitive, Option<Hit>)> = None;
        let mut limit = t_max;
        for p in &self.unbounded {
            if let Some((t, hit)) = p.probe(ray, limit) {
                limit = t;
                best = Some((p, hit));
            }
        }
        if !self.nodes.is_empty() {
            let inv = inv_dir(ray);
            let negative = [inv[0] < 0.0, inv[1] < 0.0, inv[2] < 0.0];
            let mut stack = [0u32; STACK];
            let mut top = 1usize;
            while top > 0 {
                top -= 1;
                let node = &self.nodes[stack[top] as usize];
                if slab(&node.bounds, ray, &inv, limit).is_none() {
                    continue;
                }
                if node.count > 0 {
                    let first = node.first_or_right as usize;
                    for p in &self.primitives[first..first + node.count as usize] {
                        if let Some((t, hit)) = p.probe(ray, limit) {
                            limit = t;
                            best = Some((p, hit));
                        }
                    }
                } else {
                    let index = stack[top] + 1;
                    let (near, far) = if negative[node.axis as usize] {
                        (node.first_or_right, index)
                    } else {
                        (index, node.first_or_right)
                    };
                    // Far first on the stack so the near child is popped first.
                    if top + 2 <= STACK {
                        stack[top] = far;
                        stack[top + 1] = near;
                        top += 2;
                    }
                }
            }
        }
        // Details (normal, uv) of a curved winner only now, for it alone; its own
        // nearest hit is the one found, since the traversal's limit only ever
        // excluded farther ones. A flat winner's came with its distance.
        best.and_then(|(p, hit)| hit.or_else(|| p.intersect(ray, f64::INFINITY)))
    }

    /// Every primitive that may meet a ray from `origin` inside the convex cone
    /// `{x : n·(x - origin) >= 0 for every n in planes}` (whose four `edges` span it):
    /// bounded ones whose boxes are not wholly outside one plane, and all unbounded
    /// ones, less those the cone provably misses. Conservative: it never leaves out a
    /// primitive a ray in the cone can hit. Sorted nearest bound first, for
    /// [`Self::closest_among`].
    pub fn cone_candidates(
        &self,
        origin: &nalgebra::Point3<f64>,
        planes: &[nalgebra::Vector3<f64>],
        edges: &[nalgebra::Vector3<f64>; 4],
        out: &mut Vec<Candidate>,
    ) {
        out.clear();
        let bounded = self.primitives.len() as u32;
        let push = |index: u32, p: &Primitive, out: &mut Vec<Candidate>| {
            if p.may_meet_cone(origin, edges) {
                out.push(Candidate {
                    index,
                    order: out.len() as u32,
                    near_m: p.near_bound_in_cone(origin, edges),
                });
            }
        };
        for (i, p) in self.unbounded.iter().enumerate() {
            push(bounded + i as u32, p, out);
        }
        let outside = |b: &Aabb| {
            planes.iter().any(|n| {
                // The box corner farthest along n (the "p-vertex").
                let mut d = 0.0;
                for a in 0..3 {
                    let c = if n[a] >= 0.0 { b.max[a] } else { b.min[a] };
                    d += n[a] * (c - origin[a]);
                }
                d < 0.0
            })
        };
        self.visit_bounded(
            |b| !outside(b),
            |i, p| {
                // A leaf holds several primitives: each box is culled too.
                if !p.bounds().is_some_and(|b| outside(&b)) {
                    push(i, p, out);
                }
            },
        );
        out.sort_by(|a, b| a.near_m.total_cmp(&b.near_m).then(a.order.cmp(&b.order)));
    }

    /// The closest hit among `candidates` (from [`Self::cone_candidates`]): tested
    /// nearest bound first, stopping at the first whose bound lies beyond the closest
    /// hit so far. Ties in distance go to the candidate found first by the traversal,
    /// so the result is the same as testing every candidate in traversal order.
    #[inline]
    pub fn closest_among(&self, ray: &Ray, candidates: &[Candidate]) -> Option<Hit> {
        let bounded = self.primitives.len();
        let mut best: Option<(&Primitive, u32, Option<Hit>)> = None;
        let mut limit = f64::INFINITY;
        for c in candidates {
            if c.near_m > limit {
                break;
            }
            let i = c.index as usize;
            let p = if i < bounded {
                &self.primitives[i]
            } else {
                match self.unbounded.get(i - bounded) {
                    Some(p) => p,
                    None => continue,
                }
            };
            // Up to and including `limit`, to see ties.
            if let Some((t, hit)) = p.probe(ray, limit.next_up())
                && (t < limit || best.is_none_or(|(_, order, _)| c.order < order))
            {
                limit = t;
                best = Some((p, c.order, hit));
            }
        }
        // A curved winner's details are computed once, here; the same arithmetic as
        // its distance, so the same hit.
        best.and_then(|(p, _, hit)| hit.or_else(|| p.intersect(ray, f64::INFINITY)))
    }

    /// Indices (as for [`Self::closest_among`]) of every primitive whose bounds
    /// overlap `region`, and all unbounded ones: the only primitives a segment inside
    /// `region` can meet.
    pub fn overlapping(&self, region: &Aabb, out: &mut Vec<u32>) {
        out.clear();
        let bounded = self.primitives.len() as u32;
        out.extend((0..self.unbounded.len() as u32).map(|i| bounded + i));
        let overlaps =
            |b: &Aabb| (0..3).all(|a| b.min[a] <= region.max[a] && b.max[a] >= region.min[a]);
        self.visit_bounded(overlaps, |i, p| {
            if p.bounds().is_none_or(|b| overlaps(&b)) {
                out.push(i);
            }
        });
    }

    /// Calls `visit` with the index and primitive of every bounded primitive in a leaf
    /// whose path from the root passes `enter` at every node (depth first).
    fn visit_bounded(&self, enter: impl Fn(&Aabb) -> bool, mut visit: impl FnMut(u32, &Primitive)) {
        if self.nodes.is_empty() {
            return;
        }
        let mut stack = [0u32; STACK];
        let mut top = 1usize;
        while top > 0 {
            top -= 1;
            let index = stack[top];
            let Some(node) = self.nodes.get(index as usize) else {
                continue;
            };
            if !enter(&node.bounds) {
                continue;
            }
            if node.count > 0 {
                let first = node.first_or_right;
                for i in first..first + node.count {
                    if let Some(p) = self.primitives.get(i as usize) {
                        visit(i, p);
                    }
                }
            } else if top + 2 <= STACK {
                stack[top] = node.first_or_right;
                stack[top + 1] = index + 1;
                top += 2;
            }
        }
    }

    /// [`Self::any_hit`] among the primitives `candidates` only (from
    /// [`Self::overlapping`]).
    #[inline]
    pub fn any_hit_among(&self, ray: &Ray, t_max: f64, candidates: &[u32]) -> bool {
        let bounded = self.primitives.len();
        candidates.iter().any(|&i| {
            let i = i as usize;
            let p = if i < bounded {
                self.primitives.get(i)
            } else {
                self.unbounded.get(i - bounded)
            };
            p.is_some_and(|p| p.distance(ray, t_max).is_some())
        })
    }

    /// True when anything lies on the ray closer than `t_max` (shadow rays).
    pub fn any_hit(&self, ray: &Ray, t_max: f64) -> bool {
        if self
            .unbounded
            .iter()
            .any(|p| p.distance(ray, t_max).is_some())
        {
            return true;
        }
        if self.nodes.is_empty() {
            return false;
        }
        let inv = inv_dir(ray);
        let mut stack = [0u32; STACK];
        let mut top = 1usize;
        while top > 0 {
            top -= 1;
            let index = stack[top];
            let node = &self.nodes[index as usize];
            if slab(&node.bounds, ray, &inv, t_max).is_none() {
                continue;
            }
            if node.count > 0 {
                let first = node.first_or_right as usize;
                if self.primitives[first..first + node.count as usize]
                    .iter()
                    .any(|p| p.distance(ray, t_max).is_some())
                {
                    return true;
                }
            } else if top + 2 <= STACK {
                stack[top] = node.first_or_right;
                stack[top + 1] = index + 1;
                top += 2;
            }
        }
        false
    }
}

/// `1 / dir` per axis; a zero component gives ±infinity, which the slab test handles
/// (IEEE: the slab is then either everything or nothing).
#[inline]
fn inv_dir(ray: &Ray) -> [f64; 3] {
    [1.0 / ray.dir.x, 1.0 / ray.dir.y, 1.0 / ray.dir.z]
}

/// Entry distance of the ray into the box, if it enters before `t_max`.
#[inline]
fn slab(b: &Aabb, ray: &Ray, inv: &[f64; 3], t_max: f64) -> Option<f64> {
    let mut t0 = 0.0f64;
    let mut t1 = t_max;
    for (a, inv_a) in inv.iter().enumerate() {
        let o = ray.origin[a];
        let mut near = (b.min[a] - o) * inv_a;
        let mut far = (b.max[a] - o) * inv_a;
        if near > far {
            std::mem::swap(&mut near, &mut far);
        }
        // NaN (0 · inf when the origin lies on a slab plane) must not reject: the
        // comparisons below keep the previous bound in that case.
        if near > t0 {
            t0 = near;
        }
        if far < t1 {
            t1 = far;
        }
        if t0 > t1 {
            return None;
        }
    }
    Some(t0)
}

fn bounds_of(items: &[BuildItem]) -> (Aabb, Aabb) {
    let mut b = Aabb::EMPTY;
    let mut c = Aabb::EMPTY;
    for i in items {
        b.grow(&i.bounds);
        for a in 0..3 {
            c.min[a] = c.min[a].min(i.centroid[a]);
            c.max[a] = c.max[a].max(i.centroid[a]);
        }
    }
    (b, c)
}

fn build(items: &mut [BuildItem], start: usize, end: usize, depth: usize, nodes: &mut Vec<Node>) {
    let slice = &mut items[start..end];
    let (bounds, centroids) = bounds_of(slice);
    let node_index = nodes.len();
    nodes.push(Node {
        bounds,
        first_or_right: start as u32,
        count: slice.len() as u32,
        axis: 0,
    });
    if slice.len() <= MAX_LEAF || depth >= MAX_DEPTH {
        return;
    }
    let Some((axis, split)) = best_split(slice, &centroids) else {
        return;
    };
    // Partition by the chosen plane.
    let mut mid = 0;
    for i in 0..slice.len() {
        if slice[i].centroid[axis] < split {
            slice.swap(i, mid);
            mid += 1;
        }
    }
    if mid == 0 || mid == slice.len() {
        // All centroids on one side (coincident centroids): split by count.
        mid = slice.len() / 2;
        slice.sort_by(|a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
    }
    let mid = start + mid;
    build(items, start, mid, depth + 1, nodes);
    let right = nodes.len() as u32;
    build(items, mid, end, depth + 1, nodes);
    nodes[node_index].count = 0;
    nodes[node_index].first_or_right = right;
    nodes[node_index].axis = axis as u8;
}

/// The binned-SAH split `(axis, position)`, or `None` when no split beats a leaf.
fn best_split(items: &[BuildItem], centroids: &Aabb) -> Option<(usize, f64)> {
    let mut best: Option<(f64, usize, f64)> = None;
    for axis in 0..3 {
        let lo = centroids.min[axis];
        let extent = centroids.max[axis] - lo;
        if !(extent > 0.0 && extent.is_finite()) {
            continue;
        }
        let mut bin_bounds = [Aabb::EMPTY; BINS];
        let mut bin_count = [0usize; BINS];
        let scale = BINS as f64 / extent;
        for i in items {
            let b = (((i.centroid[axis] - lo) * scale) as usize).min(BINS - 1);
            bin_bounds[b].grow(&i.bounds);
            bin_count[b] += 1;
        }
        // Sweep from the right to get suffix areas, then from the left.
        let mut right_area = [0.0; BINS];
        let mut right_count = [0usize; BINS];
        let mut acc = Aabb::EMPTY;
        let mut n = 0;
        for b in (1..BINS).rev() {
            acc.grow(&bin_bounds[b]);
            n += bin_count[b];
            right_area[b] = acc.half_area();
            right_count[b] = n;
        }
        let mut acc = Aabb::EMPTY;
        let mut n = 0;
        for b in 0..BINS - 1 {
            acc.grow(&bin_bounds[b]);
            n += bin_count[b];
            let (nl, nr) = (n, right_count[b + 1]);
            if nl == 0 || nr == 0 {
                continue;
            }
            let cost = acc.half_area() * nl as f64 + right_area[b + 1] * nr as f64;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, lo + (b + 1) as f64 / scale));
            }
        }
    }
    best.map(|(_, axis, split)| (axis, split))
}

#[cfg(test)]
mod tests {
    use nalgebra::{Point3, Vector3};

    use super::*;
    use crate::geometry::{Shape, triangle};

    /// A deterministic cloud of small triangles.
    fn soup(n: usize) -> Vec<Primitive> {
        let mut out = Vec::new();
        let mut s = 12345u64;
        let mut next = || {
            s = crate::rng::mix64(s);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        for i in 0..n {
            let c = Point3::new(next() * 10.0 - 5.0, next() * 10.0 - 5.0, next() * 10.0);
            let v = [
                c,
                c + Vector3::new(next() * 0.5, next() * 0.5, next() * 0.5),
                c + Vector3::new(next() * 0.5, next() * 0.5, next() * 0.5),
            ];
            if let Some(t) = triangle(v, [[0.0; 2]; 3], i as u32, 0) {
                out.push(t);
            }
        }
        out
    }

    #[test]
    fn bvh_agrees_with_brute_force() {
        let prims = soup(500);
        let bvh = Bvh::new(prims.clone());
        let mut s = 99u64;
        for _ in 0..2000 {
            s = crate::rng::mix64(s);
            let a = (s % 1000) as f64 / 1000.0;
            s = crate::rng::mix64(s);
            let b = (s % 1000) as f64 / 1000.0;
            let ray = Ray {
                origin: Point3::new(0.0, 0.0, -5.0),
                dir: Vector3::new(a - 0.5, b - 0.5, 1.0).normalize(),
            };
            let brute = prims
                .iter()
                .filter_map(|p| p.intersect(&ray, f64::INFINITY))
                .min_by(|x, y| x.distance_m.total_cmp(&y.distance_m));
            let fast = bvh.closest_hit(&ray, f64::INFINITY);
            assert_eq!(brute.map(|h| h.distance_m), fast.map(|h| h.distance_m));
            assert_eq!(fast.is_some(), bvh.any_hit(&ray, f64::INFINITY));
        }
    }

    #[test]
    fn unbounded_planes_are_tested() {
        let plane = Primitive {
            shape: Shape::InfinitePlane {
                origin: Point3::new(0.0, 0.0, 3.0),
                axis_u: Vector3::x(),
                axis_v: Vector3::y(),
                normal: Vector3::z(),
            },
            object: 0,
            material: 0,
        };
        let bvh = Bvh::new(vec![plane]);
        let ray = Ray {
            origin: Point3::origin(),
            dir: Vector3::z(),
        };
        assert_eq!(
            bvh.closest_hit(&ray, f64::INFINITY).map(|h| h.distance_m),
            Some(3.0)
        );
        assert!(bvh.bounds().is_none());
    }
}
