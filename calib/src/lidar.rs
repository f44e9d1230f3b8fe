//! The board in a lidar frame, from its pixels: range-image segmentation into smooth
//! surfaces, a robust plane fit per surface, the plate found by its in-plane extent
//! (outline), board pixels away from the edges for plane constraints, and the inner
//! corners in the intensity image where the resolution allows.

use nalgebra::{Point3, Vector2, Vector3};
use texel::{PinholeCamera, RangeFrame};

use crate::config::TargetConfig;
use crate::detect::{BoardCorners, DetectParams, detect_board};
use crate::geometry::{Plane, fit_plane};
use crate::gray::GrayImage;

/// Neighbouring pixels belong to one surface when their ranges differ by less than
/// this plus [`SEGMENT_RELATIVE`] of the range (a board tilted by 60 degrees steps by
/// about 1 % of the range per pixel at 128 pixels over 45 degrees).
const SEGMENT_ABSOLUTE_M: f64 = 0.015;
const SEGMENT_RELATIVE: f64 = 0.02;

/// Smallest surface considered, pixels.
const MIN_SEGMENT_PIXELS: usize = 40;

/// The plate's measured sides may differ from the configured ones by this fraction
/// (edge pixels are mixed or missing).
const EXTENT_TOLERANCE: f64 = 0.15;

/// A board found in a lidar frame.
#[derive(Debug, Clone)]
pub struct LidarBoard {
    pub view: usize,
    /// The board plane in the lidar frame, normal pointing away from the lidar.
    pub plane: Plane,
    /// RMS distance of the board pixels from the plane, metres.
    pub plane_rms_m: f64,
    /// Interior board pixels `(u, v, range_m)` (not next to the plate's edge).
    pub pixels: Vec<(u32, u32, f64)>,
    /// Every pixel of the plate's segment (for drawing its outline).
    pub segment: Vec<(u32, u32)>,
    /// Measured plate sides, metres (long, short).
    pub extent_m: [f64; 2],
    /// The inner corners in the intensity image, when found.
    pub corners: Option<BoardCorners>,
}

