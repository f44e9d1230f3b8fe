//! Range-image pyramids of a scan: per lidar pixel, the point, its normal from the
//! range grid and its range noise, at full resolution and at successive halvings
//! (KinectFusion, Newcombe et al. 2011, Sec. 3.2), with the scan's EO luminance
//! pyramid for the photometric term (which samples the EO images themselves, not the
//! lidar pixels' colours). Built once per scan; used as the moving scan
//! (source) and, later, as a model-side keyframe (target) that others are projected
//! into.

use std::sync::Arc;

use nalgebra::{Vector2, Vector3};
use texel::{PinholeCamera, Pose, TexelScan};

use crate::photometric::EoPyramid;

/// Steepest incidence (ray to surface normal) at which neighbouring pixels are still
/// taken as one surface when downsampling and when differencing for normals.
const MAX_INCIDENCE_TAN: f64 = 5.67; // tan(80°)
/// Range-noise allowance of the same rule, in standard deviations.
const NOISE_ALLOWANCE_SIGMAS: f64 = 3.0;

/// Flags of a pyramid pixel.
pub const HAS_POINT: u8 = 1;
pub const HAS_NORMAL: u8 = 2;

/// What a pyramid is built with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PyramidOptions {
    /// Levels (at least one; fewer if the grid becomes smaller than 4 pixels).
    pub levels: u32,
    /// Levels of the EO luminance pyramid, kept only for the photometric term (0:
    /// none).
    pub eo_levels: u32,
    /// The finest EO level kept (the finer ones are not read).
    pub first_eo_level: u32,
}

/// Projects scan-frame points into the scan's lidar grid (full-resolution pixels).
#[derive(Debug, Clone)]
pub struct GridProjector {
    lidar_from_scan: Pose,
    camera: PinholeCamera,
    max_r2: Option<f64>,
}

impl GridProjector {
    pub fn new(camera: &PinholeCamera, scan_from_lidar: &Pose) -> Self {
        Self {
            lidar_from_scan: scan_from_lidar.inverse(),
            camera: camera.clone(),
            max_r2: camera.max_radius_squared(),
        }
    }

    pub fn lidar_from_scan(&self) -> &Pose {
        &self.lidar_from_scan
    }

    pub fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    /// The distortion model's domain bound (normalised radius squared), if any.
    pub fn max_radius_squared(&self) -> Option<f64> {
        self.max_r2
    }

    /// The full-resolution pixel of a point given in the lidar frame; `None` behind
    /// the sensor or outside the distortion model's domain.
    #[inline]
    pub fn project_lidar(&self, p: &Vector3<f64>) -> Option<Vector2<f64>> {
        self.camera.project_with_domain(p, self.max_r2).ok()
    }

    /// Angle between neighbouring full-resolution pixels, radians (`1 / f`).
    pub fn pixel_pitch_rad(&self) -> f64 {
        1.0 / self.camera.fx.max(self.camera.fy)
    }
}

/// What association reads of one pyramid pixel, packed in 28 bytes: the point, its
/// unit normal (facing the sensor; zero where there is none) and its range-noise
/// sigma. Coordinates are in the scan frame (the scan's EO optical frame).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Surfel {
    pub point: [f32; 3],
    pub normal: [f32; 3],
    /// Range noise sigma at the point, metres.
    pub sigma_m: f32,
}

/// One pyramid level. Arrays are row-major over `width x height`.
#[derive(Debug, Clone, Default)]
pub struct Level {
    pub width: usize,
    pub height: usize,
    /// `2^level`: full-resolution pixels per level pixel along each axis.
    pub scale: f64,
    pub flags: Vec<u8>,
    pub surfels: Vec<Surfel>,
    /// Range from the lidar centre, metres.
    pub ranges_m: Vec<f32>,
}

impl Level {
    fn empty(width: usize, height: usize, scale: f64) -> Self {
        let n = width * height;
        Self {
            width,
            height,
            scale,
            flags: vec![0; n],
            surfels: vec![Surfel::default(); n],
            ranges_m: vec![0.0; n],
        }
    }

    #[inline]
    pub fn has(&self, index: usize, flag: u8) -> bool {
        self.flags.get(index).is_some_and(|f| f & flag == flag)
    }

    #[inline]
    pub fn point(&self, index: usize) -> Vector3<f64> {
        let p = self.surfels[index].point;
        Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
    }

