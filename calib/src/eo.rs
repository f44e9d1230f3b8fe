//! EO camera intrinsics and `plumb_bob` distortion from checkerboard views: Zhang's
//! closed form, then Levenberg-Marquardt over all views (intrinsics + one pose per
//! view), one round of outlier rejection, and the covariance at the solution.

use nalgebra::{Point3, Vector2};
use texel::{PinholeCamera, Pose};

use crate::config::{SolverConfig, TargetConfig};
use crate::detect::BoardCorners;
use crate::error::CalibError;
use crate::geometry::{
    Intrinsics, UNPROJECTABLE_PX, camera_of, homography, params_from_pose, pose_from_params,
    project,
};
use crate::lm::{Block, LmOptions, Problem, covariance};
use crate::zhang;

/// Fewest views a calibration accepts.
pub const MIN_VIEWS: usize = 3;

/// Views whose boards all tilt less than this are fronto-parallel.
pub const FRONTO_PARALLEL_DEG: f64 = 6.0;

/// Corners whose residual exceeds this many robust standard deviations (and 1 px)
/// are dropped as misdetections before the final solve.
const OUTLIER_SIGMAS: f64 = 5.0;

/// One view's detected board.
#[derive(Debug, Clone)]
pub struct EoObservation {
    /// Index of the view in the calibration's input.
    pub view: usize,
    pub corners: BoardCorners,
}

/// Reprojection residuals of one view.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewResidual {
    pub view: usize,
    pub rms_px: f64,
    pub max_px: f64,
    /// `(i, j, residual)`: projected minus detected, pixels.
    pub residuals: Vec<(usize, usize, Vector2<f64>)>,
}

/// The EO calibration.
#[derive(Debug, Clone)]
pub struct EoSolution {
    pub camera: PinholeCamera,
    /// `[fx, fy, cx, cy, k1, k2, p1, p2, k3]`.
    pub intrinsics: Intrinsics,
    /// Standard deviation of each intrinsic (0 for a fixed one).
    pub intrinsics_std: Intrinsics,
    /// `camera_from_board` of each observation, in input order.
    pub poses: Vec<Pose>,
    pub tilt_deg: Vec<f64>,
    pub rms_px: f64,
    pub per_view: Vec<ViewResidual>,
    pub iterations: usize,
    pub converged: bool,
    pub outliers_dropped: usize,
    /// Correspondences of each observation and which of them were kept.
    pub(crate) data: Vec<ViewData>,
    pub(crate) masks: Vec<Vec<bool>>,
}

/// Board-plane points and pixels of an observation.
fn correspondences(corners: &BoardCorners, target: &TargetConfig) -> ViewData {
    let mut ids = Vec::new();
    let mut plane = Vec::new();
    let mut image = Vec::new();
    for (i, j, p) in corners.iter() {
        let q = target.corner_point(i, j);
        ids.push((i, j));
        plane.push(Vector2::new(q[0], q[1]));
        image.push(p);
    }
    (ids, plane, image)
}

