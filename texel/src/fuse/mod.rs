//! Fusion: a lidar range frame and its EO image become a texel scan (Killpack &
//! Budge 2016, Sec. 3-4): every return becomes a 3D point in the EO frame, textured
//! by its EO projection; the range grid becomes a triangle mesh with per-triangle
//! normal accuracy and stretched / degenerate flags.
//!
//! ## The stretched-triangle rule
//!
//! Two neighbouring lidar samples `i`, `j` whose rays are `θ_ij` apart can, on one
//! continuous surface seen at incidence angle `α` (between the ray and the surface
//! normal), differ in range by about `r θ tan α`. A triangle edge is **stretched**
//! (it spans a depth discontinuity) when
//!
//! ```text
//! |r_i - r_j| > min(r_i, r_j) · θ_ij · tan(max_incidence) + k · √2 · σ(max(r_i, r_j))
//! ```
//!
//! with `σ(r)` the sensor's range noise, `max_incidence` the steepest incidence still
//! taken for one surface and `k` the noise allowance (both in [`FuseConfig`]). A
//! triangle with any stretched edge is flagged. `θ_ij` comes from the lidar's ray
//! table, computed once per sensor ([`LidarPitch`]). The test is evaluated in f32, the
//! precision of the ranges and angles it compares: its verdict can differ from an
//! exact evaluation only where `|r_i - r_j|` is within ~1e-7 (relative) of the
//! allowance.
//!
//! ## Precision
//!
//! Points are `ray · r + t` in f64 (rays turned into the EO frame once per sensor),
//! stored in f32; texture coordinates are projected in f64. Within 1e-4 m and 0.05 px
//! of the analytic truth, as the tests check; the normal accuracy is good to ~1e-6
//! ([`normal_accuracy`]).
//!
//! ## Speed
//!
//! Per sensor, [`FusionTables`] holds what does not change per frame. Per frame, the
//! grid is processed a row at a time: a branch-free placement loop over the row's
//! pixels, then the mesh between it and the row above (edge tests once per edge,
//! triangles graded as they are made), all in loops the compiler vectorises; the
//! scan's arrays are allocated once at their final size and filled by slice copies.
//! The row loop is built for the baseline target and for AVX2, chosen at run time
//! (`isa`). `cargo bench -p texel --bench fuse` measures it.

mod isa;
mod mesh;
mod rows;

use std::ops::Range;
use std::sync::Arc;

use nalgebra::Vector2;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::frames::{EoFrame, RangeFrame, is_return};
use crate::scan::TexelScan;
use crate::sensor::Sensor;

use mesh::Mesh;
use rows::{Points, Row};

// The once-per-sensor tables live below both this module and `sensor`; still
// reachable under `texel::fuse::`, where they were.
pub use crate::fusion_tables::{EoProjection, FusionTables, LidarPitch};

/// Parameters of fusion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FuseConfig {
    /// Steepest incidence angle (ray to surface normal) still taken as one continuous
    /// surface, degrees in (0, 90).
    pub max_incidence_deg: f64,
    /// Range noise allowance of the stretched rule, in standard deviations.
    pub stretch_noise_k: f64,
}

impl Default for FuseConfig {
    fn default() -> Self {
        Self {
            max_incidence_deg: 80.0,
            stretch_noise_k: 3.0,
        }
    }
}

impl FuseConfig {
    /// `tan(max_incidence)`, with the angle clamped into (0.1°, 89.9°) so the tangent
    /// is finite and positive.
    fn tan_max_incidence(&self) -> f64 {
        let deg = if self.max_incidence_deg.is_finite() {
            self.max_incidence_deg.clamp(0.1, 89.9)
        } else {
            80.0
        };
        deg.to_radians().tan()
    }

    fn noise_k(&self) -> f64 {
        if self.stretch_noise_k.is_finite() {
            self.stretch_noise_k.max(0.0)
        } else {
            3.0
        }
    }
}

#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum FuseError {
    #[error("range frame is {got_w}x{got_h}, the lidar model is {want_w}x{want_h}")]
    RangeSize {
        got_w: u32,
        got_h: u32,
        want_w: u32,
        want_h: u32,
    },
    #[error("EO frame is {got_w}x{got_h}, the EO model is {want_w}x{want_h}")]
    EoSize {
        got_w: u32,
        got_h: u32,
        want_w: u32,
        want_h: u32,
    },
    #[error("frame buffers do not match their declared sizes")]
    Inconsistent,
}

