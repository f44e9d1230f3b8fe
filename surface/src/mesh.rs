//! The extracted surface as a coloured triangle mesh near an f64 origin, and its
//! simplification to a triangle budget (meshoptimizer's quadric edge collapse).

use meshopt::SimplifyOptions;

/// A coloured triangle mesh: f32 positions as offsets from `origin_m` (world, metres),
/// so precision does not depend on where in the world the mesh is.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceMesh {
    pub origin_m: [f64; 3],
    pub positions: Vec<[f32; 3]>,
    pub colours: Vec<[u8; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

impl SurfaceMesh {
    pub fn empty(origin_m: [f64; 3]) -> Self {
        Self {
            origin_m,
            positions: Vec::new(),
            colours: Vec::new(),
            triangles: Vec::new(),
        }
    }

    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// A vertex in the world.
    pub fn world(&self, vertex: usize) -> Option<[f64; 3]> {
        let p = self.positions.get(vertex)?;
        Some([0, 1, 2].map(|a| self.origin_m[a] + f64::from(p[a])))
    }

    /// Axis-aligned bounds of the positions (offsets from the origin), `None` when the
    /// mesh has no vertex.
    pub fn local_bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        texel::scan::bounds_of(&self.positions)
    }

    /// `count` points spread over the surface by area (systematic sampling of the
    /// triangles' cumulative area, each point a triangle's centroid), world metres:
    /// where the surface is, for judging who saw it. Fewer when the mesh has fewer
    /// triangles with area; none for an empty mesh or one with an index out of range.
    pub fn area_samples(&self, count: usize) -> Vec<[f64; 3]> {
        let n = self.positions.len();
        let corners = |t: &[u32; 3]| -> Option<[[f64; 3]; 3]> {
            let mut c = [[0.0; 3]; 3];
            for (k, &v) in t.iter().enumerate() {
                let p = self
                    .positions
                    .get(v as usize)
                    .filter(|_| (v as usize) < n)?;
                c[k] = p.map(f64::from);
            }
            Some(c)
        };
        let mut areas = Vec::with_capacity(self.triangles.len());
        let mut total = 0.0;
        for t in &self.triangles {
            let area = corners(t).map_or(0.0, |[a, b, c]| {
                let (u, v) = (
                    [0, 1, 2].map(|k| b[k] - a[k]),
                    [0, 1, 2].map(|k| c[k] - a[k]),
                );
                let x = [
                    u[1] * v[2] - u[2] * v[1],
                    u[2] * v[0] - u[0] * v[2],
                    u[0] * v[1] - u[1] * v[0],
                ];
                0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()
            });
            let area = if area.is_finite() { area } else { 0.0 };
            total += area;
            areas.push(area);
        }
        // Guard: no area to spread the points over.
        if count == 0 || total <= 0.0 || total.is_nan() {
            return Vec::new();
        }
        let step = total / count as f64;
        let mut out = Vec::with_capacity(count.min(self.triangles.len()));
        let (mut next, mut below) = (0.5 * step, 0.0);
        let mut last = usize::MAX;
        for (i, (t, area)) in self.triangles.iter().zip(&areas).enumerate() {
            below += area;
            while next < below && out.len() < count {
                next += step;
                // One point per triangle: a large triangle is one place however many
                // points its area draws.
                if i != last {
                    if let Some([a, b, c]) = corners(t) {
                        out.push([0, 1, 2].map(|k| self.origin_m[k] + (a[k] + b[k] + c[k]) / 3.0));
                    }
                    last = i;
                }
            }
        }
        out
    }

    /// Bytes held by the arrays.
    pub fn heap_bytes(&self) -> usize {
        self.positions.len() * 12 + self.colours.len() * 3 + self.triangles.len() * 12
    }

    /// Drops vertices no triangle uses, keeping the order of the rest.
    pub fn compacted(mut self) -> Self {
        let mut remap = vec![u32::MAX; self.positions.len()];
        let mut next = 0u32;
        for tri in &mut self.triangles {
            for v in tri.iter_mut() {
                let slot = &mut remap[*v as usize];
                if *slot == u32::MAX {
                    *slot = next;
                    next += 1;
                }
                *v = *slot;
            }
        }
        let mut positions = vec![[0.0f32; 3]; next as usize];
        let mut colours = vec![[0u8; 3]; next as usize];
        for (old, &new) in remap.iter().enumerate() {
            if new != u32::MAX {
                positions[new as usize] = self.positions[old];
                colours[new as usize] = self.colours[old];
            }
        }
        self.positions = positions;
        self.colours = colours;
        self
    }
}