/// Finds the board's plate in a lidar frame whose pixels have the rays of `camera`.
/// `Err` says why the frame does not show the whole plate.
pub fn detect_lidar_board(
    frame: &RangeFrame,
    camera: &PinholeCamera,
    target: &TargetConfig,
    view: usize,
) -> Result<LidarBoard, String> {
    let (w, h) = (frame.width as usize, frame.height as usize);
    if !frame.is_consistent() || w != camera.width as usize || h != camera.height as usize {
        return Err(format!(
            "the range frame ({}x{}) does not match the lidar calibration ({}x{})",
            frame.width, frame.height, camera.width, camera.height
        ));
    }
    // Step 1: a 3D point per returning pixel.
    let points: Vec<Option<Point3<f64>>> = (0..w * h)
        .map(|k| {
            let r = f64::from(frame.ranges_m[k]);
            if !(r.is_finite() && r > 0.0) {
                return None;
            }
            let ray = camera
                .unproject_ray(Vector2::new((k % w) as f64, (k / w) as f64))
                .ok()?;
            Some(Point3::from(ray * r))
        })
        .collect();
    // Step 2: smooth surfaces by region growing on the range image.
    let segments = segment(frame, w, h);
    // Step 3: the plate: a planar surface of the plate's size.
    let plate = [
        target.plate_m[0].max(target.plate_m[1]),
        target.plate_m[0].min(target.plate_m[1]),
    ];
    let mut best: Option<(usize, Plane, f64, [f64; 2])> = None;
    let mut nearest_miss: Option<(f64, [f64; 2])> = None;
    for (s, pixels) in segments.iter().enumerate() {
        if pixels.len() < MIN_SEGMENT_PIXELS {
            continue;
        }
        let pts: Vec<Point3<f64>> = pixels.iter().filter_map(|&k| points[k]).collect();
        let Some((plane, rms)) = robust_plane(&pts) else {
            continue;
        };
        // The outline from points on the plane: mixed pixels at the plate's edge lie
        // behind it and would widen it.
        let on_plane: Vec<Point3<f64>> = pts
            .iter()
            .copied()
            .filter(|p| plane.distance(p).abs() < (3.0 * rms).max(0.003))
            .collect();
        let extent = plate_extent(&on_plane, &plane);
        let mismatch = ((extent[0] - plate[0]) / plate[0])
            .abs()
            .max(((extent[1] - plate[1]) / plate[1]).abs());
        if mismatch <= EXTENT_TOLERANCE && rms < 0.02 + 0.01 * plane.d {
            let better = best
                .as_ref()
                .is_none_or(|b| pixels.len() > segments[b.0].len());
            if better {
                best = Some((s, plane, rms, extent));
            }
        } else if nearest_miss.is_none_or(|(m, _)| mismatch < m) {
            nearest_miss = Some((mismatch, extent));
        }
    }
    let Some((s, plane, rms, extent)) = best else {
        return Err(match nearest_miss {
            Some((_, e)) => format!(
                "no plate-sized planar surface (the nearest is {:.2} x {:.2} m, the plate \
                 is {:.2} x {:.2} m)",
                e[0], e[1], plate[0], plate[1]
            ),
            None => "no planar surface".into(),
        });
    };
    let pixels = &segments[s];
    // Step 4: the whole plate must be inside the frame.
    if pixels.iter().any(|&k| {
        let (u, v) = (k % w, k / w);
        u == 0 || v == 0 || u + 1 == w || v + 1 == h
    }) {
        return Err("the plate touches the edge of the lidar image".into());
    }
    // Step 5: interior pixels (all 8 neighbours on the plate) near the plane.
    let mut on = vec![false; w * h];
    for &k in pixels {
        on[k] = true;
    }
    let limit = (3.0 * rms).max(0.003);
    let interior: Vec<(u32, u32, f64)> = pixels
        .iter()
        .filter(|&&k| {
            let (u, v) = ((k % w) as isize, (k / w) as isize);
            (-1..=1).all(|dv| {
                (-1..=1).all(|du| {
                    let (x, y) = (u + du, v + dv);
                    x >= 0
                        && y >= 0
                        && (x as usize) < w
                        && (y as usize) < h
                        && on[y as usize * w + x as usize]
                })
            })
        })
        .filter(|&&k| points[k].is_some_and(|p| plane.distance(&p).abs() < limit))
        .map(|&k| ((k % w) as u32, (k / w) as u32, f64::from(frame.ranges_m[k])))
        .collect();
    if interior.len() < MIN_SEGMENT_PIXELS / 2 {
        return Err(format!(
            "only {} board pixels away from the plate's edges",
            interior.len()
        ));
    }
    // Step 6: intensity corners, where the resolution allows, in the plate's
    // reflectivity (its intensity with the incidence shading divided out).
    let corners = plate_reflectivity(frame, camera, &plane, pixels)
        .and_then(|g| detect_board(&g, target, &DetectParams::lidar()).ok());
    Ok(LidarBoard {
        view,
        plane,
        plane_rms_m: rms,
        pixels: interior,
        segment: pixels
            .iter()
            .map(|&k| ((k % w) as u32, (k / w) as u32))
            .collect(),
        extent_m: extent,
        corners,
    })
}

/// The smallest incidence cosine the intensity is divided by (about 84 degrees).
const MIN_INCIDENCE_COS: f64 = 0.1;

/// The intensity image with each of the plate's pixels (`pixels`, row-major indices)
/// divided by the incidence cosine of its ray on the plate's `plane`: the reflectivity
/// the lidar saw there, up to a constant. A lidar's intensity is the reflectivity times
/// that cosine (Lambertian), which falls across a tilted board; an X-corner refined by
/// gradient orthogonality in the shaded image moves towards the brighter side, the far
/// corners more than the near ones (the cosine falls faster there), which makes the
/// board look more foreshortened than it is and biases the lidar's focal length low.
fn plate_reflectivity(
    frame: &RangeFrame,
    camera: &PinholeCamera,
    plane: &Plane,
    pixels: &[usize],
) -> Option<GrayImage> {
    let mut values = frame.intensity.clone()?;
    if !frame.is_consistent() {
        return None;
    }
    let w = frame.width as usize;
    for &k in pixels {
        let Ok(ray) = camera.unproject_ray(Vector2::new((k % w) as f64, (k / w) as f64)) else {
            continue;
        };
        let cos = plane.normal.dot(&ray).abs().max(MIN_INCIDENCE_COS);
        if let Some(v) = values.get_mut(k) {
            *v = (f64::from(*v) / cos) as f32;
        }
    }
    GrayImage::from_intensity_values(w, frame.height as usize, &values)
}