    #[inline]
    pub fn normal(&self, index: usize) -> Vector3<f64> {
        let p = self.surfels[index].normal;
        Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
    }

    #[inline]
    pub fn sigma_m(&self, index: usize) -> f32 {
        self.surfels[index].sigma_m
    }

    /// Pixels with a point and a normal, every `stride`-th in each direction.
    pub fn samples(&self, stride: usize) -> Vec<u32> {
        let stride = stride.max(1);
        let mut out = Vec::with_capacity(self.width * self.height / (stride * stride) + 1);
        for v in (0..self.height).step_by(stride) {
            for u in (0..self.width).step_by(stride) {
                let i = v * self.width + u;
                if self.has(i, HAS_POINT | HAS_NORMAL) {
                    out.push(i as u32);
                }
            }
        }
        out
    }

    /// Pixels with a point.
    pub fn point_count(&self) -> usize {
        self.flags.iter().filter(|&&f| f & HAS_POINT != 0).count()
    }
}

/// A scan's range-image pyramid. It holds what alignment reads and nothing of the
/// scan itself: a keyframe keeps its pyramid for thousands of frames, and the scan's
/// mesh and EO texture (two thirds of a pyramid's memory with the scan) are the
/// model's to keep or drop.
#[derive(Debug, Clone)]
pub struct ScanPyramid {
    pub projector: GridProjector,
    /// Finest first.
    pub levels: Vec<Level>,
    /// The EO luminance pyramid, for the photometric term.
    pub eo: Option<EoPyramid>,
}

impl ScanPyramid {
    /// Builds `levels` levels of the range image, without the EO pyramid (geometry
    /// only). `lidar` is the camera model the scan's range grid was taken with.
    pub fn build(scan: Arc<TexelScan>, lidar: &PinholeCamera, levels: u32) -> Self {
        Self::build_with(
            scan,
            lidar,
            None,
            PyramidOptions {
                levels,
                eo_levels: 0,
                first_eo_level: 0,
            },
        )
    }

    /// Builds the pyramid as `options` say; the EO luminance pyramid too when `eo`
    /// (the camera the scan's EO image was taken with) is given and
    /// `options.eo_levels` is not 0 (an EO image that does not match the camera is
    /// left out: the scan then registers on geometry alone).
    pub fn build_with(
        scan: Arc<TexelScan>,
        lidar: &PinholeCamera,
        eo: Option<&Arc<PinholeCamera>>,
        options: PyramidOptions,
    ) -> Self {
        let projector = GridProjector::new(lidar, &scan.scan_from_lidar);
        let pitch = projector.pixel_pitch_rad();
        let levels = options.levels.max(1) as usize;
        let mut out = Vec::with_capacity(levels);
        // Sec. 3.2 of KinectFusion: the finest level from the measurements...
        let mut level = finest_level(&scan, &projector);
        compute_normals(&mut level, scan.cop_m, normal_radius(0));
        out.push(level);
        // ... each coarser one by averaging 2x2 blocks within one surface.
        while out.len() < levels {
            let Some(finer) = out.last() else { break };
            if finer.width < 8 || finer.height < 8 {
                break;
            }
            let mut coarser = downsample(finer, pitch * finer.scale);
            compute_normals(&mut coarser, scan.cop_m, normal_radius(out.len()));
            out.push(coarser);
        }
        let eo = eo.filter(|_| options.eo_levels > 0).and_then(|camera| {
            EoPyramid::build(
                &scan.texture,
                Arc::clone(camera),
                options.eo_levels,
                options.first_eo_level,
            )
        });
        Self {
            projector,
            levels: out,
            eo,
        }
    }

    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// Heap bytes this pyramid keeps alive: its levels.
    pub fn heap_bytes(&self) -> usize {
        use std::mem::size_of;
        let levels: usize = self
            .levels
            .iter()
            .map(|l| {
                l.flags.capacity()
                    + l.surfels.capacity() * size_of::<Surfel>()
                    + l.ranges_m.capacity() * size_of::<f32>()
            })
            .sum();
        levels
            + self.levels.capacity() * size_of::<Level>()
            + self.eo.as_ref().map_or(0, EoPyramid::heap_bytes)
    }
}

/// Half-width of the normal-fit window at a level: 3 at full resolution (a 7x7
/// window), one less per coarser level, at least 1.
fn normal_radius(level: usize) -> usize {
    3usize.saturating_sub(level).max(1)
}

