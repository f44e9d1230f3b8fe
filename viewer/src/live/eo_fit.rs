//! Owns recovering a scan's EO camera (intrinsics and `plumb_bob` distortion) from its
//! vertices and texture coordinates, for viewers that get scans but no calibration.
//! With skew 0 each pixel axis is linear in its focal length times the distortion
//! coefficients: two linear least squares problems, no iteration, no initial guess.

use nalgebra::{DMatrix, DVector, Vector2, Vector3};
use texel::camera::{Distortion, PinholeCamera};
use texel::distortion::PlumbBob;

/// Fewest usable vertices a fit accepts: 7 unknowns per axis, and several times as
/// many equations keep a handful of stray vertices from deciding the model.
pub const MIN_FIT_VERTICES: usize = 32;

/// Most vertices (evenly strided) that enter the least squares systems: 7 unknowns
/// are pinned down long before this, and it bounds the cost of the decomposition for
/// large lidars. The reported error is still over every usable vertex.
const MAX_SYSTEM_ROWS: usize = 4096;

/// Vertices nearer the camera plane (metres) are skipped, as the field-of-view fit
/// does: their normalised coordinates carry no useful precision.
const MIN_DEPTH_M: f64 = 1.0e-3;

/// Smallest ratio of the smallest to the largest singular value of a column-scaled
/// system that is still solved (about 1e-2 for a 52 degree camera's full image: the
/// radial columns x r², x r⁴, x r⁶ are correlated). Inputs are f32 (relative precision
/// 6e-8); below 1e-6 rounding alone would move the weakest combination by several
/// percent, so the fit falls back to a model with fewer terms.
const MIN_RECIPROCAL_CONDITION: f64 = 1.0e-6;

/// Smallest spread of a coordinate, relative to its RMS, a focal length is fitted
/// over: about 1e3 times f32 rounding, so the slope is not fitted to rounding noise.
const MIN_RELATIVE_SPREAD: f64 = 1.0e-4;

/// A fitted distortion moving no vertex by more than this (pixels) is reported as none:
/// f32 texture coordinates resolve ~1e-3 px on the largest accepted image (16384 px),
/// and 0.01 px is invisible when texturing. The coefficients are judged by their
/// effect, not their size, because correlated radial terms can cancel each other.
const NEGLIGIBLE_DISTORTION_PX: f64 = 1.0e-2;

/// The EO camera recovered from a scan.
#[derive(Debug, Clone, PartialEq)]
pub struct EoFit {
    /// The camera (skew 0), validated, whose distortion domain holds every vertex used.
    pub camera: PinholeCamera,
    /// RMS distance, pixels, between the vertices projected by `camera` and their
    /// texture coordinates.
    pub rms_px: f64,
    /// How many textured vertices the fit used.
    pub vertices: usize,
}

/// A textured vertex: normalised coordinates and the pixel (centres at integers).
#[derive(Debug, Clone, Copy)]
struct Sample {
    x: f64,
    y: f64,
    px: f64,
    py: f64,
}

/// Fits the EO camera that textured `scan`: `plumb_bob` with k3, then without, then an
/// ideal pinhole, taking the first model the data determines and that validates.
/// `None` when there are too few usable vertices or no model fits.
pub fn eo_camera_of_scan(scan: &texel::TexelScan) -> Option<EoFit> {
    let (width, height) = (scan.texture.width, scan.texture.height);
    let samples = samples_of(scan);
    if samples.len() < MIN_FIT_VERTICES {
        return None;
    }
    [true, false]
        .into_iter()
        .filter_map(|with_k3| fit_plumb_bob(&samples, with_k3))
        .map(Distortion::PlumbBob)
        .chain(std::iter::once(Distortion::None))
        .find_map(|distortion| finish(&samples, width, height, distortion))
}

/// The usable textured vertices: in front of the camera, finite throughout.
fn samples_of(scan: &texel::TexelScan) -> Vec<Sample> {
    let (w, h) = (
        f64::from(scan.texture.width),
        f64::from(scan.texture.height),
    );
    scan.vertices
        .iter()
        .zip(&scan.tex_coords)
        .zip(&scan.vertex_textured)
        .filter(|(_, textured)| **textured)
        .filter_map(|((v, t), _)| {
            let [x, y, z] = v.map(f64::from);
            // Written so that a NaN depth fails too.
            if !(z > MIN_DEPTH_M && z.is_finite()) {
                return None;
            }
            let s = Sample {
                x: x / z,
                y: y / z,
                px: f64::from(t[0]) * w - 0.5,
                py: f64::from(t[1]) * h - 0.5,
            };
            [s.x, s.y, s.px, s.py]
                .iter()
                .all(|c| c.is_finite())
                .then_some(s)
        })
        .collect()
}