/// Region growing over 4-neighbours with a range-continuity test; returns the pixel
/// indices of each region.
fn segment(frame: &RangeFrame, w: usize, h: usize) -> Vec<Vec<usize>> {
    let mut label = vec![usize::MAX; w * h];
    let mut segments = Vec::new();
    let range = |k: usize| f64::from(frame.ranges_m[k]);
    let valid = |k: usize| {
        let r = range(k);
        r.is_finite() && r > 0.0
    };
    for start in 0..w * h {
        if label[start] != usize::MAX || !valid(start) {
            continue;
        }
        let id = segments.len();
        let mut members = vec![start];
        label[start] = id;
        let mut head = 0;
        while head < members.len() {
            let k = members[head];
            head += 1;
            let (u, v) = (k % w, k / w);
            let mut neighbours = [usize::MAX; 4];
            if u > 0 {
                neighbours[0] = k - 1;
            }
            if u + 1 < w {
                neighbours[1] = k + 1;
            }
            if v > 0 {
                neighbours[2] = k - w;
            }
            if v + 1 < h {
                neighbours[3] = k + w;
            }
            for n in neighbours {
                if n == usize::MAX || label[n] != usize::MAX || !valid(n) {
                    continue;
                }
                let (a, b) = (range(k), range(n));
                if (a - b).abs() < SEGMENT_ABSOLUTE_M + SEGMENT_RELATIVE * a.min(b) {
                    label[n] = id;
                    members.push(n);
                }
            }
        }
        segments.push(members);
    }
    segments
}

/// A plane fit that drops points further than 3 robust sigmas, twice; with the RMS
/// distance of the kept points.
fn robust_plane(points: &[Point3<f64>]) -> Option<(Plane, f64)> {
    let mut plane = fit_plane(points)?;
    let mut kept: Vec<Point3<f64>> = points.to_vec();
    for _ in 0..2 {
        let mut d: Vec<f64> = points.iter().map(|p| plane.distance(p).abs()).collect();
        let mid = d.len() / 2;
        d.select_nth_unstable_by(mid, f64::total_cmp);
        let limit = (3.0 * 1.4826 * d[mid]).max(0.002);
        kept = points
            .iter()
            .copied()
            .filter(|p| plane.distance(p).abs() < limit)
            .collect();
        plane = fit_plane(&kept)?;
    }
    let rms = (kept.iter().map(|p| plane.distance(p).powi(2)).sum::<f64>()
        / kept.len().max(1) as f64)
        .sqrt();
    Some((plane, rms))
}

/// Sides (long, short) of the smallest rectangle in the plane around the points,
/// over rotations in 1-degree steps, each side widened by one pixel footprint's
/// worth (edge pixels cover half a pixel beyond their centres on each side).
fn plate_extent(points: &[Point3<f64>], plane: &Plane) -> [f64; 2] {
    let n = plane.normal;
    let helper = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = n.cross(&helper).normalize();
    let e2 = n.cross(&e1);
    let uv: Vec<Vector2<f64>> = points
        .iter()
        .map(|p| Vector2::new(p.coords.dot(&e1), p.coords.dot(&e2)))
        .collect();
    let mut best = [f64::INFINITY, f64::INFINITY];
    let mut best_area = f64::INFINITY;
    for step in 0..90 {
        let a = f64::from(step).to_radians();
        let (c, s) = (a.cos(), a.sin());
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in &uv {
            let x = c * p.x + s * p.y;
            let y = -s * p.x + c * p.y;
            lo[0] = lo[0].min(x);
            hi[0] = hi[0].max(x);
            lo[1] = lo[1].min(y);
            hi[1] = hi[1].max(y);
        }
        let (a0, a1) = (hi[0] - lo[0], hi[1] - lo[1]);
        if a0 * a1 < best_area {
            best_area = a0 * a1;
            best = [a0.max(a1), a0.min(a1)];
        }
    }
    if !best[0].is_finite() {
        return [0.0, 0.0];
    }
    // Pixel pitch on the plate: the area each point covers.
    let pitch = (best_area / points.len().max(1) as f64).max(0.0).sqrt();
    [best[0] + pitch, best[1] + pitch]
}