/// Fuses one texel frame. Pure and synchronous; the EO image is moved into the scan.
///
/// A frame with no usable return gives an empty scan, not an error; only frames whose
/// sizes disagree with the sensor model are refused.
///
/// The frame is processed one row of lidar pixels at a time, and the mesh between two
/// rows built as soon as both are placed, so the working set stays in cache; every
/// array of the scan is allocated once at its final size.
pub fn fuse(
    range: &RangeFrame,
    eo: impl Into<Arc<EoFrame>>,
    sensor: &Sensor,
    config: &FuseConfig,
) -> Result<TexelScan, FuseError> {
    fuse_with(isa::Isa::detect(), range, eo.into(), sensor, config)
}

/// [`fuse`] with its row loop built for `isa`.
fn fuse_with(
    isa: isa::Isa,
    range: &RangeFrame,
    eo: Arc<EoFrame>,
    sensor: &Sensor,
    config: &FuseConfig,
) -> Result<TexelScan, FuseError> {
    check_sizes(range, &eo, sensor)?;
    let width = range.width as usize;
    let (returns, full_cells) = count_returns_and_cells(range, sensor.fusion.ray_valid());
    let mut points = Points::with_capacity(returns, range.pixel_count());
    let cop_m = [0.0; 3];
    let mut mesh = Mesh::new(
        width,
        2 * full_cells,
        config,
        sensor.model.range_noise,
        cop_m,
    );
    isa::fuse_rows_with(isa, range, sensor, &mut points, &mut mesh);
    let (triangles, triangle_flags, triangle_accuracy) = mesh.finish();
    Ok(TexelScan {
        timestamp_ns: range.timestamp_ns,
        seq: range.seq,
        grid_width: range.width,
        grid_height: range.height,
        vertices: points.vertices,
        tex_coords: points.tex_coords,
        vertex_textured: points.vertex_textured,
        vertex_pixel: points.vertex_pixel,
        pixel_vertex: points.pixel_vertex,
        triangles,
        triangle_accuracy,
        triangle_flags,
        texture: eo,
        cop_m,
        scan_from_lidar: sensor.model.eo_from_lidar,
        range_noise: sensor.model.range_noise,
    })
}

/// The row loop of [`fuse`]: each row of lidar pixels placed, appended to the scan's
/// vertices and meshed with the row above. Inlined into each of [`isa`]'s builds.
#[inline(always)]
fn fuse_rows(range: &RangeFrame, sensor: &Sensor, points: &mut Points, mesh: &mut Mesh) {
    let width = range.width as usize;
    let (mut above, mut row) = (Row::new(width), Row::new(width));
    for v in 0..range.height as usize {
        // Sec. 3: every return becomes a point in the EO frame, textured by projection.
        row.place(v, range, &sensor.fusion, sensor.model.range_bias_m);
        points.append(&mut row);
        // Sec. 3: the range grid becomes a mesh, two triangles per full 2x2 cell, each
        // graded by its normal accuracy; Sec. 4: triangles over depth discontinuities
        // are flagged stretched.
        mesh.add_row(
            (v > 0).then_some(&above),
            &row,
            &range.ranges_m,
            &sensor.lidar_pitch,
        );
        std::mem::swap(&mut above, &mut row);
    }
}

fn check_sizes(range: &RangeFrame, eo: &EoFrame, sensor: &Sensor) -> Result<(), FuseError> {
    let lidar = &sensor.model.lidar;
    if (range.width, range.height) != (lidar.width, lidar.height) {
        return Err(FuseError::RangeSize {
            got_w: range.width,
            got_h: range.height,
            want_w: lidar.width,
            want_h: lidar.height,
        });
    }
    let cam = &sensor.model.eo;
    if (eo.width, eo.height) != (cam.width, cam.height) {
        return Err(FuseError::EoSize {
            got_w: eo.width,
            got_h: eo.height,
            want_w: cam.width,
            want_h: cam.height,
        });
    }
    if !range.is_consistent() || !eo.is_consistent() || sensor.fusion.len() != range.pixel_count() {
        return Err(FuseError::Inconsistent);
    }
    Ok(())
}

/// The number of pixels with a vertex (a return along a valid ray) and of 2x2 cells
/// whose four pixels have one: the scan's vertex count, and a bound on its triangle
/// count (exact unless some vertex falls outside the EO image).
fn count_returns_and_cells(range: &RangeFrame, ray_valid: &[bool]) -> (usize, usize) {
    let w = range.width as usize;
    let (mut returns, mut cells) = (0, 0);
    // Per row, whether each pixel has a vertex, and then whether each column of the
    // row pair has two (as 0/1 bytes, so the loops vectorise).
    let mut above = vec![0u8; w];
    let mut row = vec![0u8; w];
    let mut column = vec![0u8; w];
    for (v, (ranges, valid)) in range
        .ranges_m
        .chunks_exact(w.max(1))
        .zip(ray_valid.chunks_exact(w.max(1)))
        .enumerate()
    {
        for ((has, &r), &ok) in row.iter_mut().zip(ranges).zip(valid) {
            *has = u8::from(ok & is_return(r));
        }
        returns += row.iter().map(|&h| usize::from(h)).sum::<usize>();
        if v > 0 {
            for ((full, &a), &b) in column.iter_mut().zip(&above).zip(&row) {
                *full = a & b;
            }
            cells += column
                .windows(2)
                .map(|pair| usize::from(pair[0] & pair[1]))
                .sum::<usize>();
        }
        std::mem::swap(&mut above, &mut row);
    }
    (returns, cells)
}