fn finest_level(scan: &TexelScan, projector: &GridProjector) -> Level {
    let (w, h) = (scan.grid_width as usize, scan.grid_height as usize);
    let mut level = Level::empty(w, h, 1.0);
    let lidar_origin = projector.lidar_from_scan.inverse().translation.vector;
    for (pixel, &vertex) in scan.pixel_vertex.iter().enumerate().take(w * h) {
        let Some(p) = scan.vertices.get(vertex as usize) else {
            continue;
        };
        if !p.iter().all(|c| c.is_finite()) {
            continue;
        }
        let pv = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        let range = (pv - lidar_origin).norm();
        level.flags[pixel] = HAS_POINT;
        level.ranges_m[pixel] = range as f32;
        let surfel = &mut level.surfels[pixel];
        surfel.point = *p;
        surfel.sigma_m = scan.range_noise.sigma_at(range) as f32;
    }
    level
}

/// Two ranges belong to one surface when they differ by less than a surface at the
/// steepest accepted incidence would make them, plus the noise allowance.
#[inline]
fn same_surface(r_a: f32, r_b: f32, sigma_a: f32, sigma_b: f32, pitch_rad: f64) -> bool {
    let (a, b) = (f64::from(r_a), f64::from(r_b));
    let sigma = f64::from(sigma_a.max(sigma_b));
    (a - b).abs() <= a.min(b) * pitch_rad * MAX_INCIDENCE_TAN + NOISE_ALLOWANCE_SIGMAS * sigma * 2.0
}

/// Halves the resolution: each coarse pixel averages the block's points that lie on
/// the same surface as the block's nearest one (so depth edges are not blurred
/// into points floating between surfaces).
fn downsample(finer: &Level, pitch_rad: f64) -> Level {
    let (w, h) = (finer.width / 2, finer.height / 2);
    let mut out = Level::empty(w, h, finer.scale * 2.0);
    for v in 0..h {
        for u in 0..w {
            let block = [
                (2 * v) * finer.width + 2 * u,
                (2 * v) * finer.width + 2 * u + 1,
                (2 * v + 1) * finer.width + 2 * u,
                (2 * v + 1) * finer.width + 2 * u + 1,
            ];
            let nearest = block
                .iter()
                .copied()
                .filter(|&i| finer.has(i, HAS_POINT))
                .min_by(|&a, &b| finer.ranges_m[a].total_cmp(&finer.ranges_m[b]));
            let Some(nearest) = nearest else { continue };
            let mut sum = Vector3::zeros();
            let (mut range, mut sigma, mut count) = (0.0f64, 0.0f64, 0.0f64);
            for &i in &block {
                if !finer.has(i, HAS_POINT)
                    || !same_surface(
                        finer.ranges_m[nearest],
                        finer.ranges_m[i],
                        finer.sigma_m(nearest),
                        finer.sigma_m(i),
                        pitch_rad,
                    )
                {
                    continue;
                }
                sum += finer.point(i);
                range += f64::from(finer.ranges_m[i]);
                sigma += f64::from(finer.sigma_m(i));
                count += 1.0;
            }
            // count >= 1: the nearest point always passes its own test.
            let k = v * w + u;
            let p = sum / count;
            out.flags[k] = HAS_POINT;
            out.ranges_m[k] = (range / count) as f32;
            let surfel = &mut out.surfels[k];
            surfel.point = [p.x as f32, p.y as f32, p.z as f32];
            surfel.sigma_m = (sigma / count) as f32;
        }
    }
    out
}

/// Summed-area tables of `[1, x, y, z, xx, xy, xz, yy, yz, zz]` over a level's
/// points, `(w + 1) x (h + 1)` entries of 10 sums each. Coordinates are taken
/// relative to `origin` (a point of the level) so the sums stay small and the
/// window covariances keep their precision.
fn moment_tables(level: &Level, origin: &[f64; 3]) -> Vec<[f64; 10]> {
    let (w, h) = (level.width, level.height);
    let mut table = vec![[0.0f64; 10]; (w + 1) * (h + 1)];
    for v in 0..h {
        let mut row = [0.0f64; 10];
        for u in 0..w {
            let c = v * w + u;
            if level.flags[c] & HAS_POINT != 0 {
                let p = level.surfels[c].point;
                let x = f64::from(p[0]) - origin[0];
                let y = f64::from(p[1]) - origin[1];
                let z = f64::from(p[2]) - origin[2];
                let m = [1.0, x, y, z, x * x, x * y, x * z, y * y, y * z, z * z];
                for (r, x) in row.iter_mut().zip(m) {
                    *r += x;
                }
            }
            let above = table[v * (w + 1) + u + 1];
            let out = &mut table[(v + 1) * (w + 1) + u + 1];
            for k in 0..10 {
                out[k] = above[k] + row[k];
            }
        }
    }
    table
}

