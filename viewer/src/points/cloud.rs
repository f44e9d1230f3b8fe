//! A texel scan as the point proxy's points (Lechelek et al. 2019 §4): every vertex a
//! disk with the scan's area-weighted normal and the footprint its range gives it, in
//! the scan frame, with its texture coordinate. One builder for the GPU `points` mode
//! and the measurements that use the CPU reference.

use bytemuck::{Pod, Zeroable};
use nalgebra::{Point3, Vector3};
use texel::TexelScan;

/// One point as the GPU reads it (`PointIn` in `points.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct ScanPoint {
    /// Scan frame, metres.
    pub position: [f32; 3],
    /// The disk's radius, metres.
    pub radius_m: f32,
    /// Unit normal, scan frame, turned towards the acquisition centre of projection.
    pub normal: [f32; 3],
    /// 1 where the texture coordinate is meaningful (the EO camera saw the point).
    pub textured: f32,
    /// Texture coordinate in [0, 1] (pixel centre `x` at `(x + 0.5) / width`).
    pub uv: [f32; 2],
}

/// When a scan gives no pair of neighbouring returns to measure its pitch (radians).
pub const FALLBACK_PITCH_RAD: f64 = 2.0e-3;

/// The lidar's angular pitch measured on the scan itself: the median angle between
/// the rays of horizontally neighbouring returns (seen from the lidar's centre), so
/// no sensor model is needed. Finite and positive for any input.
pub fn lidar_pitch_rad(scan: &TexelScan) -> f64 {
    let origin = scan.scan_from_lidar.translation.vector;
    let width = scan.grid_width as usize;
    let ray = |pixel: usize| -> Option<Vector3<f64>> {
        let v = *scan.pixel_vertex.get(pixel)?;
        let p = scan.vertices.get(v as usize)?;
        let d = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) - origin;
        d.try_normalize(1e-12)
    };
    // At most this many pairs: a median of a few thousand is already exact to a
    // fraction of a percent.
    const MAX_PAIRS: usize = 4096;
    let step = (scan.pixel_vertex.len() / MAX_PAIRS).max(1);
    let mut angles: Vec<f64> = (0..scan.pixel_vertex.len())
        .step_by(step)
        .filter(|&p| width > 1 && (p + 1) % width != 0)
        .filter_map(|p| {
            let (a, b) = (ray(p)?, ray(p + 1)?);
            Some(a.dot(&b).clamp(-1.0, 1.0).acos())
        })
        .filter(|a| a.is_finite() && *a > 0.0)
        .collect();
    if angles.is_empty() {
        return FALLBACK_PITCH_RAD;
    }
    let mid = angles.len() / 2;
    let (_, median, _) = angles.select_nth_unstable_by(mid, f64::total_cmp);
    *median
}

/// Area-weighted vertex normals from the scan's triangles (their winding turns them
/// towards the acquisition centre); `None` for a vertex no usable triangle touches.
pub fn vertex_normals(scan: &TexelScan) -> Vec<Option<Vector3<f64>>> {
    let mut sums = vec![Vector3::<f64>::zeros(); scan.vertices.len()];
    let vertex = |k: u32| {
        scan.vertices
            .get(k as usize)
            .map(|v| Vector3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])))
    };
    for t in &scan.triangles {
        let (Some(a), Some(b), Some(c)) = (vertex(t[0]), vertex(t[1]), vertex(t[2])) else {
            continue;
        };
        let n = (b - a).cross(&(c - a));
        if !n.iter().all(|x| x.is_finite()) {
            continue;
        }
        for &k in t {
            if let Some(acc) = sums.get_mut(k as usize) {
                *acc += n;
            }
        }
    }
    sums.into_iter().map(|n| n.try_normalize(1e-12)).collect()
}

