//! The mesh (Sec. 3-4), built between each pair of neighbouring rows as soon as both
//! are placed: two triangles per 2x2 cell of usable vertices, split along the
//! diagonal with the smaller range difference, flagged stretched from edge tests
//! done once per edge, and graded (normal accuracy) right away, while the row's
//! points are in cache.
//!
//! Every per-cell quantity is first computed for the whole row of cells by
//! branch-free loops over arrays (vectorised by the compiler), incomplete cells
//! included; the full cells' triangles are then appended run by run (slice copies).

use crate::fusion_tables::LidarPitch;
use crate::scan::{NO_VERTEX, TriangleFlags};
use crate::sensor::RangeNoise;

use super::rows::Row;
use super::{FuseConfig, grade, runs_of_true};

/// The stretched-edge rule of the module documentation with its per-call constants,
/// in f32 (the precision of the ranges and angles it compares).
#[derive(Debug, Clone, Copy)]
struct StretchRule {
    tan_alpha: f32,
    /// `k · √2`.
    noise_k: f32,
    /// The sensor's range noise, `σ(r) = sigma_m + sigma_per_m · r`.
    sigma_m: f32,
    sigma_per_m: f32,
}

impl StretchRule {
    fn new(config: &FuseConfig, noise: RangeNoise) -> Self {
        Self {
            tan_alpha: config.tan_max_incidence() as f32,
            noise_k: (config.noise_k() * std::f64::consts::SQRT_2) as f32,
            sigma_m: noise.sigma_m as f32,
            sigma_per_m: noise.sigma_per_m as f32,
        }
    }

    /// Whether the edge between ranges `ri` and `rj`, whose rays are `angle` apart,
    /// spans a depth discontinuity. Used only for two returns (finite, positive
    /// ranges); elsewhere its answer is computed but never read. Plain comparisons
    /// rather than `min`/`max` (the same for such ranges) keep the loops vectorised.
    #[inline(always)]
    fn stretched(&self, ri: f32, rj: f32, angle: f32) -> bool {
        let (near, far) = if ri < rj { (ri, rj) } else { (rj, ri) };
        // σ(r) as `RangeNoise::sigma_at` defines it: never negative.
        let sigma = self.sigma_m + self.sigma_per_m * if far > 0.0 { far } else { 0.0 };
        let sigma = if sigma > 0.0 { sigma } else { 0.0 };
        let allowed = near * angle * self.tan_alpha + self.noise_k * sigma;
        (ri - rj).abs() > allowed
    }

    /// Edge flags `out[k]` for the edges `(ri[k], rj[k])` with ray angles `angles[k]`.
    #[inline(always)]
    fn edges(&self, ri: &[f32], rj: &[f32], angles: &[f32], out: &mut [bool]) {
        for (((o, &a), &b), &angle) in out.iter_mut().zip(ri).zip(rj).zip(angles) {
            *o = self.stretched(a, b, angle);
        }
    }
}

/// Each cell of a row of cells, ready for emission.
#[derive(Debug, Default)]
struct CellRow {
    /// The cell's four vertices are usable.
    full: Vec<bool>,
    /// Its two triangles, their flags and accuracies.
    triangles: Vec<[[u32; 3]; 2]>,
    flags: Vec<[TriangleFlags; 2]>,
    accuracy: Vec<[f32; 2]>,
}

/// `p` if `s`, else `q`: a select per coordinate, which vectorises.
#[inline(always)]
fn pick(s: bool, p: [f32; 3], q: [f32; 3]) -> [f32; 3] {
    [
        if s { p[0] } else { q[0] },
        if s { p[1] } else { q[1] },
        if s { p[2] } else { q[2] },
    ]
}

#[inline(always)]
fn flag(stretched: bool, degenerate: bool) -> TriangleFlags {
    TriangleFlags(
        (u8::from(stretched) * TriangleFlags::STRETCHED)
            | (u8::from(degenerate) * TriangleFlags::DEGENERATE),
    )
}

