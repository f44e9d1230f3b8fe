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
//! table, computed once per sensor ([`LidarPitch`]).

use nalgebra::{Vector2, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::frames::{EoFrame, RangeFrame, is_return};
use crate::rays::RayTable;
use crate::scan::{NO_VERTEX, TexelScan, TriangleFlags};
use crate::sensor::Sensor;

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

/// Angles in radians between each lidar pixel's ray and its neighbours' (right,
/// down, down-right, and from the right neighbour to the down neighbour), row-major;
/// 0 where a neighbour is missing or a ray is invalid. Computed once per sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct LidarPitch {
    pub right: Vec<f32>,
    pub down: Vec<f32>,
    pub down_right: Vec<f32>,
    /// Between `(u + 1, v)` and `(u, v + 1)`.
    pub right_to_down: Vec<f32>,
}

/// The angle between two unit rays, `2 asin(|a - b| / 2)`: accurate for the tiny
/// angles between neighbouring pixels, where `acos(a·b)` loses half its digits.
fn ray_angle(a: [f32; 3], b: [f32; 3]) -> f32 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let half_chord = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() * 0.5;
    2.0 * half_chord.clamp(0.0, 1.0).asin()
}

impl LidarPitch {
    pub fn new(rays: &RayTable) -> Self {
        let (w, h) = (rays.width as usize, rays.height as usize);
        let angle = |u0: usize, v0: usize, u1: usize, v1: usize| -> f32 {
            if u1 >= w || v1 >= h {
                return 0.0;
            }
            match (rays.ray(v0 * w + u0), rays.ray(v1 * w + u1)) {
                (Some(a), Some(b)) => ray_angle(a, b),
                _ => 0.0,
            }
        };
        let mut pitch = Self {
            right: Vec::with_capacity(w * h),
            down: Vec::with_capacity(w * h),
            down_right: Vec::with_capacity(w * h),
            right_to_down: Vec::with_capacity(w * h),
        };
        for v in 0..h {
            for u in 0..w {
                pitch.right.push(angle(u, v, u + 1, v));
                pitch.down.push(angle(u, v, u, v + 1));
                pitch.down_right.push(angle(u, v, u + 1, v + 1));
                pitch.right_to_down.push(if u + 1 < w && v + 1 < h {
                    angle(u + 1, v, u, v + 1)
                } else {
                    0.0
                });
            }
        }
        pitch
    }
}

/// Fuses one texel frame. Pure and synchronous; the EO image is moved into the scan.
///
/// A frame with no usable return gives an empty scan, not an error; only frames whose
/// sizes disagree with the sensor model are refused.
pub fn fuse(
    range: &RangeFrame,
    eo: EoFrame,
    sensor: &Sensor,
    config: &FuseConfig,
) -> Result<TexelScan, FuseError> {
    check_sizes(range, &eo, sensor)?;
    // Sec. 3: every return becomes a point in the EO frame, textured by projection.
    let mut scan = empty_scan(range, eo, sensor);
    place_vertices(range, sensor, &mut scan);
    // Sec. 3: the range grid becomes a mesh, two triangles per full 2x2 cell; Sec. 4:
    // triangles over depth discontinuities are flagged stretched.
    triangulate(range, sensor, config, &mut scan);
    // Sec. 3, "normal vector accuracy", once per triangle.
    grade_triangles(&mut scan);
    Ok(scan)
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
    if !range.is_consistent() || !eo.is_consistent() {
        return Err(FuseError::Inconsistent);
    }
    Ok(())
}

fn empty_scan(range: &RangeFrame, eo: EoFrame, sensor: &Sensor) -> TexelScan {
    let pixels = range.pixel_count();
    let returns = range.return_count();
    TexelScan {
        timestamp_ns: range.timestamp_ns,
        seq: range.seq,
        grid_width: range.width,
        grid_height: range.height,
        vertices: Vec::with_capacity(returns),
        tex_coords: Vec::with_capacity(returns),
        vertex_textured: Vec::with_capacity(returns),
        vertex_pixel: Vec::with_capacity(returns),
        pixel_vertex: vec![NO_VERTEX; pixels],
        triangles: Vec::with_capacity(2 * returns),
        triangle_accuracy: Vec::new(),
        triangle_flags: Vec::with_capacity(2 * returns),
        texture: eo,
        cop_m: [0.0; 3],
        scan_from_lidar: sensor.model.eo_from_lidar,
        range_noise: sensor.model.range_noise,
    }
}

