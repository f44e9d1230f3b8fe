//! Object-space hole filling (Debevec, Yu & Borshukov 1998 §6): colours for the
//! polygons no acquisition view sees, taken from the surfaces around them, so a hole
//! looks the same from every novel viewpoint.
//!
//! The paper's three steps: (1) polygon connectivity through shared vertices, here
//! one vertex → triangles table in compressed rows (the paper's per-vertex linked
//! lists); (2) an "average" colour for every visible polygon, its centroid projected
//! into each image that sees it and sampled there ([`triangle_colours`]), skipping
//! samples next to occlusion boundaries where a sliver of a foreground edge may have
//! been projected onto the background; (3) rounds in which every hole next to a
//! coloured polygon gives each of its corners the colour of the closest coloured
//! polygon around that corner ([`fill_holes`]). Filled holes are Gouraud shaded
//! from their corner colours.
//!
//! Colours are the sRGB bytes scaled to 0..=1 (`byte / 255`), not converted to
//! linear light: averages and copies stay in the images' own encoding.
//!
//! Determinism: every choice is made on positions and colours, never on the order
//! of triangles or of a hash map; rounds read only what earlier rounds wrote.

use std::cmp::Ordering;
use std::collections::BTreeMap;

use nalgebra::{Point3, Vector2};
use texel::frames::EoFrame;
use texel_surface::SurfaceMesh;

use crate::view::AcquisitionView;

/// Rounds of filling by default: a hole wider than this many rings of triangles
/// around its nearest coloured polygon is not a small hole the paper has in mind, and
/// what remains of it gets the fallback colour.
pub const DEFAULT_MAX_ROUNDS: u32 = 256;

/// The fallback colour by default: mid grey, the least conspicuous guess.
pub const DEFAULT_FALLBACK_COLOUR: [f32; 3] = [0.5, 0.5, 0.5];

/// Hole filling's knobs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HoleFillConfig {
    /// Most rounds of filling; holes not reached by then get `fallback_colour`.
    pub max_rounds: u32,
    /// The colour of triangles no colour reaches (a component no view saw at all).
    pub fallback_colour: [f32; 3],
    /// Skip a view's sample of a triangle next to that view's occlusion boundary
    /// (when another view's sample remains).
    pub occlusion_boundary: bool,
}

