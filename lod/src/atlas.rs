//! A tile's texture atlas: every triangle of the tile's simplified mesh laid flat in a
//! rectangle of texels, alone or with the neighbour across its longest edge, the
//! rectangles shelf-packed into one RGB image; each texel coloured from the field
//! level whose voxel is as close to the texel's size as can be without being coarser.
//! A coarse tile's few large triangles so carry the colour of the finer levels, where
//! per-vertex colour would only hold the colour at their corners.
//!
//! The atlas is pure and deterministic: one mesh and one set of fields always give the
//! same bytes.

use texel_surface::{SurfaceMesh, Tsdf};

use crate::codec::MAX_TILE_VERTICES;

mod pack;
use pack::pack_at_fitting_texel;
#[cfg(test)]
use pack::{chart_size, shelf_pack};

/// Largest atlas side a tile may have (and a decoder accepts), texels.
pub const MAX_ATLAS_PX: u32 = 4096;

/// Texels of border round each chart's rectangle. Every texel of a rectangle, border
/// included, is coloured from the nearest point of its own triangles, so bilinear
/// filtering anywhere inside a triangle reads only its own rectangle: one texel is all
/// the reach a bilinear tap has.
pub const GUTTER_PX: u32 = 1;

/// Most steps a texel's colour is searched for along the triangle's normal, each way.
const MAX_SEARCH_STEPS: u32 = 8;

/// A tile's atlas image and where each vertex lies in it.
#[derive(Debug, Clone, PartialEq)]
pub struct TileTexture {
    pub width: u32,
    pub height: u32,
    /// Edge of one texel on the surface, metres.
    pub texel_m: f64,
    /// Row-major RGB, first row at v = 0; sRGB-encoded display values, as the
    /// vertex colours.
    pub rgb: Vec<u8>,
    /// One per vertex of the tile's mesh: texture coordinates in [0, 1]
    /// (texel `(i, j)` covers `[i, i + 1] / width × [j, j + 1] / height`).
    pub uvs: Vec<[f32; 2]>,
}

impl TileTexture {
    /// Bytes held by the image and the coordinates.
    pub fn heap_bytes(&self) -> usize {
        self.rgb.len() + self.uvs.len() * 8
    }
}

/// A chart's rectangle in the atlas, border included, texels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Chart {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

/// What the atlas is built from besides the mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AtlasParams {
    /// The finest texel to try, metres; doubled until the atlas fits.
    pub texel_m: f64,
    /// Largest atlas side, texels.
    pub max_px: u32,
    /// The coarsest field level to take colour from (the tile's own).
    pub lod: u8,
    /// How far off the surface a texel's colour is searched for when no voxel near
    /// the mesh holds one (the mesh's own error), metres.
    pub search_m: f64,
}

/// The mesh as the atlas draws it (its vertices split between charts, so each has
/// one texture coordinate; positions and colours as given; triangles chart by
/// chart), its texture, the charts' rectangles, and the chart of each triangle of
/// the mesh drawn.
#[derive(Debug, Clone, PartialEq)]
pub struct Atlas {
    pub mesh: SurfaceMesh,
    pub texture: TileTexture,
    pub charts: Vec<Chart>,
    pub triangle_charts: Vec<usize>,
}

/// A triangle laid flat: corner `k` of the triangle at `flat[k]` (metres, in the
/// triangle's plane, every coordinate ≥ 0), and the plane's frame in the world.
#[derive(Debug, Clone, Copy)]
struct Flat {
    flat: [[f64; 2]; 3],
    /// Extent along the longest edge and across it, metres.
    size_m: [f64; 2],
    /// The flat origin in the mesh frame and the plane's axes (unit vectors; zero
    /// for a degenerate triangle's missing axis).
    origin: [f64; 3],
    axes: [[f64; 3]; 2],
    normal: [f64; 3],
}

/// The atlas of `mesh` coloured from `fields` (finest first), or `None` when the mesh
/// is empty, has an index out of range, would split into more vertices than a tile
/// may hold, cannot fit `params.max_px` whatever the texel size, or would take its
/// colour from no finer level than `params.lod` (a finest tile's never does).
pub fn build_atlas(mesh: &SurfaceMesh, fields: &[Tsdf], params: &AtlasParams) -> Option<Atlas> {
    let voxels_m: Vec<f64> = fields.iter().map(Tsdf::voxel_m).collect();
    let plan = plan_atlas(mesh, &voxels_m, params)?;
    Some(paint_atlas(plan, mesh, fields, params))
}

