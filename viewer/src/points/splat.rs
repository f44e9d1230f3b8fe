//! Splatting a point cloud into a per-view depth map (Lechelek et al. 2019, §4): each
//! point a disk of its radius, drawn as the ellipse it projects to (semi-major axis
//! `r_proj = r f / d_z`, semi-minor `r_proj |N_z|`, the minor axis along the projected
//! normal), at constant depth with the depth test (pass 1); points classified as
//! front or back against that depth (pass 2); each class filled by pull-push (pass 3);
//! kept where pass 1 drew (pass 4); the background filling the foreground's holes
//! (pass 5).

use super::pull_push::{Sparse, pull_push};

/// A point of the proxy in the view's camera frame (x right, y down, z forward).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatPoint {
    pub position: [f32; 3],
    /// Unit normal, camera frame.
    pub normal: [f32; 3],
    /// The disk's radius (m): the footprint its range gave the texel point.
    pub radius_m: f32,
}

/// An undistorted pinhole view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatCamera {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
}

/// Points nearer than this (m) are not drawn (behind or on the eye).
pub const NEAR_M: f32 = 1.0e-3;

/// No splat is drawn larger than this many pixels across its semi-major axis, so a
/// point at the eye cannot cost a whole-screen loop.
pub const MAX_SPLAT_PX: f32 = 64.0;

/// The semi-minor axis is at least this (pixels): a disk seen edge-on (its normal
/// perpendicular to the view) still covers the pixel of its centre, which lies within
/// half a pixel of it along either axis (0.71 along a diagonal).
pub const MIN_MINOR_PX: f32 = 0.75;

/// Pass 1: per pixel, the depth of the nearest splat and which point drew it.
#[derive(Debug, Clone, PartialEq)]
pub struct SplatImage {
    pub width: usize,
    pub height: usize,
    /// z of the nearest splat (+inf where none).
    pub depth: Vec<f32>,
    /// The point that drew the pixel (`u32::MAX` where none).
    pub point: Vec<u32>,
}

impl SplatImage {
    pub fn covered(&self, i: usize) -> bool {
        self.point.get(i).is_some_and(|&p| p != u32::MAX)
    }
}

/// Where a point's centre lands, in pixels, if in front of the eye.
fn project(p: &SplatPoint, cam: &SplatCamera) -> Option<(f32, f32, f32)> {
    let [x, y, z] = p.position;
    let in_front = z.is_finite() && z > NEAR_M;
    if !in_front || !x.is_finite() || !y.is_finite() {
        return None;
    }
    Some((cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy, z))
}

/// Pass 1: draws every point as its ellipse with the depth test (nearer wins; at equal
/// depth the lower index, so the result does not depend on drawing order).
pub fn splat(points: &[SplatPoint], cam: &SplatCamera) -> SplatImage {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut image = SplatImage {
        width: w,
        height: h,
        depth: vec![f32::INFINITY; w * h],
        point: vec![u32::MAX; w * h],
    };
    for (index, p) in points.iter().enumerate() {
        let Some((u, v, z)) = project(p, cam) else {
            continue;
        };
        let r = p.radius_m.max(0.0);
        let a = (r * cam.fy / z).clamp(MIN_MINOR_PX, MAX_SPLAT_PX);
        // The minor axis along the projected normal, shortened by its z component.
        let [nx, ny, nz] = p.normal;
        let n_xy = (nx * nx + ny * ny).sqrt();
        let (ax, ay) = if n_xy > 1.0e-6 && n_xy.is_finite() {
            (nx / n_xy, ny / n_xy)
        } else {
            (1.0, 0.0)
        };
        let b = (a * nz.abs().min(1.0)).max(MIN_MINOR_PX).min(a);
        let (x0, x1) = ((u - a).floor().max(0.0), (u + a).ceil().min(w as f32 - 1.0));
        let (y0, y1) = ((v - a).floor().max(0.0), (v + a).ceil().min(h as f32 - 1.0));
        if !(x0 <= x1 && y0 <= y1) {
            continue;
        }
        for py in y0 as usize..=y1 as usize {
            for px in x0 as usize..=x1 as usize {
                let (dx, dy) = (px as f32 - u, py as f32 - v);
                // In the ellipse's frame: `minor` along the projected normal.
                let minor = dx * ax + dy * ay;
                let major = -dx * ay + dy * ax;
                if major * major / (a * a) + minor * minor / (b * b) > 1.0 {
                    continue;
                }
                let i = py * w + px;
                let d = image.depth[i];
                if z < d || (z == d && (index as u32) < image.point[i]) {
                    image.depth[i] = z;
                    image.point[i] = index as u32;
                }
            }
        }
    }
    image
}

/// Whether a depth `z` agrees with the depth `map_z` a map holds there: equal depths
/// agree; beyond `tolerance_m` plus 1 % of the depth, the point is behind (occluded).
pub fn depth_agrees(z: f32, map_z: f32, tolerance_m: f32) -> bool {
    z.is_finite() && map_z.is_finite() && (z - map_z) <= tolerance_m + 0.01 * map_z.abs()
}

/// Pass 2: which points are in front (their depth agrees with pass 1's at their
/// centre) and which are behind other splats; off-screen points are neither.
pub fn classify(points: &[SplatPoint], cam: &SplatCamera, pass1: &SplatImage) -> Vec<Option<bool>> {
    points
        .iter()
        .map(|p| {
            let (u, v, z) = project(p, cam)?;
            let (x, y) = (u.round(), v.round());
            if x < 0.0 || y < 0.0 || x >= cam.width as f32 || y >= cam.height as f32 {
                return None;
            }
            let i = y as usize * pass1.width + x as usize;
            Some(depth_agrees(z, pass1.depth[i], 2.0 * p.radius_m.max(0.0)))
        })
        .collect()
}