/// Normals from the range grid: a least-squares plane through the points of a
/// `(2r + 1)²` window, fitted as depth along the viewing ray, from summed-area
/// tables in O(1) per pixel (normal estimation on organised clouds with integral
/// images, Holzer et al. 2012). A window whose points do not lie on one plane within
/// the noise (a depth edge) gives no normal. Normals face the centre of projection
/// (KinectFusion, Sec. 3.2).
fn compute_normals(level: &mut Level, cop: [f64; 3], radius: usize) {
    let (w, h) = (level.width, level.height);
    let origin = level
        .flags
        .iter()
        .position(|f| f & HAS_POINT != 0)
        .map_or([0.0; 3], |i| level.surfels[i].point.map(f64::from));
    let table = moment_tables(level, &origin);
    let cop = Vector3::new(cop[0] - origin[0], cop[1] - origin[1], cop[2] - origin[2]);
    // Fewest points for a plane fit: over half the window, and at least 5.
    let min_points = (((2 * radius + 1) * (2 * radius + 1)) / 2).max(5) as f64;
    let stride = w + 1;
    for v in 0..h {
        let (v0, v1) = (v.saturating_sub(radius), (v + radius + 1).min(h));
        for u in 0..w {
            let c = v * w + u;
            if level.flags[c] & HAS_POINT == 0 {
                continue;
            }
            let (u0, u1) = (u.saturating_sub(radius), (u + radius + 1).min(w));
            let (a, b) = (&table[v0 * stride + u0], &table[v0 * stride + u1]);
            let (cc, d) = (&table[v1 * stride + u0], &table[v1 * stride + u1]);
            let sum: [f64; 10] = std::array::from_fn(|k| d[k] - b[k] - cc[k] + a[k]);
            if sum[0] < min_points {
                continue;
            }
            let surfel = level.surfels[c];
            let point = Vector3::new(
                f64::from(surfel.point[0]) - origin[0],
                f64::from(surfel.point[1]) - origin[1],
                f64::from(surfel.point[2]) - origin[2],
            );
            let Some(normal) = fit_plane_normal(&sum, &point, &cop, f64::from(surfel.sigma_m))
            else {
                continue;
            };
            level.surfels[c].normal = [normal.x as f32, normal.y as f32, normal.z as f32];
            level.flags[c] |= HAS_NORMAL;
        }
    }
}

/// Steepest plane the fit accepts: slope of depth across the ray, tan 85°.
const MAX_FIT_SLOPE: f64 = 11.4;

