//! Which acquisition views see which polygons (Debevec, Yu & Borshukov 1998 §5), with
//! partly visible polygons split until each piece is wholly seen or wholly unseen by
//! every view, or is too small to matter.
//!
//! The variant implemented: per view, the whole surface is rendered into a CPU depth
//! map (step 4, depth instead of polygon ids); per polygon and view, sample points on
//! the polygon are projected and compared with the depth map at their pixel and its
//! four neighbours (step 5's neighbourhood), each against the polygon's own plane
//! there: a point just behind an occluder's silhouette counts as hidden even when its
//! own pixel's centre saw past the occluder, and a slanted polygon does not hide
//! itself. Conservative: a view never textures a polygon through an occluder (the
//! paper's Fig. 1); a polygon next to a nearer surface is split and its last pieces
//! left to hole filling. Where the paper then clips a partly
//! visible polygon exactly against the image frame's and each occluder's pyramid
//! (steps 3 and 6), this splits it 1 → 4 at its edge midpoints and tests the pieces
//! again, to a fixed depth and a size threshold. The output stays a triangle mesh,
//! the number of pieces per polygon is bounded (4^depth), and no exact polygon
//! clipping with its numerical corner cases is needed; what is lost is the exact
//! boundary: pieces cut by a boundary at the last level are marked `tiny` and get a
//! colour from their surroundings, as the paper does with polygons under its size
//! threshold. Intersecting polygons (step 2) are not split: the merged surface is
//! one extracted manifold-like mesh.
//!
//! A sampled test can miss an occluder smaller than the spacing of the samples; the
//! samples are spread a few depth-map pixels apart over the polygon's image (up to a
//! bound) so only occluders a few pixels across slip through.
//!
//! Cost: one depth map per view, all kept while polygons are classified (4 bytes a
//! depth-map pixel: a 2048×1536 image at scale 0.5 takes 3 MB a view); rasterising is
//! linear in the pixels the polygons cover; classifying is one projection and five
//! depth-map reads per sample, per polygon and view.

mod depth_map;

use std::collections::HashMap;

use nalgebra::{Point3, Vector2, Vector3};
use texel_surface::SurfaceMesh;

use self::depth_map::ViewDepth;
use crate::view::AcquisitionView;
use crate::view_map::PolygonFrame;

/// Largest depth map accepted, pixels (the project's largest image, 16384², at scale 1).
pub const MAX_DEPTH_MAP_PIXELS: u64 = 16_384 * 16_384;

/// Deepest subdivision accepted: 4^8 = 65,536 pieces from one polygon.
pub const MAX_SUBDIVISION: u8 = 8;

/// Largest depth-map scale accepted: finer than 4 depth pixels per image pixel side
/// resolves nothing the image does not.
const MAX_SCALE: f64 = 4.0;

/// Sample points sit this share of the way from the polygon's corners towards its
/// centroid, so a corner is not tested exactly on the edge its neighbour shares.
const CORNER_PULL: f64 = 0.01;

/// Target spacing of sample points on a polygon's image, depth-map pixels.
const SAMPLE_SPACING_PX: f64 = 4.0;

/// Most segments a polygon edge is sampled with (91 samples): bounds the cost of a
/// polygon that fills the image.
const MAX_SAMPLE_ORDER: usize = 12;

/// Output triangles allowed per input triangle before splitting stops (at least
/// `MIN_SPLIT_BUDGET` in all): bounds the output when most of a large mesh is cut.
const SPLIT_BUDGET_PER_TRIANGLE: usize = 16;
const MIN_SPLIT_BUDGET: usize = 1 << 20;

/// The visibility test's knobs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VisibilityConfig {
    /// Depth-map pixels per image pixel side (0.5: the depth map at half the image's
    /// resolution), in `(0, 4]`.
    pub depth_map_scale: f64,
    /// A point counts as seen when its depth is no more than this beyond the depth
    /// map's: absolute metres plus a share of the depth.
    pub depth_tolerance_m: f64,
    pub depth_tolerance_per_m: f64,
    /// Pixels in from the image border a point must project to count as inside.
    pub border_margin_px: f64,
    /// Subdivision depth for partly visible triangles (each split 1 → 4 at its edge
    /// midpoints), at most [`MAX_SUBDIVISION`].
    pub max_subdivision: u8,
    /// Below this area (m²) a partly visible triangle is not split further: it is
    /// marked `tiny` and gets a colour later (the paper's size threshold).
    pub min_area_m2: f64,
}

