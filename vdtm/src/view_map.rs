//! Per-polygon view maps (Debevec, Yu & Borshukov 1998 §7): the polygon's local frame
//! (Eq. 1), the arc-length mapping of viewing directions into its plane (Eq. 2), a
//! regular grid over that plane whose every vertex holds the nearest acquisition view
//! that sees the polygon, and the query that returns, for any viewing direction, the
//! three views of the grid triangle it falls in with its barycentric coordinates as
//! weights: weights that change smoothly as the viewpoint moves.

use std::f64::consts::FRAC_PI_2;

use nalgebra::{Point3, Vector3};

/// Half the side of a view map's square, radians of arc from the normal: the square
/// holds the disk of every direction in front of the polygon (arc below π/2).
pub const HALF_SIDE_RAD: f64 = FRAC_PI_2;

/// Grid vertices per side of a view map by default: odd, so the normal's direction is
/// a vertex; 9 puts vertices 22.5 degrees of arc apart.
pub const DEFAULT_SIDE: usize = 9;

/// Largest grid side accepted (65,536 vertices a polygon).
pub const MAX_SIDE: usize = 256;

/// Below this length a cross product counts as zero: `y^W` and the normal collinear
/// (Eq. 1's second case), or a direction along the normal (Eq. 2 has no azimuth).
const COLLINEAR: f64 = 1e-9;

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ViewMapError {
    /// No view sees the polygon (or none maps to a finite point): the polygon is a
    /// hole, filled in object space instead (§6).
    #[error("no view sees the polygon: it is a hole, filled in object space")]
    NoViews,
    #[error("a view map side of {0} vertices is outside 2..={MAX_SIDE}")]
    Side(usize),
}

/// A polygon's local coordinate frame (Eq. 1): its unit normal `n`,
/// `x = y^W × n` (normalised) unless `y^W` and `n` are collinear, then `x^W`, and
/// `y = n × x`. Right-handed and orthonormal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolygonFrame {
    pub normal: Vector3<f64>,
    pub x: Vector3<f64>,
    pub y: Vector3<f64>,
}

impl PolygonFrame {
    /// The frame of a normal (any length); `None` for a zero or non-finite one.
    pub fn of_normal(normal: Vector3<f64>) -> Option<Self> {
        let n = normal.try_normalize(1e-300)?;
        if !n.iter().all(|c| c.is_finite()) {
            return None;
        }
        // Eq. 1. In the collinear case x^W is taken orthogonal to n first, so the
        // frame stays orthonormal for a normal within rounding of y^W.
        let x = Vector3::y()
            .cross(&n)
            .try_normalize(COLLINEAR)
            .or_else(|| (Vector3::x() - n * n.x).try_normalize(COLLINEAR))?;
        let y = n.cross(&x);
        Some(Self { normal: n, x, y })
    }

    /// The frame of a triangle (corners counter-clockwise seen from its front); `None`
    /// for a zero-area (degenerate) or non-finite one.
    pub fn of_triangle(a: &Point3<f64>, b: &Point3<f64>, c: &Point3<f64>) -> Option<Self> {
        Self::of_normal((b - a).cross(&(c - a)))
    }

    /// Where the direction from the polygon's `centroid` to a view at `eye` falls in
    /// the view map's plane, radians (Eq. 2): the direction `v` is turned into the
    /// plane, `v_r = (n × v) × n`, scaled to the arc length `acos(n · v)` and projected
    /// on `x` and `y`. Along the normal: the origin; straight behind: `(π, 0)`. `None`
    /// when the eye is on the centroid or not finite.
    pub fn map_view(&self, centroid: &Point3<f64>, eye: &Point3<f64>) -> Option<[f64; 2]> {
        let v = (eye - centroid).try_normalize(1e-12)?;
        if !v.iter().all(|c| c.is_finite()) {
            return None;
        }
        // Guard: rounding can take the cosine just past ±1, where acos is NaN.
        let arc = self.normal.dot(&v).clamp(-1.0, 1.0).acos();
        let turned = self.normal.cross(&v).cross(&self.normal);
        let Some(d) = turned.try_normalize(COLLINEAR) else {
            // No azimuth: the view looks along the normal, from in front or behind.
            return Some([arc, 0.0]);
        };
        Some([arc * d.dot(&self.x), arc * d.dot(&self.y)])
    }
}

/// At most three views and their weights (each in [0, 1], summing to 1), heaviest
/// first (ties to the lower view id).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Blend {
    views: [u32; 3],
    weights: [f64; 3],
    len: usize,
}

impl Blend {
    /// One view, whole (a polygon only that view sees).
    pub fn single(view: u32) -> Self {
        Self {
            views: [view, 0, 0],
            weights: [1.0, 0.0, 0.0],
            len: 1,
        }
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The views and their weights, heaviest first.
    pub fn iter(&self) -> impl Iterator<Item = (u32, f64)> + '_ {
        self.views
            .iter()
            .copied()
            .zip(self.weights.iter().copied())
            .take(self.len)
    }

    /// The weight of one view (0 when it is not in the blend).
    pub fn weight_of(&self, view: u32) -> f64 {
        self.iter()
            .find(|(v, _)| *v == view)
            .map_or(0.0, |(_, w)| w)
    }