/// Points: unit ray × radial range (the measured range less the sensor's range bias),
/// moved into the EO frame by `eo_from_lidar`, then projected through the EO model
/// (distortion included) to a texture coordinate.
fn place_vertices(range: &RangeFrame, sensor: &Sensor, scan: &mut TexelScan) {
    let eo_from_lidar = sensor.model.eo_from_lidar.to_homogeneous();
    let rot = eo_from_lidar.fixed_view::<3, 3>(0, 0).into_owned();
    let trans = eo_from_lidar.fixed_view::<3, 1>(0, 3).into_owned();
    let eo_cam = &sensor.model.eo;
    let eo_max_r2 = sensor.eo_max_r2;
    let (inv_w, inv_h) = (
        1.0 / f64::from(eo_cam.width),
        1.0 / f64::from(eo_cam.height),
    );
    for (pixel, &r) in range.ranges_m.iter().enumerate() {
        if !is_return(r) {
            continue;
        }
        let Some(ray) = sensor.lidar_rays.ray(pixel) else {
            continue;
        };
        // A bias as large as the range leaves no point in front of the lidar.
        let true_range_m = f64::from(r) - sensor.model.range_bias_m;
        if true_range_m.is_nan() || true_range_m <= 0.0 {
            continue;
        }
        let p_lidar =
            Vector3::new(f64::from(ray[0]), f64::from(ray[1]), f64::from(ray[2])) * true_range_m;
        let p_eo = rot * p_lidar + trans;
        let uv = eo_cam
            .project_with_domain(&p_eo, eo_max_r2)
            .ok()
            .filter(|px| eo_cam.contains_pixel(*px));
        scan.pixel_vertex[pixel] = scan.vertices.len() as u32;
        scan.vertices
            .push([p_eo.x as f32, p_eo.y as f32, p_eo.z as f32]);
        scan.vertex_pixel.push(pixel as u32);
        match uv {
            Some(px) => {
                scan.tex_coords
                    .push([((px.x + 0.5) * inv_w) as f32, ((px.y + 0.5) * inv_h) as f32]);
                scan.vertex_textured.push(true);
            }
            None => {
                scan.tex_coords.push([0.0, 0.0]);
                scan.vertex_textured.push(false);
            }
        }
    }
}

/// Two triangles for every 2x2 cell whose four vertices exist and are textured,
/// split along the diagonal with the smaller range difference; each triangle flagged
/// stretched if any of its edges is (the rule in the module documentation). Edges
/// are tested once per cell, with their ray angles from the pitch tables.
fn triangulate(range: &RangeFrame, sensor: &Sensor, config: &FuseConfig, scan: &mut TexelScan) {
    let (w, h) = (range.width as usize, range.height as usize);
    let ranges = &range.ranges_m;
    let pitch = &sensor.lidar_pitch;
    let tan_alpha = config.tan_max_incidence();
    let noise_k = config.noise_k() * std::f64::consts::SQRT_2;
    let noise = scan.range_noise;
    let stretched = |i: usize, j: usize, angle: f32| -> bool {
        let (ri, rj) = (f64::from(ranges[i]), f64::from(ranges[j]));
        let allowed =
            ri.min(rj) * f64::from(angle) * tan_alpha + noise_k * noise.sigma_at(ri.max(rj));
        (ri - rj).abs() > allowed
    };
    let usable = |scan: &TexelScan, pixel: usize| -> Option<u32> {
        let v = scan.pixel_vertex[pixel];
        (v != NO_VERTEX && scan.vertex_textured[v as usize]).then_some(v)
    };
    let flag = |s: bool| TriangleFlags(if s { TriangleFlags::STRETCHED } else { 0 });
    for v in 0..h.saturating_sub(1) {
        for u in 0..w.saturating_sub(1) {
            let (pa, pb, pc, pd) = (
                v * w + u,
                v * w + u + 1,
                (v + 1) * w + u,
                (v + 1) * w + u + 1,
            );
            let (Some(a), Some(b), Some(c), Some(d)) = (
                usable(scan, pa),
                usable(scan, pb),
                usable(scan, pc),
                usable(scan, pd),
            ) else {
                continue;
            };
            // a (u,v)   b (u+1,v)
            // c (u,v+1) d (u+1,v+1); (a, c, b) winds with its normal towards the COP.
            let right_a = stretched(pa, pb, pitch.right[pa]);
            let right_c = stretched(pc, pd, pitch.right[pc]);
            let down_a = stretched(pa, pc, pitch.down[pa]);
            let down_b = stretched(pb, pd, pitch.down[pb]);
            if (ranges[pa] - ranges[pd]).abs() <= (ranges[pb] - ranges[pc]).abs() {
                let diagonal = stretched(pa, pd, pitch.down_right[pa]);
                scan.triangles.push([a, c, d]);
                scan.triangle_flags
                    .push(flag(down_a || right_c || diagonal));
                scan.triangles.push([a, d, b]);
                scan.triangle_flags
                    .push(flag(diagonal || down_b || right_a));
            } else {
                let diagonal = stretched(pb, pc, pitch.right_to_down[pa]);
                scan.triangles.push([a, c, b]);
                scan.triangle_flags
                    .push(flag(down_a || diagonal || right_a));
                scan.triangles.push([b, c, d]);
                scan.triangle_flags
                    .push(flag(diagonal || right_c || down_b));
            }
        }
    }
}