/// Sec. 3: a cell (a b / c d) is split along the diagonal with the smaller range
/// difference: a-d, giving (a, c, d) + (a, d, b), or b-c, giving (a, c, b) + (b, c, d).
#[inline(always)]
fn split_along_ad(ra: f32, rb: f32, rc: f32, rd: f32) -> bool {
    (ra - rd).abs() <= (rb - rc).abs()
}

/// The mesh of a grid `width` pixels wide, built row by row.
#[derive(Debug)]
pub(super) struct Mesh {
    rule: StretchRule,
    cop: [f32; 3],
    triangles: Vec<[u32; 3]>,
    flags: Vec<TriangleFlags>,
    accuracy: Vec<f32>,
    /// Stretched flags of the horizontal edges of the row above and of this row, and
    /// of the vertical edges between them.
    right_above: Vec<bool>,
    right: Vec<bool>,
    down: Vec<bool>,
    cells: CellRow,
    /// Stretched flag of the diagonal each cell is split along.
    diagonal: Vec<bool>,
}

impl Mesh {
    /// A mesh with room for `max_triangles` triangles; `cop` is the scan's centre of
    /// projection.
    pub fn new(
        width: usize,
        max_triangles: usize,
        config: &FuseConfig,
        noise: RangeNoise,
        cop: [f64; 3],
    ) -> Self {
        let cells = width.saturating_sub(1);
        Self {
            rule: StretchRule::new(config, noise),
            cop: cop.map(|c| c as f32),
            triangles: Vec::with_capacity(max_triangles),
            flags: Vec::with_capacity(max_triangles),
            accuracy: Vec::with_capacity(max_triangles),
            right_above: vec![false; cells],
            right: vec![false; cells],
            down: vec![false; width],
            cells: CellRow {
                full: vec![false; cells],
                triangles: vec![[[0; 3]; 2]; cells],
                flags: vec![[TriangleFlags(0); 2]; cells],
                accuracy: vec![[0.0; 2]; cells],
            },
            diagonal: vec![false; cells],
        }
    }

    /// Adds the cells between `above` and `row` (none for the first row). `ranges`
    /// is the whole frame's.
    #[inline(always)]
    pub fn add_row(&mut self, above: Option<&Row>, row: &Row, ranges: &[f32], pitch: &LidarPitch) {
        let w = row.width();
        let cells = w.saturating_sub(1);
        let at = row.first_pixel;
        let (Some(r), Some(angles)) = (ranges.get(at..at + w), pitch.right.get(at..at + cells))
        else {
            return;
        };
        // Sec. 4: each horizontal edge of the row once.
        std::mem::swap(&mut self.right_above, &mut self.right);
        self.rule
            .edges(&r[..cells], &r[1..], angles, &mut self.right[..cells]);
        let Some(above) = above else {
            return;
        };
        let top = above.first_pixel;
        let (Some(r_above), Some(down)) = (ranges.get(top..top + w), pitch.down.get(top..top + w))
        else {
            return;
        };
        // Sec. 4: each vertical edge between the two rows once.
        self.rule.edges(r_above, r, down, &mut self.down[..w]);
        self.build_cells(above, row, r_above, r, pitch);
        self.emit();
    }