    /// Merges the three corners' views (a view at two corners gets both weights),
    /// drops zero weights, renormalises and sorts.
    fn of_corners(corners: [(u32, f64); 3]) -> Self {
        let mut views = [0u32; 3];
        let mut weights = [0.0f64; 3];
        let mut len = 0;
        for (view, weight) in corners {
            // Guard: the barycentric weights are clamped to [0, 1] by construction; a
            // non-finite one (impossible from finite input) counts as nothing.
            let weight = if weight.is_finite() {
                weight.clamp(0.0, 1.0)
            } else {
                0.0
            };
            if weight <= 0.0 {
                continue;
            }
            match views[..len].iter().position(|v| *v == view) {
                Some(k) => weights[k] += weight,
                None => {
                    views[len] = view;
                    weights[len] = weight;
                    len += 1;
                }
            }
        }
        let total: f64 = weights[..len].iter().sum();
        if total > 0.0 {
            for w in &mut weights[..len] {
                *w = (*w / total).clamp(0.0, 1.0);
            }
        }
        // Sort by weight, heaviest first (three entries: a small insertion sort).
        for i in 1..len {
            let mut k = i;
            while k > 0
                && (weights[k] > weights[k - 1]
                    || (weights[k] == weights[k - 1] && views[k] < views[k - 1]))
            {
                weights.swap(k, k - 1);
                views.swap(k, k - 1);
                k -= 1;
            }
        }
        Self {
            views,
            weights,
            len,
        }
    }
}

/// One polygon's view map: a `side × side` grid over `[-π/2, π/2]²` in the arc-length
/// plane, each vertex holding the nearest view (in that plane) among those that see
/// the polygon (Fig. 6).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ViewMap {
    side: usize,
    /// Row-major, `views[j * side + i]` at `(-π/2 + i·step, -π/2 + j·step)`.
    views: Vec<u32>,
}

impl ViewMap {
    /// Regularises the sparse views (`(view id, mapped point)` from
    /// [`PolygonFrame::map_view`], for the views that see the polygon) onto the grid:
    /// each vertex takes the nearest, ties to the lower id. Points not finite are
    /// left out.
    pub fn build(mapped: &[(u32, [f64; 2])], side: usize) -> Result<Self, ViewMapError> {
        if !(2..=MAX_SIDE).contains(&side) {
            return Err(ViewMapError::Side(side));
        }
        let finite: Vec<(u32, [f64; 2])> = mapped
            .iter()
            .copied()
            .filter(|(_, p)| p.iter().all(|c| c.is_finite()))
            .collect();
        if finite.is_empty() {
            return Err(ViewMapError::NoViews);
        }
        let step = grid_step(side);
        let mut views = Vec::with_capacity(side * side);
        for j in 0..side {
            for i in 0..side {
                let at = [
                    -HALF_SIDE_RAD + i as f64 * step,
                    -HALF_SIDE_RAD + j as f64 * step,
                ];
                let nearest = finite
                    .iter()
                    .map(|(view, p)| ((p[0] - at[0]).powi(2) + (p[1] - at[1]).powi(2), *view))
                    .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                // `finite` is not empty, so every vertex has a nearest view.
                views.push(nearest.map_or(finite[0].0, |(_, v)| v));
            }
        }
        Ok(Self { side, views })
    }

    /// Vertices per side.
    pub fn side(&self) -> usize {
        self.side
    }

    /// The view at grid vertex `(i, j)`, when inside the grid.
    pub fn vertex(&self, i: usize, j: usize) -> Option<u32> {
        (i < self.side && j < self.side)
            .then(|| self.views.get(j * self.side + i).copied())
            .flatten()
    }

    /// Bytes the map holds.
    pub fn heap_bytes(&self) -> usize {
        self.views.len() * std::mem::size_of::<u32>()
    }

    /// The views and weights for a viewing direction mapped to `p` (§7): the grid
    /// triangle `p` falls in, its corners' views and `p`'s barycentric coordinates. A
    /// point outside the square (a view from behind the polygon's plane, far round)
    /// is first clamped onto it; a non-finite one counts as the normal's direction.
    pub fn query(&self, p: [f64; 2]) -> Blend {
        let p = if p.iter().all(|c| c.is_finite()) {
            p
        } else {
            [0.0, 0.0]
        };
        let step = grid_step(self.side);
        let last_cell = self.side - 2;
        let cell = |c: f64| -> (usize, f64) {
            let s = (c.clamp(-HALF_SIDE_RAD, HALF_SIDE_RAD) + HALF_SIDE_RAD) / step;
            // Guard: `s` is finite and within [0, side - 1]; the last vertex falls in
            // the last cell with a local coordinate of 1.
            let i = (s.floor().max(0.0) as usize).min(last_cell);
            (i, (s - i as f64).clamp(0.0, 1.0))
        };
        let ((i, u), (j, v)) = (cell(p[0]), cell(p[1]));
        let at = |di: usize, dj: usize| self.views[(j + dj) * self.side + i + di];
        // Each cell is cut along its (1, 0)-(0, 1) diagonal into two triangles.
        let corners = if u + v <= 1.0 {
            [(at(0, 0), 1.0 - u - v), (at(1, 0), u), (at(0, 1), v)]
        } else {
            [
                (at(1, 1), u + v - 1.0),
                (at(0, 1), 1.0 - u),
                (at(1, 0), 1.0 - v),
            ]
        };
        Blend::of_corners(corners)
    }
}

/// Distance between neighbouring grid vertices, radians (`side` at least 2).
fn grid_step(side: usize) -> f64 {
    2.0 * HALF_SIDE_RAD / (side.max(2) - 1) as f64
}

#[cfg(test)]
mod tests;