/// A simplified mesh and the largest distance, in metres, the simplification moved
/// the surface (meshoptimizer's error estimate).
#[derive(Debug, Clone, PartialEq)]
pub struct SimplifyOutcome {
    pub mesh: SurfaceMesh,
    pub error_m: f64,
}

/// Simplifies `mesh` towards `target_triangles`, moving the surface by at most
/// `max_error_m`, whichever stops first. Border vertices stay where they are, so
/// neighbouring tiles simplified apart still meet. A mesh already within the budget
/// comes back unchanged with error 0.
pub fn simplify(mesh: &SurfaceMesh, target_triangles: usize, max_error_m: f64) -> SimplifyOutcome {
    if mesh.triangle_count() <= target_triangles || mesh.positions.is_empty() {
        return SimplifyOutcome {
            mesh: mesh.clone(),
            error_m: 0.0,
        };
    }
    let indices: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
    let mut error = 0.0f32;
    let max_error = if max_error_m.is_finite() {
        max_error_m.max(0.0) as f32
    } else {
        f32::MAX
    };
    let kept = meshopt::simplify_decoder(
        &indices,
        &mesh.positions,
        target_triangles.saturating_mul(3),
        max_error,
        SimplifyOptions::LockBorder | SimplifyOptions::ErrorAbsolute,
        Some(&mut error),
    );
    let simplified = SurfaceMesh {
        origin_m: mesh.origin_m,
        positions: mesh.positions.clone(),
        colours: mesh.colours.clone(),
        triangles: kept.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect(),
    }
    .compacted();
    SimplifyOutcome {
        mesh: simplified,
        error_m: if error.is_finite() {
            f64::from(error.max(0.0))
        } else {
            0.0
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad(origin_m: [f64; 3], side_m: f32) -> SurfaceMesh {
        SurfaceMesh {
            origin_m,
            positions: vec![
                [0.0, 0.0, 0.0],
                [side_m, 0.0, 0.0],
                [side_m, side_m, 0.0],
                [0.0, side_m, 0.0],
            ],
            colours: vec![[0; 3]; 4],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        }
    }

    #[test]
    fn area_samples_lie_on_the_surface_spread_by_area() {
        // A small quad and a large one beside it: the large one gets most points.
        let mut mesh = quad([1000.0, -50.0, 2.0], 1.0);
        let big = quad([0.0; 3], 3.0);
        for p in &big.positions {
            mesh.positions.push([p[0] + 10.0, p[1], p[2]]);
        }
        mesh.colours.extend(&big.colours);
        mesh.triangles
            .extend(big.triangles.iter().map(|t| t.map(|v| v + 4)));
        let samples = mesh.area_samples(20);
        assert_eq!(samples.len(), 4, "one point per triangle at most");
        assert!(samples.iter().all(|p| (p[2] - 2.0).abs() < 1e-9));
        let on_big = samples.iter().filter(|p| p[0] >= 1010.0).count();
        assert_eq!(on_big, 2);
        let few = mesh.area_samples(2);
        assert_eq!(few.len(), 2);
        assert!(
            few.iter().all(|p| p[0] >= 1010.0),
            "the area is on the big quad: {few:?}"
        );
    }

    #[test]
    fn area_samples_of_degenerate_meshes_are_empty() {
        let mut mesh = quad([0.0; 3], 1.0);
        assert!(mesh.area_samples(0).is_empty());
        mesh.positions[2] = [f32::NAN, 0.0, 0.0];
        mesh.triangles.push([0, 1, 9]);
        let samples = mesh.area_samples(8);
        assert!(samples.iter().all(|p| p.iter().all(|c| c.is_finite())));
        assert!(SurfaceMesh::empty([0.0; 3]).area_samples(8).is_empty());
        let flat = SurfaceMesh {
            triangles: vec![[0, 0, 0]],
            ..quad([0.0; 3], 1.0)
        };
        assert!(flat.area_samples(8).is_empty());
    }
}