    /// Triangles, flags and accuracies of every cell between `above` and `row`,
    /// whether or not its vertices exist (incomplete cells are not emitted).
    #[inline(always)]
    fn build_cells(
        &mut self,
        above: &Row,
        row: &Row,
        r_above: &[f32],
        r: &[f32],
        pitch: &LidarPitch,
    ) {
        let n = row.width().saturating_sub(1);
        let top = above.first_pixel;
        let (Some(down_right), Some(right_to_down)) = (
            pitch.down_right.get(top..top + n),
            pitch.right_to_down.get(top..top + n),
        ) else {
            return;
        };
        let (rt, rb) = (&r_above[..n + 1], &r[..n + 1]);
        // Sec. 4: the diagonal each cell is split along.
        let diagonal = &mut self.diagonal[..n];
        for (u, stretched) in diagonal.iter_mut().enumerate() {
            let s = split_along_ad(rt[u], rt[u + 1], rb[u], rb[u + 1]);
            let (ri, rj) = if s {
                (rt[u], rb[u + 1])
            } else {
                (rt[u + 1], rb[u])
            };
            let angle = if s { down_right[u] } else { right_to_down[u] };
            *stretched = self.rule.stretched(ri, rj, angle);
        }
        let diagonal = &self.diagonal[..n];
        let (tx, ty, tz) = (&above.x[..n + 1], &above.y[..n + 1], &above.z[..n + 1]);
        let (bx, by, bz) = (&row.x[..n + 1], &row.y[..n + 1], &row.z[..n + 1]);
        let (vt, vb) = (&above.usable[..n + 1], &row.usable[..n + 1]);
        let (right_top, right_bottom, down) = (
            &self.right_above[..n],
            &self.right[..n],
            &self.down[..n + 1],
        );
        let CellRow {
            full,
            triangles,
            flags,
            accuracy,
        } = &mut self.cells;
        let (full, triangles) = (&mut full[..n], &mut triangles[..n]);
        let (flags, accuracy) = (&mut flags[..n], &mut accuracy[..n]);
        let cop = self.cop;
        for u in 0..n {
            // a (u,v)   b (u+1,v)
            // c (u,v+1) d (u+1,v+1); (a, c, b) winds with its normal towards the COP.
            let a = [tx[u], ty[u], tz[u]];
            let b = [tx[u + 1], ty[u + 1], tz[u + 1]];
            let c = [bx[u], by[u], bz[u]];
            let d = [bx[u + 1], by[u + 1], bz[u + 1]];
            let (va, vb_, vc, vd) = (vt[u], vt[u + 1], vb[u], vb[u + 1]);
            let s = split_along_ad(rt[u], rt[u + 1], rb[u], rb[u + 1]);
            // Sec. 4: a triangle is stretched when any of its three edges is. (Bitwise
            // selects: both values are loaded, so the loop stays vectorised.)
            let (right_a, right_c) = (right_top[u], right_bottom[u]);
            let diagonal = diagonal[u];
            let stretched1 = down[u] | diagonal | (s & right_c) | (!s & right_a);
            let stretched2 = diagonal | down[u + 1] | (s & right_a) | (!s & right_c);
            // Sec. 3: normal accuracy.
            let (acc1, degenerate1) = grade(a, c, pick(s, d, b), cop);
            let (acc2, degenerate2) = grade(pick(s, a, b), pick(s, d, c), pick(s, b, d), cop);
            full[u] =
                (va != NO_VERTEX) & (vb_ != NO_VERTEX) & (vc != NO_VERTEX) & (vd != NO_VERTEX);
            triangles[u] = [
                [va, vc, if s { vd } else { vb_ }],
                [
                    if s { va } else { vb_ },
                    if s { vd } else { vc },
                    if s { vb_ } else { vd },
                ],
            ];
            flags[u] = [flag(stretched1, degenerate1), flag(stretched2, degenerate2)];
            accuracy[u] = [acc1, acc2];
        }
    }

    /// Appends the two triangles of every full cell, run by run (slice copies).
    #[inline(always)]
    fn emit(&mut self) {
        let cells = &self.cells;
        for run in runs_of_true(&cells.full) {
            self.triangles
                .extend_from_slice(cells.triangles[run.clone()].as_flattened());
            self.flags
                .extend_from_slice(cells.flags[run.clone()].as_flattened());
            self.accuracy
                .extend_from_slice(cells.accuracy[run].as_flattened());
        }
    }

    /// The triangles, their flags and accuracies, at their exact size.
    pub fn finish(mut self) -> (Vec<[u32; 3]>, Vec<TriangleFlags>, Vec<f32>) {
        if self.triangles.len() < self.triangles.capacity() {
            // Some counted cells had an untextured vertex: give the room back.
            self.triangles.shrink_to_fit();
            self.flags.shrink_to_fit();
            self.accuracy.shrink_to_fit();
        }
        (self.triangles, self.flags, self.accuracy)
    }
}