/// Passes 1 to 5: the view's depth map (z per pixel, `None` where no splat drew) and
/// how many points were front and back.
pub fn depth_map(points: &[SplatPoint], cam: &SplatCamera) -> (Vec<Option<f32>>, usize, usize) {
    depth_map_with(points, cam, true)
}

/// [`depth_map`], or without pass 2 (`classify` false: every point is pulled and pushed
/// together, as Marroquim et al.'s original, which the seed improves on).
pub fn depth_map_with(
    points: &[SplatPoint],
    cam: &SplatCamera,
    classify_points: bool,
) -> (Vec<Option<f32>>, usize, usize) {
    let pass1 = splat(points, cam);
    let classes: Vec<Option<bool>> = if classify_points {
        classify(points, cam, &pass1)
    } else {
        points
            .iter()
            .map(|p| project(p, cam).map(|_| true))
            .collect()
    };
    let (w, h) = (pass1.width, pass1.height);
    let mut front = Sparse::empty(w, h);
    let mut back = Sparse::empty(w, h);
    let (mut n_front, mut n_back) = (0, 0);
    for (p, class) in points.iter().zip(&classes) {
        let (Some(is_front), Some((u, v, z))) = (class, project(p, cam)) else {
            continue;
        };
        let (x, y) = (u.round() as usize, v.round() as usize);
        if *is_front {
            front.set(x, y, z, 1.0);
            n_front += 1;
        } else {
            back.set(x, y, z, 1.0);
            n_back += 1;
        }
    }
    let (front, _) = pull_push(&front);
    let (back, _) = pull_push(&back);
    let map = (0..w * h)
        .map(|i| {
            if !pass1.covered(i) {
                return None;
            }
            let (x, y) = (i % w, i / w);
            front.get(x, y).or_else(|| back.get(x, y))
        })
        .collect();
    (map, n_front, n_back)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> SplatCamera {
        SplatCamera {
            width: 32,
            height: 24,
            fx: 30.0,
            fy: 30.0,
            cx: 15.5,
            cy: 11.5,
        }
    }

    fn point(x: f32, y: f32, z: f32, r: f32) -> SplatPoint {
        SplatPoint {
            position: [x, y, z],
            normal: [0.0, 0.0, -1.0],
            radius_m: r,
        }
    }

    #[test]
    fn a_facing_disk_is_a_circle_and_an_edge_on_one_a_line() {
        // r_proj = 0.2 * 30 / 1 = 6 px.
        let image = splat(&[point(0.0, 0.0, 1.0, 0.2)], &cam());
        let covered = image.point.iter().filter(|&&p| p == 0).count();
        let area = std::f32::consts::PI * 36.0;
        assert!(
            (covered as f32 - area).abs() < 0.15 * area,
            "{covered} vs {area}"
        );
        // Its normal perpendicular to the view (along x): a thin vertical line.
        let mut edge_on = point(0.0, 0.0, 1.0, 0.2);
        edge_on.normal = [1.0, 0.0, 0.0];
        let image = splat(&[edge_on], &cam());
        let cols: std::collections::BTreeSet<usize> = (0..image.depth.len())
            .filter(|&i| image.covered(i))
            .map(|i| i % 32)
            .collect();
        assert!(!cols.is_empty() && cols.len() <= 2, "{cols:?}");
        assert!(
            image
                .depth
                .iter()
                .all(|d| d.is_finite() || *d == f32::INFINITY)
        );
    }

    #[test]
    fn equal_depths_agree_and_the_lower_index_wins_a_tie() {
        assert!(depth_agrees(2.0, 2.0, 0.0));
        assert!(!depth_agrees(2.5, 2.0, 0.01));
        assert!(!depth_agrees(f32::NAN, 2.0, 0.01));
        let pts = [point(0.0, 0.0, 1.0, 0.05), point(0.0, 0.0, 1.0, 0.05)];
        let forward = splat(&pts, &cam());
        let centre = 12 * 32 + 16;
        assert_eq!(forward.point[centre], 0);
        let classes = classify(&pts, &cam(), &forward);
        assert_eq!(classes, vec![Some(true), Some(true)]);
    }

    #[test]
    fn a_hidden_point_is_back_and_does_not_leak_into_the_front_depth() {
        // A wall of points at 1 m, one point 1 m behind it.
        let mut pts: Vec<SplatPoint> = Vec::new();
        for j in -6..=6 {
            for i in -8..=8 {
                pts.push(point(i as f32 * 0.04, j as f32 * 0.04, 1.0, 0.03));
            }
        }
        pts.push(point(0.0, 0.0, 2.0, 0.03));
        let (map, front, back) = depth_map(&pts, &cam());
        assert_eq!((front, back), (pts.len() - 1, 1));
        for d in map.iter().flatten() {
            assert!((d - 1.0).abs() < 1e-6, "{d}");
        }
        assert!(map.iter().filter(|d| d.is_some()).count() > 200);
    }

    #[test]
    fn nothing_to_draw_gives_an_empty_map() {
        let (map, front, back) = depth_map(&[], &cam());
        assert!(map.iter().all(Option::is_none));
        assert_eq!((front, back), (0, 0));
        // Behind the eye, at the eye, non-finite: not drawn.
        let pts = [
            point(0.0, 0.0, -1.0, 0.1),
            point(0.0, 0.0, 0.0, 0.1),
            point(f32::NAN, 0.0, 1.0, 0.1),
        ];
        let (map, _, _) = depth_map(&pts, &cam());
        assert!(map.iter().all(Option::is_none));
    }
}