impl Default for VisibilityConfig {
    fn default() -> Self {
        Self {
            // Half resolution: a quarter of the pixels to rasterise, and polygons on
            // the merged surface span several image pixels anyway.
            depth_map_scale: 0.5,
            // 2 cm covers the f32 mesh and depth map's rounding and the depth change
            // across a depth-map pixel on a slanted surface; 1 cm a metre grows with
            // the pixel's footprint.
            depth_tolerance_m: 0.02,
            depth_tolerance_per_m: 0.01,
            // One pixel: texture lookups at the very border would read the border's
            // edge (and feathering towards it needs the border inside).
            border_margin_px: 1.0,
            // Three levels: 64 pieces, each an eighth of the polygon's edge.
            max_subdivision: 3,
            // 1 cm²: a piece this small is a few pixels in any view; a flat colour
            // is not noticeable there.
            min_area_m2: 1.0e-4,
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VisibilityError {
    #[error("view {view}: the camera's image is {width}x{height}")]
    EmptyImage { view: u32, width: u32, height: u32 },
    #[error("view {view}: a {width}x{height} depth map exceeds {MAX_DEPTH_MAP_PIXELS} pixels")]
    DepthMapTooLarge { view: u32, width: u64, height: u64 },
    #[error("triangle {triangle} names vertex {vertex} of a mesh with {vertices} vertices")]
    IndexOutOfRange {
        triangle: usize,
        vertex: u32,
        vertices: usize,
    },
    #[error("the mesh has {colours} colours for {positions} vertices")]
    ColourCount { colours: usize, positions: usize },
    #[error("the subdivided mesh would need more than u32 vertex indices")]
    TooManyVertices,
    #[error("visibility config: {0}")]
    Config(&'static str),
}

/// The surface with partly visible polygons subdivided, and who sees what.
#[derive(Debug, Clone, PartialEq)]
pub struct VisibleMesh {
    /// The input mesh, partly visible triangles replaced by their pieces (new
    /// vertices appended, colours interpolated); the input's vertices keep their
    /// indices.
    pub mesh: SurfaceMesh,
    /// Per output triangle: the input triangle it came from (the paper's step 1).
    pub source_triangle: Vec<u32>,
    /// Per output triangle: the ids of the views that see it wholly, ascending.
    pub seen_by: Vec<Vec<u32>>,
    /// Per output triangle: left partly visible to some view at the subdivision
    /// limit or the size threshold.
    pub tiny: Vec<bool>,
}

/// What the visibility step did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct VisibilityStats {
    pub input_triangles: usize,
    pub output_triangles: usize,
    /// Triangles split 1 → 4 (`output = input + 3 × subdivided`).
    pub subdivided: usize,
    pub tiny: usize,
    /// Output triangles of zero area or with a corner not finite (seen by none).
    pub degenerate: usize,
    /// Output triangles seen wholly by 0, 1, 2 and 3 or more views.
    pub seen_by_views: [usize; 4],
    /// Depth-map pixels over all views.
    pub depth_map_pixels: usize,
    /// Sample points tested (each one projection and five depth-map reads).
    pub samples_tested: usize,
    /// Whether splitting stopped at the output budget (pieces left `tiny` early).
    pub split_budget_reached: bool,
}

/// How one view sees one polygon.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Sight {
    Whole,
    Part,
    None,
}

/// Which views see which polygons of `mesh` (§5), partly visible ones subdivided.
pub fn visibility(
    mesh: &SurfaceMesh,
    views: &[AcquisitionView<'_>],
    config: &VisibilityConfig,
) -> Result<(VisibleMesh, VisibilityStats), VisibilityError> {
    validate(config)?;
    let vertices = mesh.positions.len();
    if mesh.colours.len() != vertices {
        return Err(VisibilityError::ColourCount {
            colours: mesh.colours.len(),
            positions: vertices,
        });
    }
    for (triangle, t) in mesh.triangles.iter().enumerate() {
        if let Some(&vertex) = t.iter().find(|&&v| v as usize >= vertices) {
            return Err(VisibilityError::IndexOutOfRange {
                triangle,
                vertex,
                vertices,
            });
        }
    }
    let sizes = views
        .iter()
        .map(|v| depth_map_size(v, config.depth_map_scale))
        .collect::<Result<Vec<_>, _>>()?;

    // Step 4: the original polygons rendered into every view's depth map.
    let corners: Vec<Option<[Point3<f64>; 3]>> =
        mesh.triangles.iter().map(|t| corners_of(mesh, t)).collect();
    let depths: Vec<ViewDepth<'_, '_>> = views
        .iter()
        .zip(&sizes)
        .map(|(v, size)| ViewDepth::render(v, &corners, *size, config.depth_map_scale))
        .collect();

    let mut stats = VisibilityStats {
        input_triangles: mesh.triangles.len(),
        depth_map_pixels: depths.iter().map(ViewDepth::pixels).sum(),
        ..VisibilityStats::default()
    };
    let budget = mesh
        .triangles
        .len()
        .saturating_mul(SPLIT_BUDGET_PER_TRIANGLE)
        .max(MIN_SPLIT_BUDGET);
    let mut out = VisibleMesh {
        mesh: SurfaceMesh {
            origin_m: mesh.origin_m,
            positions: mesh.positions.clone(),
            colours: mesh.colours.clone(),
            triangles: Vec::with_capacity(mesh.triangles.len()),
        },
        source_triangle: Vec::with_capacity(mesh.triangles.len()),
        seen_by: Vec::with_capacity(mesh.triangles.len()),
        tiny: Vec::with_capacity(mesh.triangles.len()),
    };
    // Midpoint vertex of each split edge, shared by the triangles on both sides.
    let mut midpoints: HashMap<(u32, u32), u32> = HashMap::new();
    let mut stack: Vec<([u32; 3], u8)> = Vec::new();
    for (source, &input) in mesh.triangles.iter().enumerate() {
        // Guard: the source id fits u32 whenever the mesh's indices do.
        let source = u32::try_from(source).map_err(|_| VisibilityError::TooManyVertices)?;
        stack.push((input, 0));
        while let Some((tri, level)) = stack.pop() {
            let (seen, partly, degenerate) = match corners_of(&out.mesh, &tri) {
                Some(c) if PolygonFrame::of_triangle(&c[0], &c[1], &c[2]).is_some() => {
                    let (seen, partly) = classify(&c, &depths, config, &mut stats);
                    let area = 0.5 * (c[1] - c[0]).cross(&(c[2] - c[0])).norm();
                    let room = out.mesh.triangles.len() + stack.len() + 4 <= budget;
                    let wants =
                        partly && level < config.max_subdivision && area >= config.min_area_m2;
                    stats.split_budget_reached |= wants && !room;
                    if wants && room {
                        let children = split(&mut out.mesh, &mut midpoints, tri)?;
                        stats.subdivided += 1;
                        // Reversed, so the pieces come out in order.
                        stack.extend(children.iter().rev().map(|c| (*c, level + 1)));
                        continue;
                    }
                    (seen, partly, false)
                }
                _ => (Vec::new(), false, true),
            };
            stats.degenerate += usize::from(degenerate);
            stats.tiny += usize::from(partly);
            stats.seen_by_views[seen.len().min(3)] += 1;
            out.mesh.triangles.push(tri);
            out.source_triangle.push(source);
            out.seen_by.push(seen);
            out.tiny.push(partly);
        }
    }
    stats.output_triangles = out.mesh.triangles.len();
    Ok((out, stats))
}

fn validate(c: &VisibilityConfig) -> Result<(), VisibilityError> {
    let bad = |m| Err(VisibilityError::Config(m));
    if !(c.depth_map_scale > 0.0 && c.depth_map_scale <= MAX_SCALE) {
        return bad("depth_map_scale must be in (0, 4]");
    }
    let finite_non_negative = |x: f64| x.is_finite() && x >= 0.0;
    if !(finite_non_negative(c.depth_tolerance_m) && finite_non_negative(c.depth_tolerance_per_m)) {
        return bad("depth tolerances must be finite and not negative");
    }
    if !finite_non_negative(c.border_margin_px) {
        return bad("border_margin_px must be finite and not negative");
    }
    if c.max_subdivision > MAX_SUBDIVISION {
        return bad("max_subdivision must be at most 8");
    }
    if !finite_non_negative(c.min_area_m2) {
        return bad("min_area_m2 must be finite and not negative");
    }
    Ok(())
}

/// A view's depth-map size, checked against the allocation bound.
fn depth_map_size(
    view: &AcquisitionView<'_>,
    scale: f64,
) -> Result<(usize, usize), VisibilityError> {
    let (w, h) = (view.camera.width, view.camera.height);
    if w == 0 || h == 0 {
        return Err(VisibilityError::EmptyImage {
            view: view.id,
            width: w,
            height: h,
        });
    }
    // The scale is in (0, 4] and the sides are u32: the products are finite and at
    // least 1 after ceil.
    let side = |s: u32| ((f64::from(s) * scale).ceil() as u64).max(1);
    let (mw, mh) = (side(w), side(h));
    if mw.saturating_mul(mh) > MAX_DEPTH_MAP_PIXELS {
        return Err(VisibilityError::DepthMapTooLarge {
            view: view.id,
            width: mw,
            height: mh,
        });
    }
    let too_large = || VisibilityError::DepthMapTooLarge {
        view: view.id,
        width: mw,
        height: mh,
    };
    Ok((
        usize::try_from(mw).map_err(|_| too_large())?,
        usize::try_from(mh).map_err(|_| too_large())?,
    ))
}

/// A triangle's corners in the world; `None` when an index is out of range or a
/// corner is not finite.
pub(crate) fn corners_of(mesh: &SurfaceMesh, t: &[u32; 3]) -> Option<[Point3<f64>; 3]> {
    let mut out = [Point3::origin(); 3];
    for (slot, &v) in out.iter_mut().zip(t) {
        let w = mesh.world(v as usize)?;
        if !w.iter().all(|c| c.is_finite()) {
            return None;
        }
        *slot = Point3::from(w);
    }
    Some(out)
}

/// The views that see the triangle wholly (ascending, without repeats) and whether
/// any view sees it only in part.
fn classify(
    c: &[Point3<f64>; 3],
    depths: &[ViewDepth<'_, '_>],
    config: &VisibilityConfig,
    stats: &mut VisibilityStats,
) -> (Vec<u32>, bool) {
    let normal = (c[1] - c[0]).cross(&(c[2] - c[0]));
    let centroid = Point3::from((c[0].coords + c[1].coords + c[2].coords) / 3.0);
    let mut seen = Vec::new();
    let mut partly = false;
    for d in depths {
        match sight(c, &normal, &centroid, d, config, stats) {
            Sight::Whole => seen.push(d.view.id),
            Sight::Part => partly = true,
            Sight::None => {}
        }
    }
    seen.sort_unstable();
    seen.dedup();
    (seen, partly)
}

/// How one view sees a triangle: a back face (the normal, constant over the plane,
/// pointing away from the centre) is not seen; otherwise the sample points are
/// projected, each seen when inside the image's margin and no farther than the depth
/// map (within tolerance). All seen and the true corners inside: whole; none: not
/// seen; some: in part.
fn sight(
    c: &[Point3<f64>; 3],
    normal: &Vector3<f64>,
    centroid: &Point3<f64>,
    d: &ViewDepth<'_, '_>,
    config: &VisibilityConfig,
    stats: &mut VisibilityStats,
) -> Sight {
    if normal.dot(&(d.centre - centroid)) <= 0.0 {
        return Sight::None;
    }
    let margin = config.border_margin_px;
    let pixels = c.map(|p| d.project(&p));
    // The exact corners decide the image frame: the image of a triangle wholly in
    // front is the triangle of its corners' images (up to lens distortion).
    let corners_inside = pixels
        .iter()
        .all(|p| p.is_some_and(|(px, _)| d.view.inside(&px, margin)));
    // Sample density from the triangle's size in the depth map.
    let order = match pixels {
        [Some((a, _)), Some((b, _)), Some((e, _))] => {
            let longest = (b - a).norm().max((e - b).norm()).max((a - e).norm());
            let segments = (longest * config.depth_map_scale / SAMPLE_SPACING_PX).ceil();
            if segments.is_finite() {
                (segments as usize).clamp(2, MAX_SAMPLE_ORDER)
            } else {
                MAX_SAMPLE_ORDER
            }
        }
        _ => 2,
    };
    let (mut total, mut hits) = (0usize, 0usize);
    let step = 1.0 / order as f64;
    let grid = (0..=order).flat_map(|i| (0..=order - i).map(move |j| (i, j)));
    let points = grid
        .map(|(i, j)| {
            let (u, v) = (i as f64 * step, j as f64 * step);
            let p = c[0].coords * (1.0 - u - v) + c[1].coords * u + c[2].coords * v;
            Point3::from(p + (centroid.coords - p) * CORNER_PULL)
        })
        .chain(std::iter::once(*centroid));
    let gradient = depth_gradient(&pixels);
    for p in points {
        total += 1;
        let seen = d.project(&p).is_some_and(|(pixel, depth)| {
            let tolerance = config.depth_tolerance_m + config.depth_tolerance_per_m * depth;
            d.view.inside(&pixel, margin)
                && d.clear_around(&pixel, depth, gradient, tolerance) == Some(true)
        });
        hits += usize::from(seen);
    }
    stats.samples_tested += total;
    match hits {
        0 => Sight::None,
        h if h == total && corners_inside => Sight::Whole,
        _ => Sight::Part,
    }
}

/// How the triangle's depth changes per image pixel (x, y), from its projected
/// corners (the plane through them; perspective's curvature is negligible over the
/// pixel it is used for). Zero for a triangle edge-on or not wholly in front: then
/// each point is compared at its neighbours with its own depth.
fn depth_gradient(pixels: &[Option<(Vector2<f64>, f64)>; 3]) -> [f64; 2] {
    let [Some((a, za)), Some((b, zb)), Some((c, zc))] = *pixels else {
        return [0.0, 0.0];
    };
    let (u, v) = (b - a, c - a);
    let det = u.x * v.y - u.y * v.x;
    // Guard: an edge-on triangle spans no area in the image.
    if det.abs() < 1e-9 {
        return [0.0, 0.0];
    }
    let (du, dv) = (zb - za, zc - za);
    let g = [(du * v.y - dv * u.y) / det, (dv * u.x - du * v.x) / det];
    if g.iter().all(|x| x.is_finite()) {
        g
    } else {
        [0.0, 0.0]
    }
}

/// Splits a triangle 1 → 4 at its edge midpoints (shared with the neighbour across
/// each edge), returning the four pieces, same winding as the parent.
fn split(
    mesh: &mut SurfaceMesh,
    midpoints: &mut HashMap<(u32, u32), u32>,
    [a, b, c]: [u32; 3],
) -> Result<[[u32; 3]; 4], VisibilityError> {
    let ab = midpoint(mesh, midpoints, a, b)?;
    let bc = midpoint(mesh, midpoints, b, c)?;
    let ca = midpoint(mesh, midpoints, c, a)?;
    Ok([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]])
}

fn midpoint(
    mesh: &mut SurfaceMesh,
    midpoints: &mut HashMap<(u32, u32), u32>,
    a: u32,
    b: u32,
) -> Result<u32, VisibilityError> {
    let key = (a.min(b), a.max(b));
    if let Some(&m) = midpoints.get(&key) {
        return Ok(m);
    }
    let m = u32::try_from(mesh.positions.len()).map_err(|_| VisibilityError::TooManyVertices)?;
    if m == u32::MAX {
        return Err(VisibilityError::TooManyVertices);
    }
    // The indices were checked against the mesh before any split.
    let (Some(pa), Some(pb)) = (
        mesh.positions.get(a as usize),
        mesh.positions.get(b as usize),
    ) else {
        return Err(VisibilityError::TooManyVertices);
    };
    let position = [0, 1, 2].map(|k| ((f64::from(pa[k]) + f64::from(pb[k])) * 0.5) as f32);
    let (ca, cb) = (
        mesh.colours.get(a as usize).copied().unwrap_or_default(),
        mesh.colours.get(b as usize).copied().unwrap_or_default(),
    );
    let colour = [0, 1, 2].map(|k| (u16::from(ca[k]) + u16::from(cb[k])).div_ceil(2) as u8);
    mesh.positions.push(position);
    mesh.colours.push(colour);
    midpoints.insert(key, m);
    Ok(m)
}

#[cfg(test)]
mod tests;