/// The distortion coefficients, from the two axes' linear systems. Unknowns per axis:
/// `[f, f k1, f k2, f k3, f p1, f p2, c]` (k3's column left out when `!with_k3`).
fn fit_plumb_bob(samples: &[Sample], with_k3: bool) -> Option<PlumbBob> {
    let stride = samples.len().div_ceil(MAX_SYSTEM_ROWS).max(1);
    let rows: Vec<Sample> = samples.iter().step_by(stride).copied().collect();
    let columns: &[usize] = if with_k3 {
        &[0, 1, 2, 3, 4, 5, 6]
    } else {
        &[0, 1, 2, 4, 5, 6]
    };
    let powers = |s: &Sample| {
        let r2 = s.x * s.x + s.y * s.y;
        (r2, r2 * r2, r2 * r2 * r2, 2.0 * s.x * s.y)
    };
    let u = solve(&rows, columns, |s| {
        let ((r2, r4, r6, xy2), x) = (powers(s), s.x);
        (
            [x, x * r2, x * r4, x * r6, xy2, r2 + 2.0 * x * x, 1.0],
            s.px,
        )
    })?;
    let v = solve(&rows, columns, |s| {
        let ((r2, r4, r6, xy2), y) = (powers(s), s.y);
        (
            [y, y * r2, y * r4, y * r6, r2 + 2.0 * y * y, xy2, 1.0],
            s.py,
        )
    })?;
    let (fx, fy) = (u[0], v[0]);
    if !(fx > 0.0 && fy > 0.0) {
        return None;
    }
    // Each axis measures every coefficient; they agree on exact data, and on noisy
    // data the mean of the two independent estimates has half the variance.
    let mean = |i: usize| 0.5 * (u[i] / fx + v[i] / fy);
    // `D` order is [k1, k2, p1, p2, k3].
    let d = PlumbBob::from_slice(&[mean(1), mean(2), mean(4), mean(5), mean(3)])?;
    d.is_finite().then_some(d)
}

/// Least squares for the chosen columns of `row`'s terms; the unknowns come back in
/// their column slots (0 for columns left out). `None` when ill-conditioned.
fn solve(
    rows: &[Sample],
    columns: &[usize],
    row: impl Fn(&Sample) -> ([f64; 7], f64),
) -> Option<[f64; 7]> {
    let mut a = DMatrix::<f64>::zeros(rows.len(), columns.len());
    let mut b = DVector::<f64>::zeros(rows.len());
    for (i, s) in rows.iter().enumerate() {
        let (terms, target) = row(s);
        for (j, &c) in columns.iter().enumerate() {
            a[(i, j)] = terms[c];
        }
        b[i] = target;
    }
    // Unit-norm columns: the terms span orders of magnitude (x r⁶ against 1), and the
    // conditioning test should measure correlation between terms, not their units.
    let mut scale = Vec::with_capacity(columns.len());
    for mut column in a.column_iter_mut() {
        let norm = column.norm();
        if !(norm > 0.0 && norm.is_finite()) {
            return None;
        }
        column /= norm;
        scale.push(norm);
    }
    // SVD rather than normal equations, which would square the condition number.
    let svd = a.try_svd(true, true, f64::EPSILON, 1000)?;
    let (max, min) = (svd.singular_values.max(), svd.singular_values.min());
    let conditioned = min > max * MIN_RECIPROCAL_CONDITION;
    if !conditioned {
        return None;
    }
    let z = svd.solve(&b, 0.0).ok()?;
    let mut out = [0.0; 7];
    for ((&c, zj), sj) in columns.iter().zip(z.iter()).zip(&scale) {
        out[c] = zj / sj;
    }
    out.iter().all(|c| c.is_finite()).then_some(out)
}