/// Calibrates the EO camera of a `width x height` image from board observations.
pub fn calibrate_eo(
    observations: &[EoObservation],
    target: &TargetConfig,
    width: u32,
    height: u32,
    solver: &SolverConfig,
) -> Result<EoSolution, CalibError> {
    if observations.len() < MIN_VIEWS {
        return Err(CalibError::TooFewViews {
            usable: observations.len(),
            total: observations.len(),
            needed: MIN_VIEWS,
            nx: target.nx(),
            ny: target.ny(),
            reasons: String::new(),
        });
    }
    let centre = (
        (f64::from(width) - 1.0) * 0.5,
        (f64::from(height) - 1.0) * 0.5,
    );
    // Step 1: a homography per view (Zhang §2.3).
    let data: Vec<_> = observations
        .iter()
        .map(|o| correspondences(&o.corners, target))
        .collect();
    let homographies: Vec<_> = data
        .iter()
        .map(|(_, plane, image)| homography(plane, image))
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| CalibError::Diverged {
            stage: "EO homography",
            detail: "a view's corners do not determine a homography".into(),
        })?;
    // Step 2: closed-form intrinsics (Zhang §3.1); judge tilt with them, or with a
    // 60-degree field of view when they cannot be had.
    let init = zhang::intrinsics(&homographies, centre);
    let focal_guess = init.map_or(f64::from(width.max(height)) * 0.87, |k| 0.5 * (k[0] + k[1]));
    let tilt_deg: Vec<f64> = homographies
        .iter()
        .map(|h| zhang::tilt_deg(h, focal_guess, centre).unwrap_or(0.0))
        .collect();
    let max_tilt = tilt_deg.iter().copied().fold(0.0f64, f64::max);
    if max_tilt < FRONTO_PARALLEL_DEG {
        return Err(CalibError::FrontoParallel {
            views: observations.len(),
            max_tilt_deg: max_tilt,
        });
    }
    let k = init.ok_or(CalibError::TooLittleTilt {
        views: observations.len(),
        relative_std_percent: f64::INFINITY,
        limit_percent: solver.max_focal_relative_std * 100.0,
        max_tilt_deg: max_tilt,
    })?;
    // Step 3: each view's pose from its homography (Zhang eq. 2).
    let poses: Vec<Pose> = homographies
        .iter()
        .map(|h| zhang::pose_from_homography(h, k))
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| CalibError::Diverged {
            stage: "EO initial pose",
            detail: "a homography gives no pose".into(),
        })?;
    // Step 4: Levenberg-Marquardt over intrinsics, distortion and poses (Zhang §3.3),
    // then once more without corners that do not fit.
    let mut x: Vec<f64> = vec![k[0], k[1], k[2], k[3], 0.0, 0.0, 0.0, 0.0, 0.0];
    for p in &poses {
        x.extend_from_slice(&params_from_pose(p));
    }
    let mut masks: Vec<Vec<bool>> = data
        .iter()
        .map(|(ids, _, _)| vec![true; ids.len()])
        .collect();
    let options = LmOptions {
        max_iterations: solver.max_iterations,
        ..LmOptions::default()
    };
    let mut dropped = 0;
    let mut result = None;
    for round in 0..2 {
        let problem = build_problem(&data, &masks, solver);
        let r = problem.solve(&x, &options);
        x.clone_from(&r.x);
        if round == 0 {
            let residuals = problem.residuals(&x);
            let all: Vec<f64> = residuals
                .iter()
                .flat_map(|r| r.chunks_exact(2).map(|c| c[0].hypot(c[1])))
                .collect();
            let robust = median(&all) * 1.4826;
            let limit = (OUTLIER_SIGMAS * robust).max(1.0);
            let mut any = false;
            for (v, r) in residuals.iter().enumerate() {
                let active: Vec<usize> = (0..masks[v].len()).filter(|&c| masks[v][c]).collect();
                for (n, c) in r.chunks_exact(2).enumerate() {
                    if c[0].hypot(c[1]) > limit {
                        masks[v][active[n]] = false;
                        dropped += 1;
                        any = true;
                    }
                }
            }
            if !any {
                result = Some((r, problem.fixed.clone()));
                break;
            }
        } else {
            result = Some((r, problem.fixed.clone()));
        }
    }
    let Some((result, fixed)) = result else {
        return Err(CalibError::Diverged {
            stage: "EO bundle adjustment",
            detail: "no solve ran".into(),
        });
    };
    if !result.x.iter().all(|v| v.is_finite()) {
        return Err(CalibError::Diverged {
            stage: "EO bundle adjustment",
            detail: "non-finite parameters".into(),
        });
    }
    // Step 5: uncertainty from the covariance at the solution.
    let cov = covariance(&result, &fixed);
    let mut intrinsics = [0.0; 9];
    let mut intrinsics_std = [0.0; 9];
    for i in 0..9 {
        intrinsics[i] = result.x[i];
        intrinsics_std[i] = cov[(i, i)].max(0.0).sqrt();
    }
    let camera = camera_of(width, height, &intrinsics);
    if camera.validate().is_err() || !(intrinsics[0] > 0.0 && intrinsics[1] > 0.0) {
        return Err(CalibError::Diverged {
            stage: "EO bundle adjustment",
            detail: format!(
                "the solution is not a camera (fx {}, fy {})",
                intrinsics[0], intrinsics[1]
            ),
        });
    }
    let focal_rel = (intrinsics_std[0] / intrinsics[0]).max(intrinsics_std[1] / intrinsics[1]);
    if !(focal_rel <= solver.max_focal_relative_std) {
        return Err(CalibError::TooLittleTilt {
            views: observations.len(),
            relative_std_percent: focal_rel * 100.0,
            limit_percent: solver.max_focal_relative_std * 100.0,
            max_tilt_deg: max_tilt,
        });
    }
    let poses: Vec<Pose> = (0..observations.len())
        .map(|v| pose_from_params(&result.x[9 + 6 * v..15 + 6 * v]))
        .collect();
    let per_view: Vec<ViewResidual> = observations
        .iter()
        .zip(&data)
        .zip(&poses)
        .map(|((o, (ids, plane, image)), pose)| {
            view_residual(o.view, &intrinsics, pose, ids, plane, image)
        })
        .collect();
    let (sum, n) = per_view.iter().fold((0.0, 0usize), |(s, n), v| {
        (
            s + v.residuals.iter().map(|r| r.2.norm_squared()).sum::<f64>(),
            n + v.residuals.len(),
        )
    });
    Ok(EoSolution {
        camera,
        intrinsics,
        intrinsics_std,
        poses,
        tilt_deg,
        rms_px: (sum / n.max(1) as f64).sqrt(),
        per_view,
        iterations: result.iterations,
        converged: result.converged,
        outliers_dropped: dropped,
        data,
        masks,
    })
}

