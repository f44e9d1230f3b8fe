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