/// Fits fx, cx, fy, cy for a fixed distortion, drops a negligible distortion, then
/// validates the camera and measures its reprojection error.
fn finish(samples: &[Sample], width: u32, height: u32, distortion: Distortion) -> Option<EoFit> {
    let distorted: Vec<Vector2<f64>> = samples
        .iter()
        .map(|s| {
            let p = Vector2::new(s.x, s.y);
            match &distortion {
                Distortion::None => p,
                Distortion::PlumbBob(d) => d.distort(p),
            }
        })
        .collect();
    // Refitting the linear intrinsics with the averaged coefficients keeps them
    // consistent with the distortion actually reported.
    let (fx, cx) = line_fit(distorted.iter().zip(samples).map(|(d, s)| (d.x, s.px)))?;
    let (fy, cy) = line_fit(distorted.iter().zip(samples).map(|(d, s)| (d.y, s.py)))?;
    let camera = PinholeCamera {
        width,
        height,
        fx,
        fy,
        cx,
        cy,
        skew: 0.0,
        distortion,
    };
    camera.validate().ok()?;
    if matches!(distortion, Distortion::PlumbBob(_)) {
        let shift = distorted
            .iter()
            .zip(samples)
            .map(|(d, s)| (fx * (d.x - s.x)).abs().max((fy * (d.y - s.y)).abs()))
            .fold(0.0, f64::max);
        if shift < NEGLIGIBLE_DISTORTION_PX {
            return finish(samples, width, height, Distortion::None);
        }
    }
    // Fusion textures only vertices inside the true model's domain, so a fit whose
    // domain leaves one out is not that model (and cannot project it).
    let max_r2 = camera.max_radius_squared();
    let mut sum = 0.0;
    for s in samples {
        let p = camera
            .project_with_domain(&Vector3::new(s.x, s.y, 1.0), max_r2)
            .ok()?;
        sum += (p - Vector2::new(s.px, s.py)).norm_squared();
    }
    let rms_px = (sum / samples.len() as f64).sqrt();
    rms_px.is_finite().then_some(EoFit {
        camera,
        rms_px,
        vertices: samples.len(),
    })
}

