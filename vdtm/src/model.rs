//! The merged surface prepared for view-dependent texture mapping, the paper's
//! preprocessing as a recipe: visibility per polygon and view (§5), colours for the
//! polygons no view sees (§6), and a view map for every polygon two or more views see
//! (§7); then, per frame, each polygon's at most three views and weights (§8).

use std::collections::BTreeMap;

use nalgebra::Point3;
use texel_surface::SurfaceMesh;

use crate::hole_fill::{
    HoleFill, HoleFillConfig, HoleFillError, fill_holes, triangle_colours_where,
};
use crate::view::AcquisitionView;
use crate::view_map::{Blend, DEFAULT_SIDE, PolygonFrame, ViewMap, ViewMapError};
use crate::visibility::{
    VisibilityConfig, VisibilityError, VisibilityStats, VisibleMesh, corners_of, visibility,
};

/// The preprocessing's knobs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VdtmConfig {
    pub visibility: VisibilityConfig,
    pub hole_fill: HoleFillConfig,
    /// Grid vertices per side of each polygon's view map.
    pub view_map_side: usize,
}

impl Default for VdtmConfig {
    fn default() -> Self {
        Self {
            visibility: VisibilityConfig::default(),
            hole_fill: HoleFillConfig::default(),
            view_map_side: DEFAULT_SIDE,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum VdtmError {
    #[error("visibility: {0}")]
    Visibility(#[from] VisibilityError),
    #[error("hole filling: {0}")]
    HoleFill(#[from] HoleFillError),
    #[error("view map: {0}")]
    ViewMap(#[from] ViewMapError),
}

/// How one polygon is textured.
#[derive(Debug, Clone, PartialEq)]
pub enum Texturing {
    /// Seen by no view: Gouraud-shaded from its corner colours (§6), drawn first.
    Hole { corners: [[f32; 3]; 3] },
    /// Seen by one view: that view's image alone (§8's separate list).
    Single(u32),
    /// Seen by two or more: its view map.
    Mapped(ViewMap),
}

/// What the preprocessing made.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct VdtmStats {
    pub visibility: VisibilityStats,
    pub holes: usize,
    pub single: usize,
    pub mapped: usize,
    /// Bytes of every view map.
    pub view_map_bytes: usize,
    /// Rounds hole filling took.
    pub fill_rounds: u32,
}

/// The model ready to render.
#[derive(Debug, Clone)]
pub struct VdtmModel {
    /// The surface, partly visible polygons subdivided.
    pub mesh: SurfaceMesh,
    /// Per polygon: the input polygon it came from.
    pub source_triangle: Vec<u32>,
    /// Per polygon: the views that see it wholly, ascending (§5).
    pub seen_by: Vec<Vec<u32>>,
    /// Per polygon: its centroid (world) and local frame (`None` when degenerate).
    pub centroids: Vec<Point3<f64>>,
    pub frames: Vec<Option<PolygonFrame>>,
    pub texturing: Vec<Texturing>,
    pub stats: VdtmStats,
}

impl VdtmModel {
    /// Prepares `mesh` for rendering from `views` (their images colour the holes'
    /// surroundings): the recipe of the three steps below.
    pub fn build(
        mesh: &SurfaceMesh,
        views: &[AcquisitionView<'_>],
        config: &VdtmConfig,
    ) -> Result<Self, VdtmError> {
        // §5: which views see which polygons, partly visible ones subdivided.
        let (visible, visibility_stats) = visibility(mesh, views, &config.visibility)?;
        // §6: colours for the polygons no view sees, from their neighbours'.
        let fill = Self::fill(&visible, views, &config.hole_fill)?;
        // §7: a view map per polygon seen by two or more views.
        Self::assemble(visible, visibility_stats, &fill, views, config)
    }

    /// §6 on visibility's output: the seen polygons' colours, then the holes'.
    pub fn fill(
        visible: &VisibleMesh,
        views: &[AcquisitionView<'_>],
        config: &HoleFillConfig,
    ) -> Result<HoleFill, VdtmError> {
        // Filling reads only the polygons sharing a vertex with a hole: only those
        // sample the images; the other seen ones count as coloured.
        let holes: Vec<bool> = visible.seen_by.iter().map(Vec::is_empty).collect();
        let near = near_holes(&visible.mesh, &holes);
        let wanted = |t: usize| near.get(t).copied().unwrap_or(false);
        let colours =
            triangle_colours_where(&visible.mesh, &visible.seen_by, views, config, &wanted)
                .into_iter()
                .enumerate()
                .map(|(t, c)| match c {
                    None if !wanted(t) && !holes.get(t).copied().unwrap_or(true) => Some([0.0; 3]),
                    c => c,
                })
                .collect::<Vec<_>>();
        Ok(fill_holes(&visible.mesh, &colours, config)?)
    }

    /// §7: per polygon its frame and a hole, one view, or a view map.
    pub fn assemble(
        visible: VisibleMesh,
        visibility_stats: VisibilityStats,
        fill: &HoleFill,
        views: &[AcquisitionView<'_>],
        config: &VdtmConfig,
    ) -> Result<Self, VdtmError> {
        let centre_of: BTreeMap<u32, Point3<f64>> =
            views.iter().map(|v| (v.id, v.centre())).collect();
        let mut stats = VdtmStats {
            visibility: visibility_stats,
            fill_rounds: fill.stats.rounds,
            ..VdtmStats::default()
        };
        let n = visible.mesh.triangle_count();
        let mut centroids = Vec::with_capacity(n);
        let mut frames = Vec::with_capacity(n);
        let mut texturing = Vec::with_capacity(n);
        for (t, seen) in visible.seen_by.iter().enumerate() {
            let corners = visible
                .mesh
                .triangles
                .get(t)
                .and_then(|tri| corners_of(&visible.mesh, tri));
            let centroid = corners.map_or(Point3::origin(), |[a, b, c]| {
                Point3::from((a.coords + b.coords + c.coords) / 3.0)
            });
            let frame = corners.and_then(|[a, b, c]| PolygonFrame::of_triangle(&a, &b, &c));
            let mapped: Vec<(u32, [f64; 2])> = frame
                .map(|f| {
                    seen.iter()
                        .filter_map(|id| Some((*id, f.map_view(&centroid, centre_of.get(id)?)?)))
                        .collect()
                })
                .unwrap_or_default();
            let how = match (mapped.as_slice(), fill.corner_colours.get(t)) {
                ([], corners) => {
                    stats.holes += 1;
                    Texturing::Hole {
                        corners: corners
                            .copied()
                            .flatten()
                            .unwrap_or([config.hole_fill.fallback_colour; 3]),
                    }
                }
                ([(only, _)], _) => {
                    stats.single += 1;
                    Texturing::Single(*only)
                }
                (many, _) => {
                    let map = ViewMap::build(many, config.view_map_side)?;
                    stats.mapped += 1;
                    stats.view_map_bytes += map.heap_bytes();
                    Texturing::Mapped(map)
                }
            };
            centroids.push(centroid);
            frames.push(frame);
            texturing.push(how);
        }
        Ok(Self {
            mesh: visible.mesh,
            source_triangle: visible.source_triangle,
            seen_by: visible.seen_by,
            centroids,
            frames,
            texturing,
            stats,
        })
    }

    /// §8: the views texturing `polygon` for an eye at `eye` and their weights;
    /// `None` for a hole (or a polygon out of range).
    pub fn blend(&self, polygon: usize, eye: &Point3<f64>) -> Option<Blend> {
        match self.texturing.get(polygon)? {
            Texturing::Hole { .. } => None,
            Texturing::Single(view) => Some(Blend::single(*view)),
            Texturing::Mapped(map) => {
                let frame = self.frames.get(polygon).copied().flatten()?;
                let centroid = self.centroids.get(polygon)?;
                // An eye on the centroid has no direction: the normal's stands in.
                let p = frame.map_view(centroid, eye).unwrap_or([0.0, 0.0]);
                Some(map.query(p))
            }
        }
    }
}

/// Per triangle, whether it shares a vertex with a hole (`holes`, per triangle);
/// indices out of range count for nothing.
fn near_holes(mesh: &SurfaceMesh, holes: &[bool]) -> Vec<bool> {
    let mut touched = vec![false; mesh.positions.len()];
    for (t, tri) in mesh.triangles.iter().enumerate() {
        if holes.get(t).copied().unwrap_or(true) {
            for &v in tri {
                if let Some(flag) = touched.get_mut(v as usize) {
                    *flag = true;
                }
            }
        }
    }
    mesh.triangles
        .iter()
        .map(|tri| {
            tri.iter()
                .any(|&v| touched.get(v as usize).copied().unwrap_or(false))
        })
        .collect()
}