fn median(v: &[f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut v = v.to_vec();
    let mid = v.len() / 2;
    v.select_nth_unstable_by(mid, f64::total_cmp);
    v[mid]
}

/// Parameters held fixed by the solver settings.
pub(crate) fn fixed_intrinsics(solver: &SolverConfig) -> [bool; 9] {
    [
        false,
        false,
        false,
        false,
        false,
        false,
        !solver.estimate_tangential,
        !solver.estimate_tangential,
        !solver.estimate_k3,
    ]
}

pub(crate) type ViewData = (Vec<(usize, usize)>, Vec<Vector2<f64>>, Vec<Vector2<f64>>);

fn build_problem(
    data: &[ViewData],
    masks: &[Vec<bool>],
    solver: &SolverConfig,
) -> Problem<'static> {
    let n = 9 + 6 * data.len();
    let mut fixed = vec![false; n];
    fixed[..9].copy_from_slice(&fixed_intrinsics(solver));
    let mut scale = vec![0.1; n];
    for s in scale.iter_mut().take(4) {
        *s = 100.0;
    }
    for s in scale.iter_mut().take(9).skip(4) {
        *s = 1.0;
    }
    Problem {
        blocks: eo_blocks(data, masks, 1.0),
        scale,
        fixed,
    }
}

/// One residual block per view: reprojection errors of its kept corners divided by
/// `sigma_px`, over parameters `0..9` (intrinsics) and `9 + 6v..15 + 6v` (the pose).
pub(crate) fn eo_blocks(
    data: &[ViewData],
    masks: &[Vec<bool>],
    sigma_px: f64,
) -> Vec<Block<'static>> {
    let inv = 1.0 / sigma_px.max(1.0e-6);
    data.iter()
        .zip(masks)
        .enumerate()
        .map(|(v, ((_, plane, image), mask))| {
            let points: Vec<(Vector2<f64>, Vector2<f64>)> = plane
                .iter()
                .zip(image)
                .zip(mask)
                .filter(|(_, m)| **m)
                .map(|((p, q), _)| (*p, *q))
                .collect();
            let count = points.len();
            let mut params: Vec<usize> = (0..9).collect();
            params.extend(9 + 6 * v..15 + 6 * v);
            Block {
                params,
                residuals: 2 * count,
                class: 0,
                eval: Box::new(move |p: &[f64], r: &mut [f64]| {
                    let pose = pose_from_params(&p[9..15]);
                    for (n, (board, pixel)) in points.iter().enumerate() {
                        let c = pose * Point3::new(board.x, board.y, 0.0);
                        match project(&p[..9], &c.coords) {
                            Some(q) => {
                                r[2 * n] = (q.x - pixel.x) * inv;
                                r[2 * n + 1] = (q.y - pixel.y) * inv;
                            }
                            None => {
                                r[2 * n] = UNPROJECTABLE_PX;
                                r[2 * n + 1] = UNPROJECTABLE_PX;
                            }
                        }
                    }
                }),
            }
        })
        .collect()
}