/// The runs of consecutive `true` in `flags`, as index ranges, in order.
#[inline(always)]
fn runs_of_true(flags: &[bool]) -> impl Iterator<Item = Range<usize>> + '_ {
    let mut start = 0;
    std::iter::from_fn(move || {
        let run_start = start + flags.get(start..)?.iter().position(|&f| f)?;
        let run_len = flags[run_start..]
            .iter()
            .position(|&f| !f)
            .unwrap_or(flags.len() - run_start);
        start = run_start + run_len;
        Some(run_start..start)
    })
}

/// Normal accuracy of triangle `(a, b, c)` seen from `cop`: the cosine between its
/// right-handed normal `(b - a) x (c - a)` and the direction from its centroid to the
/// COP, clamped to [0, 1]. `None` for a degenerate triangle: coincident or collinear
/// vertices (sine of the angle at `a` below 1e-6, the resolution of f32 coordinates)
/// or a centroid on the COP.
///
/// Computed in f32: the vertices are f32 already and neighbouring vertices subtract
/// exactly, so the cosine is good to ~1e-6 (its last steps, two roots, a product and a
/// quotient, add at most a few units of f32 rounding, ~2e-7). Products of squared
/// lengths are formed so that they stay in f32's range wherever the squared lengths
/// themselves do.
#[inline]
pub fn normal_accuracy(a: [f32; 3], b: [f32; 3], c: [f32; 3], cop: [f64; 3]) -> Option<f32> {
    let (accuracy, degenerate) = grade(a, b, c, cop.map(|x| x as f32));
    (!degenerate).then_some(accuracy)
}

/// [`normal_accuracy`] as `(accuracy, degenerate)` (accuracy 0 when degenerate),
/// computed without branches so that loops over triangles vectorise; `fuse` grades
/// with it, the same arithmetic.
#[inline(always)]
fn grade(a: [f32; 3], b: [f32; 3], c: [f32; 3], cop: [f32; 3]) -> (f32, bool) {
    let sub = |x: [f32; 3], y: [f32; 3]| [x[0] - y[0], x[1] - y[1], x[2] - y[2]];
    let dot = |x: [f32; 3], y: [f32; 3]| x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
    let e1 = sub(b, a);
    let e2 = sub(c, a);
    let normal = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    let third = 1.0 / 3.0;
    let to_cop = [
        cop[0] - (a[0] + b[0] + c[0]) * third,
        cop[1] - (a[1] + b[1] + c[1]) * third,
        cop[2] - (a[2] + b[2] + c[2]) * third,
    ];
    let (n2, c2) = (dot(normal, normal), dot(to_cop, to_cop));
    // sin² of the angle at `a` against 1e-12, scaled before the second factor so the
    // product cannot overflow where n2 does not. Written so that a NaN (impossible
    // for finite input) also counts as degenerate.
    let bound = (1e-12 * dot(e1, e1)) * dot(e2, e2);
    let collinear = n2.partial_cmp(&bound) != Some(std::cmp::Ordering::Greater);
    let degenerate = collinear | !n2.is_finite() | !c2.is_finite() | (c2 == 0.0);
    // Where not degenerate, n2 and c2 are positive and finite, so the roots are
    // positive; but near f32's range the product of the roots and the dot product
    // can overflow (inf / inf, or inf - inf inside the dot product). `max` and `min`
    // map a NaN to a bound where `clamp` would pass it on.
    #[allow(clippy::manual_clamp)]
    let accuracy = (dot(normal, to_cop) / (n2.sqrt() * c2.sqrt()))
        .max(0.0)
        .min(1.0);
    (if degenerate { 0.0 } else { accuracy }, degenerate)
}

/// The pixel coordinate of a texture coordinate in an image of the given size (the
/// inverse of the mapping `fuse` uses).
pub fn pixel_of_tex_coord(uv: [f32; 2], width: u32, height: u32) -> Vector2<f64> {
    Vector2::new(
        f64::from(uv[0]) * f64::from(width) - 0.5,
        f64::from(uv[1]) * f64::from(height) - 0.5,
    )
}