/// Where an atlas's charts go and which level colours it, decided from the mesh and
/// the levels' voxel sizes alone: the owner of paged fields brings that level's
/// blocks back before [`paint_atlas`] reads them.
pub struct AtlasPlan {
    plans: Vec<ChartPlan>,
    flats: Vec<Flat>,
    texel_m: f64,
    charts: Vec<Chart>,
    width: u32,
    height: u32,
    /// The field level the texels are coloured from.
    pub level: usize,
}

/// [`build_atlas`]'s first half: `None` in the same cases. `voxels_m` holds each
/// level's voxel size, finest first.
pub fn plan_atlas(mesh: &SurfaceMesh, voxels_m: &[f64], params: &AtlasParams) -> Option<AtlasPlan> {
    let n = mesh.vertex_count();
    if mesh.is_empty()
        || mesh.triangles.iter().flatten().any(|&v| v as usize >= n)
        || mesh.triangle_count().saturating_mul(3) > MAX_TILE_VERTICES as usize
        || params.max_px == 0
        || params.max_px > MAX_ATLAS_PX
        || !(params.texel_m.is_finite() && params.texel_m > 0.0)
    {
        return None;
    }
    let (plans, flats) = plan_charts(mesh);
    let sizes_m: Vec<[f64; 2]> = plans.iter().map(|p| p.size_m).collect();
    let (texel_m, charts, width, height) = pack_at_fitting_texel(&sizes_m, params)?;
    let level = colour_level(voxels_m, params.lod, texel_m);
    if level >= usize::from(params.lod) {
        // Colour no finer than the tile's own level: its vertices, about a voxel of
        // that level apart where it matters, already carry it, at a fraction of the
        // bytes (an atlas splits the vertices between charts).
        return None;
    }
    Some(AtlasPlan {
        plans,
        flats,
        texel_m,
        charts,
        width,
        height,
        level,
    })
}