impl Default for HoleFillConfig {
    fn default() -> Self {
        Self {
            max_rounds: DEFAULT_MAX_ROUNDS,
            fallback_colour: DEFAULT_FALLBACK_COLOUR,
            occlusion_boundary: true,
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HoleFillError {
    #[error("{colours} colours for {triangles} triangles")]
    ColourCount { colours: usize, triangles: usize },
    #[error("triangle {triangle} names vertex {vertex}, the mesh has {vertices} vertices")]
    VertexIndex {
        triangle: usize,
        vertex: u32,
        vertices: usize,
    },
    #[error("the fallback colour {0:?} is not finite")]
    NonFiniteFallback([f32; 3]),
}

/// What hole filling did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct HoleFillStats {
    /// Triangles with their own colour (textured from the views).
    pub coloured: usize,
    /// Holes filled from their surroundings.
    pub filled: usize,
    /// Rounds that filled at least one hole.
    pub rounds: u32,
    /// Holes given the fallback colour.
    pub fallback: usize,
    /// Whether filling stopped at `max_rounds` with holes still reachable.
    pub hit_round_limit: bool,
}

/// The holes' colours.
#[derive(Debug, Clone, PartialEq)]
pub struct HoleFill {
    /// Per triangle: its three corner colours for Gouraud shading; `None` for
    /// triangles with their own colour (textured from the views).
    pub corner_colours: Vec<Option<[[f32; 3]; 3]>>,
    /// Per triangle: the round it was filled in (0 for coloured ones, `u32::MAX`
    /// for the fallback).
    pub round: Vec<u32>,
    pub stats: HoleFillStats,
}

/// The paper's step 1: for every vertex, the triangles using it, ascending, in
/// compressed rows (`triangles[offsets[v]..offsets[v + 1]]`). A triangle naming a
/// vertex twice is listed once under it.
#[derive(Debug, Clone, PartialEq, Eq)]
struct VertexTriangles {
    offsets: Vec<usize>,
    triangles: Vec<u32>,
}

impl VertexTriangles {
    /// The table of a mesh whose indices are all below `vertices` (checked first).
    fn build(triangles: &[[u32; 3]], vertices: usize) -> Self {
        let distinct = |t: &[u32; 3]| {
            let [a, b, c] = *t;
            [
                Some(a),
                (b != a).then_some(b),
                (c != a && c != b).then_some(c),
            ]
        };
        let mut counts = vec![0usize; vertices + 1];
        for t in triangles {
            for v in distinct(t).into_iter().flatten() {
                if let Some(n) = counts.get_mut((v as usize).saturating_add(1)) {
                    *n += 1;
                }
            }
        }
        for v in 0..vertices {
            counts[v + 1] += counts[v];
        }
        let offsets = counts;
        let mut next = offsets.clone();
        let mut list = vec![0u32; offsets.last().copied().unwrap_or(0)];
        for (t, tri) in triangles.iter().enumerate() {
            for v in distinct(tri).into_iter().flatten() {
                if let Some(slot) = next.get_mut(v as usize)
                    && let Some(entry) = list.get_mut(*slot)
                {
                    *entry = t as u32;
                    *slot += 1;
                }
            }
        }
        Self {
            offsets,
            triangles: list,
        }
    }

    /// The triangles using vertex `v` (empty for one out of range).
    fn around(&self, v: u32) -> &[u32] {
        let v = v as usize;
        match (self.offsets.get(v), self.offsets.get(v + 1)) {
            (Some(&start), Some(&end)) => self.triangles.get(start..end).unwrap_or(&[]),
            _ => &[],
        }
    }
}

/// The first triangle naming a vertex out of range.
fn check_indices(mesh: &SurfaceMesh) -> Result<(), HoleFillError> {
    let vertices = mesh.positions.len();
    for (triangle, tri) in mesh.triangles.iter().enumerate() {
        if let Some(&vertex) = tri.iter().find(|&&v| v as usize >= vertices) {
            return Err(HoleFillError::VertexIndex {
                triangle,
                vertex,
                vertices,
            });
        }
    }
    Ok(())
}

/// A vertex's offset from the mesh origin in f64; `None` out of range or not finite.
fn local(mesh: &SurfaceMesh, v: u32) -> Option<Point3<f64>> {
    let p = mesh.positions.get(v as usize)?;
    let p = Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
    p.iter().all(|c| c.is_finite()).then_some(p)
}

/// A triangle's centroid as an offset from the mesh origin; `None` when a corner is
/// out of range or not finite.
fn local_centroid(mesh: &SurfaceMesh, tri: &[u32; 3]) -> Option<Point3<f64>> {
    let [a, b, c] = tri.map(|v| local(mesh, v));
    let (a, b, c) = (a?, b?, c?);
    Some(Point3::from((a.coords + b.coords + c.coords) / 3.0))
}

/// The paper's step 2: every visible triangle's "average" colour, its centroid
/// projected into the image of each view in `seen_by` (views looked up by id in
/// `views`; a view without image, an unknown id, or a centroid off the image gives no
/// sample) and the bilinearly sampled colours averaged. Colours are sRGB bytes scaled
/// to 0..=1.
///
/// With `config.occlusion_boundary`, a view's sample is skipped for a triangle at that
/// view's occlusion boundary (an edge neighbour not seen by the view, or a border
/// edge without neighbour), unless every sample would be skipped: then all are used.
///
/// `None` for a triangle without any sample (no view sees it, or it names a vertex out
/// of range, or a corner is not finite). `seen_by` shorter than the triangles counts
/// as empty lists for the rest; the output always has one entry per triangle.
pub fn triangle_colours(
    mesh: &SurfaceMesh,
    seen_by: &[Vec<u32>],
    views: &[AcquisitionView<'_>],
    config: &HoleFillConfig,
) -> Vec<Option<[f32; 3]>> {
    triangle_colours_where(mesh, seen_by, views, config, &|_| true)
}

/// [`triangle_colours`] for the triangles `wanted` says, `None` for the others:
/// filling reads only the triangles that share a vertex with a hole, and sampling
/// every image of every seen triangle would cost far more than the filling.
pub fn triangle_colours_where(
    mesh: &SurfaceMesh,
    seen_by: &[Vec<u32>],
    views: &[AcquisitionView<'_>],
    config: &HoleFillConfig,
    wanted: &dyn Fn(usize) -> bool,
) -> Vec<Option<[f32; 3]>> {
    let n = mesh.triangles.len();
    let vertices = mesh.positions.len();
    // The first view of each id counts.
    let mut by_id: BTreeMap<u32, &AcquisitionView<'_>> = BTreeMap::new();
    for view in views {
        by_id.entry(view.id).or_insert(view);
    }
    // Triangles naming a vertex out of range take no part: not in the table, no colour.
    let valid: Vec<bool> = mesh
        .triangles
        .iter()
        .map(|t| t.iter().all(|&v| (v as usize) < vertices))
        .collect();
    let usable: Vec<[u32; 3]> = mesh
        .triangles
        .iter()
        .zip(&valid)
        .map(|(t, &ok)| if ok { *t } else { [u32::MAX; 3] })
        .collect();
    let table = VertexTriangles::build(&usable, vertices);
    let seen = |t: usize| seen_by.get(t).map_or(&[][..], Vec::as_slice);

    let mut out = Vec::with_capacity(n);
    let mut neighbours: Vec<u32> = Vec::new();
    for (t, tri) in mesh.triangles.iter().enumerate() {
        if !wanted(t) {
            out.push(None);
            continue;
        }
        let ids = seen(t);
        let centroid = if valid[t] {
            local_centroid(mesh, tri)
        } else {
            None
        };
        let (Some(centroid), false) = (centroid, ids.is_empty()) else {
            out.push(None);
            continue;
        };
        let world = Point3::new(
            mesh.origin_m[0] + centroid.x,
            mesh.origin_m[1] + centroid.y,
            mesh.origin_m[2] + centroid.z,
        );
        // Edge neighbours (sharing two vertices); a border edge has none.
        neighbours.clear();
        let mut border = false;
        for (a, b) in [(tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])] {
            if a == b {
                continue;
            }
            let before = neighbours.len();
            for &u in table.around(a) {
                let shares_b = usable.get(u as usize).is_some_and(|ut| ut.contains(&b));
                if u as usize != t && shares_b {
                    neighbours.push(u);
                }
            }
            border |= neighbours.len() == before;
        }

        // Per view: the sample and whether it sits at that view's occlusion boundary.
        let mut inner = Accumulator::default();
        let mut all = Accumulator::default();
        for id in ids {
            let Some(colour) = by_id.get(id).and_then(|view| sample_view(view, &world)) else {
                continue;
            };
            all.add(colour);
            let at_boundary = border || neighbours.iter().any(|&u| !seen(u as usize).contains(id));
            if !(config.occlusion_boundary && at_boundary) {
                inner.add(colour);
            }
        }
        out.push(inner.mean().or_else(|| all.mean()));
    }
    out
}

/// A running sum of colours.
#[derive(Debug, Default, Clone, Copy)]
struct Accumulator {
    sum: [f64; 3],
    count: u32,
}

impl Accumulator {
    fn add(&mut self, c: [f64; 3]) {
        for (s, v) in self.sum.iter_mut().zip(c) {
            *s += v;
        }
        self.count += 1;
    }

    fn mean(&self) -> Option<[f32; 3]> {
        if self.count == 0 {
            return None;
        }
        let n = f64::from(self.count);
        let m = self.sum.map(|s| (s / n) as f32);
        m.iter().all(|c| c.is_finite()).then_some(m)
    }
}

/// A world point's colour in a view's image, bilinear between the four nearest pixel
/// centres; `None` without image, behind the camera or off the image. An image of
/// another size than the camera's is scaled to it (pixel centres kept aligned); one
/// whose bytes do not match its size gives nothing.
fn sample_view(view: &AcquisitionView<'_>, world: &Point3<f64>) -> Option<[f64; 3]> {
    let image = view.image?;
    let (pixel, _depth) = view.project(world)?;
    if !view.inside(&pixel, 0.0) {
        return None;
    }
    let (cw, ch) = (f64::from(view.camera.width), f64::from(view.camera.height));
    if cw <= 0.0 || ch <= 0.0 {
        return None;
    }
    let sx = f64::from(image.width) / cw;
    let sy = f64::from(image.height) / ch;
    let at = Vector2::new((pixel.x + 0.5) * sx - 0.5, (pixel.y + 0.5) * sy - 0.5);
    bilinear(image, &at)
}

/// Bilinear interpolation of an image at a pixel position (centres at integers),
/// clamped to the outermost pixel centres.
fn bilinear(image: &EoFrame, at: &Vector2<f64>) -> Option<[f64; 3]> {
    let (w, h) = (image.width as usize, image.height as usize);
    if w == 0 || h == 0 || image.rgb.len() != 3 * w * h || !at.x.is_finite() || !at.y.is_finite() {
        return None;
    }
    let x = at.x.clamp(0.0, (w - 1) as f64);
    let y = at.y.clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let px = |xi: usize, yi: usize| -> Option<[f64; 3]> {
        let i = 3 * (yi * w + xi);
        let p = image.rgb.get(i..i + 3)?;
        Some([0, 1, 2].map(|k| f64::from(p[k]) / 255.0))
    };
    let (a, b, c, d) = (px(x0, y0)?, px(x1, y0)?, px(x0, y1)?, px(x1, y1)?);
    Some([0, 1, 2].map(|k| {
        let top = a[k] + (b[k] - a[k]) * fx;
        let bottom = c[k] + (d[k] - c[k]) * fx;
        top + (bottom - top) * fy
    }))
}

/// Not yet filled (rounds read only lower values).
const UNFILLED: u32 = u32::MAX - 1;

/// The paper's steps 1 and 3: every triangle without colour (`None`, or a colour not
/// finite) that touches a coloured triangle at a vertex is filled in rounds. In each
/// round every such hole gives each of its corners the colour of the closest (corner
/// to centroid) coloured triangle around that corner, or, when none is coloured
/// around it, of the closest coloured triangle around the hole. Coloured means with
/// its own colour or filled in an earlier round, so the result does not depend on
/// triangle order; a filled triangle passes on its corner colour nearest the corner
/// being coloured (the shared corner's own, so shading stays continuous). Rounds stop
/// when nothing changes or at `config.max_rounds`; the holes left get
/// `config.fallback_colour` and round `u32::MAX`.
///
/// Ties in distance go to the smaller colour (component-wise order), never to the
/// lower triangle index. A corner not finite is equally far from every candidate;
/// a centroid not finite is farther than any finite one.
pub fn fill_holes(
    mesh: &SurfaceMesh,
    colours: &[Option<[f32; 3]>],
    config: &HoleFillConfig,
) -> Result<HoleFill, HoleFillError> {
    let n = mesh.triangles.len();
    if colours.len() != n {
        return Err(HoleFillError::ColourCount {
            colours: colours.len(),
            triangles: n,
        });
    }
    check_indices(mesh)?;
    if !config.fallback_colour.iter().all(|c| c.is_finite()) {
        return Err(HoleFillError::NonFiniteFallback(config.fallback_colour));
    }
    let own: Vec<Option<[f32; 3]>> = colours
        .iter()
        .map(|c| c.filter(|c| c.iter().all(|v| v.is_finite())))
        .collect();
    let table = VertexTriangles::build(&mesh.triangles, mesh.positions.len());
    let centroids: Vec<Option<Point3<f64>>> = mesh
        .triangles
        .iter()
        .map(|t| local_centroid(mesh, t))
        .collect();

    let mut round: Vec<u32> = own
        .iter()
        .map(|c| if c.is_some() { 0 } else { UNFILLED })
        .collect();
    let mut corner_colours: Vec<Option<[[f32; 3]; 3]>> = vec![None; n];
    let mut stats = HoleFillStats {
        coloured: own.iter().filter(|c| c.is_some()).count(),
        ..HoleFillStats::default()
    };

    // The colour a coloured triangle `u` offers a hole's corner at `p`: its own, or,
    // for one filled in an earlier round, its corner colour nearest `p`.
    let offered = |u: usize, p: Option<&Point3<f64>>, corners: &[Option<[[f32; 3]; 3]>]| {
        if let Some(c) = own.get(u).copied().flatten() {
            return c;
        }
        let cc = corners
            .get(u)
            .copied()
            .flatten()
            .unwrap_or([config.fallback_colour; 3]);
        let Some(tri) = mesh.triangles.get(u) else {
            return cc[0];
        };
        let mut best = (f64::INFINITY, cc[0]);
        for (k, &v) in tri.iter().enumerate() {
            let d = distance(p, local(mesh, v).as_ref());
            if better((d, cc[k]), best) {
                best = (d, cc[k]);
            }
        }
        best.1
    };

    // `sources`: the triangles coloured in the last round, at first those with their
    // own colour; `stamp` marks a hole already queued for the coming round.
    let mut stamp: Vec<u32> = vec![0; n];
    let mut frontier: Vec<u32> = Vec::new();
    let mut sources: Vec<u32> = (0..n as u32).filter(|&t| round[t as usize] == 0).collect();
    let mut r: u32 = 0;
    while !sources.is_empty() {
        let next = r.saturating_add(1);
        // Holes touching a triangle coloured in the last round.
        frontier.clear();
        for &s in &sources {
            let Some(tri) = mesh.triangles.get(s as usize) else {
                continue;
            };
            for &v in tri {
                for &u in table.around(v) {
                    let ui = u as usize;
                    if round[ui] == UNFILLED && stamp[ui] != next {
                        stamp[ui] = next;
                        frontier.push(u);
                    }
                }
            }
        }
        if frontier.is_empty() {
            break;
        }
        if r >= config.max_rounds {
            stats.hit_round_limit = true;
            break;
        }
        r = next;
        frontier.sort_unstable();
        // Every hole of this round reads only triangles of earlier rounds.
        let mut fills: Vec<(u32, [[f32; 3]; 3])> = Vec::with_capacity(frontier.len());
        for &h in &frontier {
            let hi = h as usize;
            let Some(tri) = mesh.triangles.get(hi) else {
                continue;
            };
            let coloured = |u: u32| u != h && round.get(u as usize).is_some_and(|&q| q < r);
            let mut corners = [config.fallback_colour; 3];
            let mut any = false;
            for (k, &v) in tri.iter().enumerate() {
                let p = local(mesh, v);
                let pick = |cands: &mut dyn Iterator<Item = u32>| -> Option<[f32; 3]> {
                    let mut best: Option<(f64, [f32; 3])> = None;
                    for u in cands {
                        let ui = u as usize;
                        let d = distance(p.as_ref(), centroids.get(ui).copied().flatten().as_ref());
                        let c = offered(ui, p.as_ref(), &corner_colours);
                        if best.is_none_or(|b| better((d, c), b)) {
                            best = Some((d, c));
                        }
                    }
                    best.map(|b| b.1)
                };
                let around_vertex =
                    pick(&mut table.around(v).iter().copied().filter(|&u| coloured(u)));
                let chosen = around_vertex.or_else(|| {
                    pick(
                        &mut tri
                            .iter()
                            .flat_map(|&w| table.around(w).iter().copied())
                            .filter(|&u| coloured(u)),
                    )
                });
                if let Some(c) = chosen {
                    corners[k] = c;
                    any = true;
                }
            }
            if any {
                fills.push((h, corners));
            }
        }
        if fills.is_empty() {
            break;
        }
        sources.clear();
        for (h, corners) in fills {
            round[h as usize] = r;
            corner_colours[h as usize] = Some(corners);
            sources.push(h);
            stats.filled += 1;
        }
        stats.rounds = r;
    }

    for (t, q) in round.iter_mut().enumerate() {
        if *q == UNFILLED {
            *q = u32::MAX;
            corner_colours[t] = Some([config.fallback_colour; 3]);
            stats.fallback += 1;
        }
    }
    Ok(HoleFill {
        corner_colours,
        round,
        stats,
    })
}

/// Distance between two points; infinite when either is missing (not finite).
fn distance(a: Option<&Point3<f64>>, b: Option<&Point3<f64>>) -> f64 {
    match (a, b) {
        (Some(a), Some(b)) => {
            let d = (a - b).norm();
            if d.is_finite() { d } else { f64::INFINITY }
        }
        _ => f64::INFINITY,
    }
}

/// Whether candidate `a` beats `b`: nearer, or as near with the smaller colour.
fn better(a: (f64, [f32; 3]), b: (f64, [f32; 3])) -> bool {
    match a.0.total_cmp(&b.0) {
        Ordering::Less => true,
        Ordering::Greater => false,
        Ordering::Equal => {
            let ord = a.1[0]
                .total_cmp(&b.1[0])
                .then(a.1[1].total_cmp(&b.1[1]))
                .then(a.1[2].total_cmp(&b.1[2]));
            ord == Ordering::Less
        }
    }
}

#[cfg(test)]
mod tests;