/// The normal of the plane fitted to window moments `sum` as depth along the ray
/// axis `a` (from `point` to `cop`): with `C` the window covariance, the plane
/// `n·(x - mean) = 0` with `n·a = 1` that minimises the depth residuals
/// `Σ (n·(x - mean))² = nᵀ C n` is `n = C⁻¹a / (aᵀC⁻¹a)` (a Lagrange multiplier).
/// Using the adjugate (`adj C = det C · C⁻¹`) keeps it defined for exactly planar
/// windows: `y = adj(C) a`, whose `a·y` is the determinant of the covariance across
/// the ray (zero when the points are collinear), and whose residual variance is
/// `det C / a·y` (the Schur complement). `None` for too steep a plane, a singular
/// fit, or points off the plane by more than the noise allows.
fn fit_plane_normal(
    sum: &[f64; 10],
    point: &Vector3<f64>,
    cop: &Vector3<f64>,
    sigma_m: f64,
) -> Option<Vector3<f64>> {
    let n = sum[0];
    if !(n > 0.0) {
        return None;
    }
    let inv = 1.0 / n;
    let (mx, my, mz) = (sum[1] * inv, sum[2] * inv, sum[3] * inv);
    let cxx = sum[4] * inv - mx * mx;
    let cxy = sum[5] * inv - mx * my;
    let cxz = sum[6] * inv - mx * mz;
    let cyy = sum[7] * inv - my * my;
    let cyz = sum[8] * inv - my * mz;
    let czz = sum[9] * inv - mz * mz;
    let to_cop = cop - point;
    let len = to_cop.norm();
    if !(len > 0.0) || !len.is_finite() {
        return None;
    }
    let a = to_cop / len;
    // The adjugate of the symmetric covariance.
    let axx = cyy * czz - cyz * cyz;
    let axy = cxz * cyz - cxy * czz;
    let axz = cxy * cyz - cxz * cyy;
    let ayy = cxx * czz - cxz * cxz;
    let ayz = cxy * cxz - cxx * cyz;
    let azz = cxx * cyy - cxy * cxy;
    let y = Vector3::new(
        axx * a.x + axy * a.y + axz * a.z,
        axy * a.x + ayy * a.y + ayz * a.z,
        axz * a.x + ayz * a.y + azz * a.z,
    );
    let det_across = a.dot(&y);
    let c_aa = a.x * (cxx * a.x + cxy * a.y + cxz * a.z)
        + a.y * (cxy * a.x + cyy * a.y + cyz * a.z)
        + a.z * (cxz * a.x + cyz * a.y + czz * a.z);
    let trace_across = cxx + cyy + czz - c_aa;
    if !(trace_across > 0.0) || !(det_across > 1.0e-9 * trace_across * trace_across) {
        return None;
    }
    // n with n·a = 1: its length² is 1 + slope².
    let scaled = y / det_across;
    let len2 = scaled.norm_squared();
    if !(len2 < 1.0 + MAX_FIT_SLOPE * MAX_FIT_SLOPE) {
        return None;
    }
    let det_c = cxx * axx + cxy * axy + cxz * axz;
    let residual = (det_c / det_across).max(0.0);
    let allowed = NOISE_ALLOWANCE_SIGMAS * sigma_m;
    if residual > allowed * allowed * len2 {
        return None;
    }
    // len2 >= 1: the axis component is 1.
    let normal = scaled / len2.sqrt();
    normal.iter().all(|c| c.is_finite()).then_some(normal)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn plane_fits_recover_the_normal_and_refuse_edges() {
        // A 7x7 window on the plane z = 2 + 0.3 x seen from the origin.
        let mut sum = [0.0f64; 10];
        let mut add = |p: Vector3<f64>| {
            let m = [
                1.0,
                p.x,
                p.y,
                p.z,
                p.x * p.x,
                p.x * p.y,
                p.x * p.z,
                p.y * p.y,
                p.y * p.z,
                p.z * p.z,
            ];
            for (s, x) in sum.iter_mut().zip(m) {
                *s += x;
            }
        };
        for i in -3..=3 {
            for j in -3..=3 {
                let (x, y) = (0.02 * f64::from(i), 0.02 * f64::from(j));
                add(Vector3::new(x, y, 2.0 + 0.3 * x));
            }
        }
        let centre = Vector3::new(0.0, 0.0, 2.0);
        let n = fit_plane_normal(&sum, &centre, &Vector3::zeros(), 0.005).unwrap();
        let truth = Vector3::new(0.3, 0.0, -1.0).normalize();
        assert!((n - truth).norm() < 1e-9, "{n:?}");
        // A depth edge in the window: half the points 20 cm behind.
        let mut edge = [0.0f64; 10];
        for i in -3..=3 {
            for j in -3..=3 {
                let (x, y) = (0.02 * f64::from(i), 0.02 * f64::from(j));
                let z = if i > 0 { 2.2 } else { 2.0 };
                let m = [1.0, x, y, z, x * x, x * y, x * z, y * y, y * z, z * z];
                for (s, v) in edge.iter_mut().zip(m) {
                    *s += v;
                }
            }
        }
        assert!(fit_plane_normal(&edge, &centre, &Vector3::zeros(), 0.005).is_none());
        // Collinear points: no plane.
        let mut line = [0.0f64; 10];
        for i in -3..=3 {
            let x = 0.02 * f64::from(i);
            let m = [1.0, x, 0.0, 2.0, x * x, 0.0, 2.0 * x, 0.0, 0.0, 4.0];
            for (s, v) in line.iter_mut().zip(m) {
                *s += v;
            }
        }
        assert!(fit_plane_normal(&line, &centre, &Vector3::zeros(), 0.005).is_none());
    }
}