/// [`build_atlas`]'s second half: every texel of the planned charts coloured from
/// the plan's level of `fields` (from the mesh's vertex colours where that level
/// holds no colour near the texel).
pub fn paint_atlas(
    plan: AtlasPlan,
    mesh: &SurfaceMesh,
    fields: &[Tsdf],
    params: &AtlasParams,
) -> Atlas {
    let AtlasPlan {
        plans,
        flats,
        texel_m,
        charts,
        width,
        height,
        level,
    } = plan;
    let field = fields.get(level);
    let search_m = if params.search_m.is_finite() {
        params.search_m.max(0.0)
    } else {
        0.0
    };
    let mut rgb = vec![0u8; width as usize * height as usize * 3];
    let g = f64::from(GUTTER_PX);
    // width, height ≥ 1: pack_at_fitting_texel never returns an empty atlas.
    let (inv_w, inv_h) = (1.0 / f64::from(width), 1.0 / f64::from(height));
    let mut out = SurfaceMesh::empty(mesh.origin_m);
    let mut uvs = Vec::with_capacity(mesh.triangle_count() * 3);
    let mut triangle_charts = Vec::with_capacity(mesh.triangle_count());
    for (c, (plan, chart)) in plans.iter().zip(&charts).enumerate() {
        // The chart's vertices: each of its triangles' corners once.
        let mut local: Vec<(u32, u32)> = Vec::with_capacity(4);
        for &t in &plan.triangles {
            let tri = mesh.triangles[t];
            let mut corners = [0u32; 3];
            for k in 0..3 {
                let v = tri[k];
                corners[k] = match local.iter().find(|(old, _)| *old == v) {
                    Some(&(_, new)) => new,
                    None => {
                        let new = out.positions.len() as u32;
                        local.push((v, new));
                        out.positions.push(mesh.positions[v as usize]);
                        out.colours
                            .push(mesh.colours.get(v as usize).copied().unwrap_or([0; 3]));
                        let corner = flats[t].flat[k];
                        uvs.push([
                            ((f64::from(chart.x) + g + corner[0] / texel_m) * inv_w) as f32,
                            ((f64::from(chart.y) + g + corner[1] / texel_m) * inv_h) as f32,
                        ]);
                        new
                    }
                };
            }
            out.triangles.push(corners);
            triangle_charts.push(c);
        }
        // A paired chart is split at the shared edge (y = the lower triangle's
        // height): each texel is coloured from the nearest point of its side's
        // triangle, the two agreeing along the edge.
        let hinge_m = match plan.triangles.as_slice() {
            [_, lower] => flats[*lower].flat.iter().map(|c| c[1]).fold(0.0, f64::max),
            _ => f64::NEG_INFINITY,
        };
        for j in 0..chart.height {
            for i in 0..chart.width {
                let texel_centre = [
                    (f64::from(i) + 0.5 - g) * texel_m,
                    (f64::from(j) + 0.5 - g) * texel_m,
                ];
                let t = match plan.triangles.as_slice() {
                    [_, lower] if texel_centre[1] < hinge_m => *lower,
                    [first, ..] => *first,
                    [] => continue,
                };
                let flat = &flats[t];
                let bary = closest_barycentric(&flat.flat, texel_centre);
                // The texel's centre moved onto the triangle, in the world.
                let in_plane =
                    [0, 1].map(|k| (0..3).map(|c| bary[c] * flat.flat[c][k]).sum::<f64>());
                let on = [0, 1, 2].map(|a| {
                    mesh.origin_m[a]
                        + flat.origin[a]
                        + in_plane[0] * flat.axes[0][a]
                        + in_plane[1] * flat.axes[1][a]
                });
                let colour = field
                    .and_then(|f| colour_near(f, on, flat.normal, search_m))
                    .unwrap_or_else(|| {
                        let corner = mesh.triangles[t].map(|v| {
                            mesh.colours
                                .get(v as usize)
                                .map_or([0.0; 3], |c| c.map(f64::from))
                        });
                        [0, 1, 2].map(|c| (0..3).map(|k| bary[k] * corner[k][c]).sum())
                    });
                let at = ((chart.y + j) as usize * width as usize + (chart.x + i) as usize) * 3;
                for (texel, c) in rgb[at..at + 3].iter_mut().zip(colour) {
                    *texel = c.round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
    Atlas {
        mesh: out,
        texture: TileTexture {
            width,
            height,
            texel_m,
            rgb,
            uvs,
        },
        charts,
        triangle_charts,
    }
}

/// The level to colour from: the coarsest whose voxel is no coarser than the texel,
/// and no coarser than the tile's own level (the finest when even that one is).
fn colour_level(voxels_m: &[f64], lod: u8, texel_m: f64) -> usize {
    let last = usize::from(lod).min(voxels_m.len().saturating_sub(1));
    (0..=last)
        .rev()
        .find(|&k| {
            voxels_m
                .get(k)
                .is_some_and(|v| *v <= texel_m * (1.0 + 1e-9))
        })
        .unwrap_or(0)
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `v` scaled to unit length, `None` when it is (nearly) zero or not finite.
fn unit(v: [f64; 3]) -> Option<[f64; 3]> {
    let len = dot(v, v).sqrt();
    (len.is_finite() && len > 1e-12).then(|| v.map(|x| x / len))
}

/// The corner a triangle's longest edge starts at (edge `k` runs from corner `k` to
/// corner `k + 1`).
fn longest_edge(p: [[f32; 3]; 3]) -> usize {
    let p = p.map(|v| v.map(f64::from));
    let edge = |k: usize| sub(p[(k + 1) % 3], p[k]);
    (0..3)
        .max_by(|&a, &b| dot(edge(a), edge(a)).total_cmp(&dot(edge(b), edge(b))))
        .unwrap_or(0)
}

/// Lays a triangle flat with its longest edge along the first axis.
#[cfg(test)]
fn flatten(p: [[f32; 3]; 3]) -> Flat {
    let a = longest_edge(p);
    flatten_on(p, a, (a + 1) % 3, false)
}

/// Lays a triangle flat: corner `a` at the origin, corner `b` on the first axis and
/// the third corner above it (below it when `below`). When `a`–`b` is the longest
/// edge the third corner projects inside it, so `[0, |ab|] × [0, height]` (or
/// `[-height, 0]`) holds the whole triangle.
fn flatten_on(p: [[f32; 3]; 3], a: usize, b: usize, below: bool) -> Flat {
    let p = p.map(|v| v.map(f64::from));
    // Two distinct corners of three (a triangle repeating a vertex may name one
    // twice): anything else lays it from its first edge.
    let (a, b) = if a < 3 && b < 3 && a != b {
        (a, b)
    } else {
        (0, 1)
    };
    let c = 3 - a - b;
    let ab = sub(p[b], p[a]);
    let ac = sub(p[c], p[a]);
    let along = dot(ab, ab).sqrt();
    let along = if along.is_finite() { along } else { 0.0 };
    let normal = unit(cross(sub(p[1], p[0]), sub(p[2], p[0]))).unwrap_or([0.0, 0.0, 1.0]);
    let (x_axis, y_axis, cx, cy) = match unit(ab) {
        Some(x_axis) => {
            let cx = dot(ac, x_axis).clamp(0.0, along);
            let across = sub(ac, x_axis.map(|x| x * cx));
            match unit(across) {
                Some(y_axis) => (x_axis, y_axis, cx, dot(across, y_axis).max(0.0)),
                None => (x_axis, [0.0; 3], cx, 0.0),
            }
        }
        // All three corners (nearly) at one point.
        None => ([0.0; 3], [0.0; 3], 0.0, 0.0),
    };
    let sign = if below { -1.0 } else { 1.0 };
    let mut flat = [[0.0; 2]; 3];
    flat[a] = [0.0, 0.0];
    flat[b] = [along, 0.0];
    flat[c] = [cx, sign * cy];
    Flat {
        size_m: [along, cy],
        flat,
        origin: p[a],
        // Below the edge the flat y runs against the triangle's own across direction.
        axes: [x_axis, y_axis.map(|y| sign * y)],
        normal,
    }
}

/// One chart's triangles (one, or two sharing the longest edge of both, unfolded
/// about it so the edge runs through the chart with no seam) and its extent, metres.
struct ChartPlan {
    triangles: Vec<usize>,
    size_m: [f64; 2],
}

/// The charts and each triangle laid flat in its chart's frame (coordinates ≥ 0).
/// Pairing halves the vertices the shared edge would otherwise take twice, and the
/// gutters between the pair.
fn plan_charts(mesh: &SurfaceMesh) -> (Vec<ChartPlan>, Vec<Flat>) {
    let corners = |t: usize| mesh.triangles[t].map(|v| mesh.positions[v as usize]);
    let key = |a: u32, b: u32| (a.min(b), a.max(b));
    let longest: Vec<usize> = (0..mesh.triangle_count())
        .map(|t| longest_edge(corners(t)))
        .collect();
    let longest_key = |t: usize| {
        let tri = mesh.triangles[t];
        key(tri[longest[t]], tri[(longest[t] + 1) % 3])
    };
    let mut by_edge: std::collections::HashMap<(u32, u32), Vec<usize>> =
        std::collections::HashMap::new();
    for t in 0..mesh.triangle_count() {
        by_edge.entry(longest_key(t)).or_default().push(t);
    }
    let mut paired = vec![false; mesh.triangle_count()];
    let mut plans = Vec::new();
    let mut flats: Vec<Option<Flat>> = vec![None; mesh.triangle_count()];
    for t in 0..mesh.triangle_count() {
        if paired[t] {
            continue;
        }
        paired[t] = true;
        let tri = mesh.triangles[t];
        let a = longest[t];
        let b = (a + 1) % 3;
        let upper = flatten_on(corners(t), a, b, false);
        // Its partner: the other triangle whose longest edge this is too (only on a
        // manifold edge: exactly two triangles on it).
        let partner = by_edge
            .get(&longest_key(t))
            .filter(|ts| ts.len() == 2)
            .and_then(|ts| ts.iter().copied().find(|&u| u != t && !paired[u]));
        let Some(u) = partner else {
            plans.push(ChartPlan {
                triangles: vec![t],
                size_m: upper.size_m,
            });
            flats[t] = Some(upper);
            continue;
        };
        paired[u] = true;
        let other = mesh.triangles[u];
        let find = |v: u32| (0..3).find(|&k| other[k] == v).unwrap_or(0);
        let lower = flatten_on(corners(u), find(tri[a]), find(tri[b]), true);
        // Both in the chart's frame: the shared edge at y = the lower one's height.
        let shift = lower.size_m[1];
        let lift = |mut f: Flat| {
            for c in &mut f.flat {
                c[1] += shift;
            }
            f.origin = sub(f.origin, f.axes[1].map(|y| y * shift));
            f
        };
        plans.push(ChartPlan {
            triangles: vec![t, u],
            size_m: [upper.size_m[0], upper.size_m[1] + shift],
        });
        flats[t] = Some(lift(upper));
        flats[u] = Some(lift(lower));
    }
    let flats = flats
        .into_iter()
        .enumerate()
        .map(|(t, f)| f.unwrap_or_else(|| flatten_on(corners(t), 0, 1, false)))
        .collect();
    (plans, flats)
}

/// Barycentric coordinates of the point of the flat triangle nearest `q`.
fn closest_barycentric(t: &[[f64; 2]; 3], q: [f64; 2]) -> [f64; 3] {
    let bary = barycentric(t, q);
    if let Some(b) = bary
        && b.iter().all(|&x| x >= 0.0)
    {
        return b;
    }
    // Outside (or degenerate): the nearest point of the three edges.
    let mut best = ([1.0, 0.0, 0.0], f64::INFINITY);
    for k in 0..3 {
        let (a, b) = (t[k], t[(k + 1) % 3]);
        let d = [b[0] - a[0], b[1] - a[1]];
        let len2 = d[0] * d[0] + d[1] * d[1];
        let s = if len2 > 1e-24 {
            (((q[0] - a[0]) * d[0] + (q[1] - a[1]) * d[1]) / len2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let p = [a[0] + s * d[0], a[1] + s * d[1]];
        let dist = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2);
        if dist < best.1 {
            let mut w = [0.0; 3];
            w[k] = 1.0 - s;
            w[(k + 1) % 3] = s;
            best = (w, dist);
        }
    }
    best.0
}

/// Barycentric coordinates of `q` in a flat triangle, `None` when it has no area.
fn barycentric(t: &[[f64; 2]; 3], q: [f64; 2]) -> Option<[f64; 3]> {
    let (a, b, c) = (t[0], t[1], t[2]);
    let det = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1]);
    if det.abs() < 1e-18 {
        return None;
    }
    let l0 = ((b[1] - c[1]) * (q[0] - c[0]) + (c[0] - b[0]) * (q[1] - c[1])) / det;
    let l1 = ((c[1] - a[1]) * (q[0] - c[0]) + (a[0] - c[0]) * (q[1] - c[1])) / det;
    Some([l0, l1, 1.0 - l0 - l1])
}

/// The field's colour at `p`, or, where no voxel round it holds colour (the mesh
/// lies off the surface by up to its error), the nearest found stepping a voxel at a
/// time along the normal, either way, within `search_m`.
fn colour_near(field: &Tsdf, p: [f64; 3], normal: [f64; 3], search_m: f64) -> Option<[f64; 3]> {
    if let Some(c) = trilinear_colour(field, p) {
        return Some(c);
    }
    let voxel_m = field.voxel_m();
    // voxel_m > 0 (a field's config is validated); the cast is bounded by the cap.
    let steps = ((search_m / voxel_m).ceil().max(0.0) as u32).min(MAX_SEARCH_STEPS);
    for k in 1..=steps {
        for sign in [1.0, -1.0] {
            let s = sign * f64::from(k) * voxel_m;
            let q = [0, 1, 2].map(|a| p[a] + s * normal[a]);
            if let Some(c) = trilinear_colour(field, q) {
                return Some(c);
            }
        }
    }
    None
}

/// Trilinear interpolation of the colour of the eight voxels round `p`, weighing only
/// those that hold colour (by their trilinear weight); `None` when none does.
fn trilinear_colour(field: &Tsdf, p: [f64; 3]) -> Option<[f64; 3]> {
    let voxel_m = field.voxel_m();
    let origin = field.origin_m();
    // Continuous index relative to voxel centres: voxel i's centre is at i + 0.5.
    let f = [0, 1, 2].map(|a| (p[a] - origin[a]) / voxel_m - 0.5);
    if f.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let base = f.map(|x| x.floor());
    let frac = [0, 1, 2].map(|a| f[a] - base[a]);
    let base = base.map(|x| x as i64);
    let mut sum = [0.0f64; 3];
    let mut weight = 0.0f64;
    for corner in 0..8usize {
        let bit = |a: usize| (corner >> a) & 1;
        let index = [0, 1, 2].map(|a| base[a] + bit(a) as i64);
        let w: f64 = (0..3)
            .map(|a| if bit(a) == 1 { frac[a] } else { 1.0 - frac[a] })
            .product();
        if w <= 0.0 {
            continue;
        }
        let Some(v) = field.voxel(index) else {
            continue;
        };
        if v.colour_weight <= 0.0 {
            continue;
        }
        // colour_weight > 0: checked above.
        for (s, c) in sum.iter_mut().zip(v.colour_sum) {
            *s += w * f64::from(c / v.colour_weight);
        }
        weight += w;
    }
    (weight > 1e-9).then(|| sum.map(|s| s / weight))
}

#[cfg(test)]
mod tests;
