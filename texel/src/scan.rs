//! The texel scan: one fused lidar + EO frame as a textured 2.5D triangle mesh with
//! per-triangle normal accuracy and flags (Killpack & Budge 2016, Sec. 3). It is what
//! registration, the model, the stream and the viewer all carry.

use std::sync::Arc;

use crate::frames::EoFrame;
use crate::pose::Pose;
use crate::sensor::RangeNoise;

/// `pixel_vertex` value of a lidar pixel without a vertex.
pub const NO_VERTEX: u32 = u32::MAX;

/// Per-triangle flags.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TriangleFlags(pub u8);

impl TriangleFlags {
    /// The triangle spans a depth discontinuity (see `fuse` for the rule); renderers
    /// drop it by default.
    pub const STRETCHED: u8 = 1;
    /// Collinear or coincident vertices: no normal, accuracy 0.
    pub const DEGENERATE: u8 = 2;

    pub fn is_stretched(self) -> bool {
        self.0 & Self::STRETCHED != 0
    }

    pub fn is_degenerate(self) -> bool {
        self.0 & Self::DEGENERATE != 0
    }

    /// Neither stretched nor degenerate: a triangle worth drawing.
    pub fn is_usable(self) -> bool {
        self.0 == 0
    }
}

/// One texel image.
///
/// Coordinates are in the **scan frame**: the EO camera's optical frame at
/// acquisition (+x right, +y down, +z forward, origin at the EO centre of projection).
/// A scan is placed in the world by `world_from_scan`, which is the frame's
/// `world_from_eo` pose.
#[derive(Debug, Clone, PartialEq)]
pub struct TexelScan {
    pub timestamp_ns: u64,
    pub seq: u32,
    /// The lidar grid the scan was fused from.
    pub grid_width: u32,
    pub grid_height: u32,
    /// One vertex per lidar return, in metres, scan frame (f32 relative to the scan's
    /// own origin, so precision does not depend on where the scan is in the world).
    pub vertices: Vec<[f32; 3]>,
    /// Texture coordinates in [0, 1] (u right, v down; pixel centre `x` maps to
    /// `(x + 0.5) / width`). Meaningful only where `vertex_textured` is true.
    pub tex_coords: Vec<[f32; 2]>,
    /// False for vertices behind the EO camera or outside its image.
    pub vertex_textured: Vec<bool>,
    /// Row-major lidar pixel of each vertex.
    pub vertex_pixel: Vec<u32>,
    /// Vertex of each lidar pixel (row-major), [`NO_VERTEX`] where there is none:
    /// O(1) lookups for projective data association.
    pub pixel_vertex: Vec<u32>,
    /// Vertex indices; for a surface facing the camera the right-handed normal of
    /// `(a, b, c)`, `(b - a) x (c - a)`, points towards the centre of projection.
    pub triangles: Vec<[u32; 3]>,
    /// Normal accuracy in [0, 1]: cosine between the triangle normal and the
    /// direction to the acquisition centre of projection (0 for degenerate ones).
    pub triangle_accuracy: Vec<f32>,
    pub triangle_flags: Vec<TriangleFlags>,
    /// The full-resolution EO image, shared with the frame it came from (never
    /// copied: the recorder may still be writing the same pixels).
    pub texture: Arc<EoFrame>,
    /// The acquisition centre of projection in the scan frame (the EO camera centre).
    pub cop_m: [f64; 3],
    /// The lidar's pose in the scan frame (`eo_from_lidar`).
    pub scan_from_lidar: Pose,
    pub range_noise: RangeNoise,
}

impl TexelScan {
    pub fn vertex_count(&self) -> usize {
        self.vertices.len()
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Triangles neither stretched nor degenerate.
    pub fn usable_triangle_count(&self) -> usize {
        self.triangle_flags.iter().filter(|f| f.is_usable()).count()
    }

    pub fn stretched_count(&self) -> usize {
        self.triangle_flags
            .iter()
            .filter(|f| f.is_stretched())
            .count()
    }

    /// The texture colour at a vertex (nearest pixel), if it is textured.
    pub fn vertex_colour(&self, vertex: usize) -> Option<[u8; 3]> {
        if !*self.vertex_textured.get(vertex)? {
            return None;
        }
        let [u, v] = *self.tex_coords.get(vertex)?;
        let x = (u * self.texture.width as f32 - 0.5).round().max(0.0) as u32;
        let y = (v * self.texture.height as f32 - 0.5).round().max(0.0) as u32;
        self.texture.pixel(
            x.min(self.texture.width.saturating_sub(1)),
            y.min(self.texture.height.saturating_sub(1)),
        )
    }

    /// Axis-aligned bounds of the vertices in the scan frame, `None` for an empty scan.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        bounds_of(&self.vertices)
    }

    /// Bytes held by the scan's arrays and texture (for memory accounting).
    pub fn heap_bytes(&self) -> usize {
        self.vertices.len() * 12
            + self.tex_coords.len() * 8
            + self.vertex_textured.len()
            + self.vertex_pixel.len() * 4
            + self.pixel_vertex.len() * 4
            + self.triangles.len() * 12
            + self.triangle_accuracy.len() * 4
            + self.triangle_flags.len()
            + self.texture.rgb.len()
    }
}

/// Axis-aligned bounds (minimum, maximum) of points, `None` for no point.
pub fn bounds_of(points: &[[f32; 3]]) -> Option<([f32; 3], [f32; 3])> {
    let mut it = points.iter();
    let first = *it.next()?;
    Some(it.fold((first, first), |(mut lo, mut hi), p| {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
        (lo, hi)
    }))
}