pub(crate) fn view_residual(
    view: usize,
    k: &Intrinsics,
    pose: &Pose,
    ids: &[(usize, usize)],
    plane: &[Vector2<f64>],
    image: &[Vector2<f64>],
) -> ViewResidual {
    let residuals: Vec<(usize, usize, Vector2<f64>)> = ids
        .iter()
        .zip(plane.iter().zip(image))
        .map(|(&(i, j), (b, px))| {
            let c = pose * Point3::new(b.x, b.y, 0.0);
            let q =
                project(k, &c.coords).unwrap_or(Vector2::new(UNPROJECTABLE_PX, UNPROJECTABLE_PX));
            (i, j, q - px)
        })
        .collect();
    let n = residuals.len().max(1) as f64;
    let rms = (residuals.iter().map(|r| r.2.norm_squared()).sum::<f64>() / n).sqrt();
    let max = residuals.iter().map(|r| r.2.norm()).fold(0.0, f64::max);
    ViewResidual {
        view,
        rms_px: rms,
        max_px: max,
        residuals,
    }
}

/// The board's pose in a calibrated camera from its corners (homography of the
/// undistorted corners, then Levenberg-Marquardt on the pose alone), with the view's
/// reprojection residuals: how held-out views are scored.
pub fn fit_board_pose(
    camera: &PinholeCamera,
    corners: &BoardCorners,
    target: &TargetConfig,
    view: usize,
) -> Option<(Pose, ViewResidual)> {
    let (ids, plane, image) = correspondences(corners, target);
    let normalised: Vec<Vector2<f64>> = image
        .iter()
        .map(|p| camera.unproject(*p).ok().map(|n| Vector2::new(n.x, n.y)))
        .collect::<Option<Vec<_>>>()?;
    let h = homography(&plane, &normalised)?;
    let init = zhang::pose_from_homography(&h, [1.0, 1.0, 0.0, 0.0])?;
    let k = crate::geometry::intrinsics_of(camera);
    let points: Vec<(Vector2<f64>, Vector2<f64>)> =
        plane.iter().copied().zip(image.iter().copied()).collect();
    let block = Block {
        params: (0..6).collect(),
        residuals: 2 * points.len(),
        class: 0,
        eval: Box::new(move |p: &[f64], r: &mut [f64]| {
            let pose = pose_from_params(p);
            for (n, (b, px)) in points.iter().enumerate() {
                let c = pose * Point3::new(b.x, b.y, 0.0);
                let q = project(&k, &c.coords)
                    .unwrap_or(Vector2::new(UNPROJECTABLE_PX, UNPROJECTABLE_PX));
                r[2 * n] = q.x - px.x;
                r[2 * n + 1] = q.y - px.y;
            }
        }),
    };
    let problem = Problem {
        blocks: vec![block],
        scale: vec![0.1; 6],
        fixed: vec![false; 6],
    };
    let result = problem.solve(&params_from_pose(&init), &LmOptions::default());
    let pose = pose_from_params(&result.x);
    Some((
        pose,
        view_residual(
            view,
            &crate::geometry::intrinsics_of(camera),
            &pose,
            &ids,
            &plane,
            &image,
        ),
    ))
}