/// Normal accuracy of every triangle (Sec. 3: cosine between the triangle normal and
/// the direction to the COP, clamped to [0, 1]); degenerate ones get 0 and a flag.
fn grade_triangles(scan: &mut TexelScan) {
    let TexelScan {
        triangles,
        vertices,
        triangle_accuracy,
        triangle_flags,
        cop_m,
        ..
    } = scan;
    triangle_accuracy.reserve_exact(triangles.len());
    for (t, flags) in triangles.iter().zip(triangle_flags.iter_mut()) {
        let [a, b, c] = t.map(|i| vertices[i as usize]);
        match normal_accuracy(a, b, c, *cop_m) {
            Some(accuracy) => triangle_accuracy.push(accuracy),
            None => {
                flags.0 |= TriangleFlags::DEGENERATE;
                triangle_accuracy.push(0.0);
            }
        }
    }
}

/// Normal accuracy of triangle `(a, b, c)` seen from `cop`: the cosine between its
/// right-handed normal `(b - a) x (c - a)` and the direction from its centroid to the
/// COP, clamped to [0, 1]. `None` for a degenerate triangle: coincident or collinear
/// vertices (sine of the angle at `a` below 1e-6, the resolution of f32 coordinates)
/// or a centroid on the COP.
///
/// Computed in f32: the vertices are f32 already and neighbouring vertices subtract
/// exactly, so the cosine is good to ~1e-6.
#[inline]
pub fn normal_accuracy(a: [f32; 3], b: [f32; 3], c: [f32; 3], cop: [f64; 3]) -> Option<f32> {
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
        cop[0] as f32 - (a[0] + b[0] + c[0]) * third,
        cop[1] as f32 - (a[1] + b[1] + c[1]) * third,
        cop[2] as f32 - (a[2] + b[2] + c[2]) * third,
    ];
    // Squared norms in f64: they can exceed f32's range for large coordinates.
    let n2 = f64::from(dot(normal, normal));
    let c2 = f64::from(dot(to_cop, to_cop));
    let e12 = f64::from(dot(e1, e1)) * f64::from(dot(e2, e2));
    // Written so that a NaN (impossible for finite input) also counts as degenerate.
    let collinear = n2.partial_cmp(&(1e-12 * e12)) != Some(std::cmp::Ordering::Greater);
    if collinear || !n2.is_finite() || !c2.is_finite() || c2 == 0.0 {
        return None;
    }
    // n2, c2 > 0 and finite, so the root is positive.
    Some((f64::from(dot(normal, to_cop)) / (n2 * c2).sqrt()).clamp(0.0, 1.0) as f32)
}

/// The pixel coordinate of a texture coordinate in an image of the given size (the
/// inverse of the mapping `fuse` uses).
pub fn pixel_of_tex_coord(uv: [f32; 2], width: u32, height: u32) -> Vector2<f64> {
    Vector2::new(
        f64::from(uv[0]) * f64::from(width) - 0.5,
        f64::from(uv[1]) * f64::from(height) - 0.5,
    )
}