/// The scan's points: every finite vertex with a normal, its disk `range × pitch_rad`
/// in radius (the spacing of neighbouring returns at its range, so neighbouring disks
/// overlap and a surface sampled by the scan is closed).
pub fn scan_points(scan: &TexelScan, pitch_rad: f64) -> Vec<ScanPoint> {
    let pitch = if pitch_rad.is_finite() && pitch_rad > 0.0 {
        pitch_rad
    } else {
        FALLBACK_PITCH_RAD
    };
    let cop = Point3::from(scan.cop_m);
    scan.vertices
        .iter()
        .zip(vertex_normals(scan))
        .enumerate()
        .filter_map(|(i, (v, n))| {
            let n = n?;
            if !v.iter().all(|c| c.is_finite()) {
                return None;
            }
            let p = Point3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
            let range = (p - cop).norm();
            let textured = scan.vertex_textured.get(i).copied().unwrap_or(false);
            Some(ScanPoint {
                position: *v,
                radius_m: (range * pitch) as f32,
                normal: [n.x as f32, n.y as f32, n.z as f32],
                textured: if textured { 1.0 } else { 0.0 },
                uv: scan.tex_coords.get(i).copied().unwrap_or([0.0, 0.0]),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use texel::{EoFrame, Pose, RangeNoise};

    /// A flat wall at z = 2 m seen by a 5 x 4 grid with a pitch of 0.01 rad.
    fn wall() -> TexelScan {
        let (w, h) = (5u32, 4u32);
        let mut vertices = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let (ax, ay) = ((x as f64 - 2.0) * 0.01, (y as f64 - 1.5) * 0.01);
                vertices.push([(2.0 * ax.tan()) as f32, (2.0 * ay.tan()) as f32, 2.0]);
            }
        }
        let mut triangles = Vec::new();
        for y in 0..h - 1 {
            for x in 0..w - 1 {
                let i = y * w + x;
                // Winding with the normal towards the camera (-z).
                triangles.push([i, i + w, i + 1]);
                triangles.push([i + 1, i + w, i + w + 1]);
            }
        }
        let n = vertices.len();
        TexelScan {
            timestamp_ns: 0,
            seq: 0,
            grid_width: w,
            grid_height: h,
            tex_coords: vec![[0.5, 0.5]; n],
            vertex_textured: vec![true; n],
            vertex_pixel: (0..n as u32).collect(),
            pixel_vertex: (0..n as u32).collect(),
            triangle_accuracy: vec![1.0; triangles.len()],
            triangle_flags: vec![Default::default(); triangles.len()],
            triangles,
            vertices,
            texture: Arc::new(EoFrame {
                width: 1,
                height: 1,
                rgb: vec![1, 2, 3],
                timestamp_ns: 0,
                exposure: None,
            }),
            cop_m: [0.0; 3],
            scan_from_lidar: Pose::identity(),
            range_noise: RangeNoise {
                sigma_m: 0.01,
                sigma_per_m: 0.0,
            },
        }
    }

    #[test]
    fn a_wall_gives_its_pitch_normals_towards_the_camera_and_disks_that_close_it() {
        let scan = wall();
        let pitch = lidar_pitch_rad(&scan);
        assert!((pitch - 0.01).abs() < 1e-4, "{pitch}");
        let points = scan_points(&scan, pitch);
        assert_eq!(points.len(), 20);
        for p in &points {
            assert!(p.normal[2] < -0.999, "{:?}", p.normal);
            assert!((p.radius_m - 0.02).abs() < 1e-3, "{}", p.radius_m);
        }
    }

    #[test]
    fn a_scan_without_neighbours_or_triangles_stays_finite() {
        let mut scan = wall();
        scan.triangles.clear();
        scan.pixel_vertex = vec![texel::scan::NO_VERTEX; scan.pixel_vertex.len()];
        assert_eq!(lidar_pitch_rad(&scan), FALLBACK_PITCH_RAD);
        assert!(scan_points(&scan, f64::NAN).is_empty());
        let mut nan = wall();
        nan.vertices[0] = [f32::NAN, 0.0, 1.0];
        let points = scan_points(&nan, lidar_pitch_rad(&nan));
        assert!(
            points
                .iter()
                .all(|p| p.position.iter().all(|c| c.is_finite()))
        );
        assert!(points.iter().all(|p| p.radius_m.is_finite()));
    }
}