/// `(slope, intercept)` of `y = slope x + intercept` by least squares, on centred
/// sums so that the intercept does not cost the slope precision.
fn line_fit(pairs: impl Iterator<Item = (f64, f64)> + Clone) -> Option<(f64, f64)> {
    let (n, sx, sy, sx2) = pairs.clone().fold((0.0, 0.0, 0.0, 0.0), |a, (x, y)| {
        (a.0 + 1.0, a.1 + x, a.2 + y, a.3 + x * x)
    });
    let (mx, my) = (sx / n, sy / n);
    let (sxx, sxy) = pairs.fold((0.0, 0.0), |(sxx, sxy), (x, y)| {
        (sxx + (x - mx) * (x - mx), sxy + (x - mx) * (y - my))
    });
    let (slope, intercept) = (sxy / sxx, my - sxy / sxx * mx);
    let spread = sxx > MIN_RELATIVE_SPREAD * MIN_RELATIVE_SPREAD * sx2;
    (n >= 2.0 && spread && slope.is_finite() && intercept.is_finite()).then_some((slope, intercept))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    /// The first scan of the box scene seen by the test sensor with `eo` as its camera.
    fn scan_with(eo: PinholeCamera) -> texel::TexelScan {
        let mut model = crate::scenes::test_sensor().model;
        model.eo = eo;
        let sensor = texel::Sensor::new(model);
        let model = crate::scenes::model_of(
            &crate::scenes::box_scene(),
            &sensor,
            &crate::scenes::box_scene_poses(),
            &texel::Pose::identity(),
        );
        texel::TexelScan::clone(model.scans()[0].scan.as_ref().unwrap())
    }

    fn distorted_camera() -> PinholeCamera {
        PinholeCamera {
            fx: 126.0,
            fy: 121.5,
            cx: 83.2,
            cy: 56.1,
            // D = [k1, k2, p1, p2, k3]
            distortion: Distortion::PlumbBob(
                PlumbBob::from_slice(&[-0.12, 0.03, 0.001, -0.0005, 0.0]).unwrap(),
            ),
            ..crate::scenes::test_sensor().model.eo
        }
    }

    /// Largest distance (pixels) from a textured vertex's projection to its texel.
    fn max_reprojection_px(scan: &texel::TexelScan, camera: &PinholeCamera) -> f64 {
        samples_of(scan)
            .iter()
            .map(|s| {
                let p = camera.project(&Vector3::new(s.x, s.y, 1.0)).unwrap();
                (p - Vector2::new(s.px, s.py)).norm()
            })
            .fold(0.0, f64::max)
    }

    /// K within 1e-3 px: the fits reach ~1e-6 px on these exact (f32-rounded) scans,
    /// so this leaves a wide margin and stays far inside a twentieth of a pixel.
    fn assert_intrinsics_near(got: &PinholeCamera, truth: &PinholeCamera) {
        let (g, t) = (got.k_row_major(), truth.k_row_major());
        assert!(
            g.iter().zip(t).all(|(g, t)| (g - t).abs() < 1e-3),
            "{g:?} vs {t:?}"
        );
    }

    #[test]
    fn an_ideal_camera_is_recovered() {
        let truth = crate::scenes::test_sensor().model.eo;
        let scan = scan_with(truth.clone());
        let fit = eo_camera_of_scan(&scan).unwrap();
        assert_eq!(fit.camera.distortion, Distortion::None);
        assert_intrinsics_near(&fit.camera, &truth);
        assert!(fit.rms_px < 1e-3 && fit.vertices >= MIN_FIT_VERTICES);
    }

    #[test]
    fn a_distorted_off_centre_camera_is_recovered() {
        let truth = distorted_camera();
        let scan = scan_with(truth.clone());
        let fit = eo_camera_of_scan(&scan).unwrap();
        let c = &fit.camera;
        let (Distortion::PlumbBob(got), Distortion::PlumbBob(want)) =
            (c.distortion, truth.distortion)
        else {
            panic!("distortion lost: {:?}", c.distortion);
        };
        // Measured within 4e-7 (k2, the least determined); what matters is below.
        for (g, w) in got.to_array().into_iter().zip(want.to_array()) {
            assert!((g - w).abs() < 1e-4, "{got:?} vs {want:?}");
        }
        assert_intrinsics_near(c, &truth);
        assert!(max_reprojection_px(&scan, c) < 0.05);
        assert!(fit.rms_px < 1e-3);
    }

    #[test]
    fn too_few_or_degenerate_vertices_give_nothing() {
        let full = scan_with(distorted_camera());
        let mut scan = full.clone();
        let mut kept = 0;
        for textured in scan.vertex_textured.iter_mut().filter(|t| **t) {
            *textured = kept < MIN_FIT_VERTICES - 1;
            kept += 1;
        }
        assert!(kept >= MIN_FIT_VERTICES);
        assert_eq!(eo_camera_of_scan(&scan), None);
        // One row of an ideal co-boresighted lidar shares its y/z: fy is undetermined.
        let mut scan = full;
        let (width, row) = (scan.grid_width, scan.grid_height / 2);
        for (textured, pixel) in scan.vertex_textured.iter_mut().zip(&scan.vertex_pixel) {
            *textured &= pixel / width == row;
        }
        assert!(scan.vertex_textured.iter().filter(|t| **t).count() >= MIN_FIT_VERTICES);
        assert_eq!(eo_camera_of_scan(&scan), None);
        scan.vertex_textured.iter_mut().for_each(|t| *t = false);
        assert_eq!(eo_camera_of_scan(&scan), None);
    }

    #[test]
    fn non_finite_vertices_are_skipped() {
        let clean = scan_with(distorted_camera());
        let mut scan = clean.clone();
        let textured: Vec<usize> = (0..scan.vertex_count())
            .filter(|&i| scan.vertex_textured[i])
            .collect();
        scan.vertices[textured[0]] = [f32::NAN, 0.0, 1.0];
        scan.vertices[textured[1]] = [0.0, f32::INFINITY, 1.0];
        scan.vertices[textured[2]] = [0.0, 0.0, f32::NAN];
        scan.vertices[textured[3]] = [0.1, 0.1, 0.0];
        scan.tex_coords[textured[4]] = [f32::NAN, 0.5];
        let fit = eo_camera_of_scan(&scan).unwrap();
        let reference = eo_camera_of_scan(&clean).unwrap();
        assert_eq!(fit.vertices, reference.vertices - 5);
        assert!(fit.rms_px.is_finite() && fit.rms_px < 1e-3);
        assert!(max_reprojection_px(&clean, &fit.camera) < 0.05);
        // Every vertex poisoned: nothing usable, no NaN camera.
        scan.vertices.iter_mut().for_each(|v| v[2] = f32::NAN);
        assert_eq!(eo_camera_of_scan(&scan), None);
    }
}
