//! The lidar-to-EO extrinsic `eo_from_lidar` and the range bias.
//!
//! Initialisation from plane correspondences (Unnikrishnan & Hebert 2005; Zhang &
//! Pless 2004): each view gives the board plane twice, `(n_E, d_E)` from the EO
//! board pose and `(n_L, d_L)` from the lidar's plane fit. The rotation aligns the
//! normals (`n_E = R n_L`, Kabsch), and the translation and bias solve the linear
//! system `n_E·t - b·c = d_E - d_L` (`c` the mean of `n_L·ray` over the board pixels).
//! Then one joint Levenberg-Marquardt refines everything together: EO intrinsics and
//! board poses (EO corner reprojection), `eo_from_lidar`, the bias and, when asked,
//! the lidar's intrinsics (board pixels on the EO board plane; intensity corners
//! reprojected into the lidar). Each residual class is divided by its own standard
//! deviation, measured from the data in a first pass.

use nalgebra::{DMatrix, DVector, Matrix3, Point3, SymmetricEigen, Vector2, Vector3};
use texel::{Distortion, PinholeCamera, Pose};

use crate::config::{SolverConfig, TargetConfig};
use crate::eo::{EoSolution, eo_blocks, fixed_intrinsics, view_residual};
use crate::error::CalibError;
use crate::geometry::{
    UNPROJECTABLE_PX, camera_of, nearest_rotation, params_from_pose, pose_from_params, project,
};
use crate::lidar::LidarBoard;
use crate::lm::{Block, LmOptions, Problem, covariance};

/// Normals spread over less than this (degrees) leave the extrinsic unfixed.
const MIN_NORMAL_SPREAD_DEG: f64 = 4.0;

/// The refined extrinsic is refused when its standard deviation exceeds these.
const MAX_ROTATION_STD_DEG: f64 = 0.2;
const MAX_TRANSLATION_STD_M: f64 = 0.005;

/// Residual classes of the joint problem.
const CLASS_EO: usize = 0;
const CLASS_PLANE: usize = 1;
const CLASS_LIDAR_CORNER: usize = 2;

/// One lidar view's fit.
#[derive(Debug, Clone, PartialEq)]
pub struct LidarViewResidual {
    pub view: usize,
    /// RMS distance of the board pixels from the EO board plane, metres.
    pub plane_rms_m: f64,
    /// Mean signed distance (lidar behind the EO plane is positive), metres.
    pub plane_mean_m: f64,
    /// RMS of the intensity corners' reprojection, lidar pixels.
    pub corner_rms_px: Option<f64>,
}

/// The lidar side of a calibration.
#[derive(Debug, Clone)]
pub struct LidarSolution {
    pub eo_from_lidar: Pose,
    /// Standard deviation of the rotation about the EO x, y, z axes, degrees.
    pub rotation_std_deg: [f64; 3],
    /// Standard deviation of the translation, metres.
    pub translation_std_m: [f64; 3],
    /// Constant added to true ranges by the lidar, metres (0 when not estimated).
    pub range_bias_m: f64,
    pub range_bias_std_m: f64,
    pub lidar: PinholeCamera,
    /// `[fx, fy, cx, cy]` standard deviations when the lidar intrinsics were estimated.
    pub lidar_intrinsics_std: Option<[f64; 4]>,
    pub plane_rms_m: f64,
    pub corner_rms_px: Option<f64>,
    pub per_view: Vec<LidarViewResidual>,
    /// Number of views with lidar intensity corners.
    pub corner_views: usize,
    pub iterations: usize,
}

/// A lidar board paired with the EO observation of the same view.
pub struct Paired<'a> {
    /// Index of the EO observation (its pose in the EO solution).
    pub observation: usize,
    pub board: &'a LidarBoard,
}

/// EO board plane `(n, d)` in the EO frame, normal away from the camera.
fn eo_plane(camera_from_board: &Pose) -> (Vector3<f64>, f64) {
    let n = camera_from_board.rotation * Vector3::z();
    let d = n.dot(&camera_from_board.translation.vector);
    if d < 0.0 { (-n, -d) } else { (n, d) }
}

/// Refines EO and lidar together; returns the updated EO solution and the lidar's.
#[allow(clippy::too_many_arguments)]
pub fn calibrate_joint(
    eo: &EoSolution,
    paired: &[Paired<'_>],
    lidar_camera: &PinholeCamera,
    target: &TargetConfig,
    solver: &SolverConfig,
) -> Result<(EoSolution, LidarSolution), CalibError> {
    // Step 1: enough different planes.
    let normals: Vec<Vector3<f64>> = paired
        .iter()
        .map(|p| eo_plane(&eo.poses[p.observation]).0)
        .collect();
    let spread = normal_spread_deg(&normals);
    if paired.len() < 3 || spread < MIN_NORMAL_SPREAD_DEG {
        return Err(CalibError::ExtrinsicUnconstrained {
            what: format!(
                "{} lidar view(s) of the whole board, whose board normals spread over \
                 {spread:.1} degrees (at least 3 views spreading over {MIN_NORMAL_SPREAD_DEG} \
                 degrees are needed)",
                paired.len()
            ),
        });
    }
    // Step 2: closed-form rotation, translation and bias from plane pairs.
    let rays: Vec<Vec<Vector3<f64>>> = paired
        .iter()
        .map(|p| {
            p.board
                .pixels
                .iter()
                .map(|&(u, v, _)| {
                    lidar_camera
                        .unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                        .unwrap_or_else(|_| Vector3::z())
                })
                .collect()
        })
        .collect();
    let init = initial_extrinsic(eo, paired, &rays, solver.estimate_range_bias)?;
    // Step 3: joint refinement, twice: the first pass measures each residual class's
    // standard deviation, the second weighs them by it.
    let corner_views = paired.iter().filter(|p| p.board.corners.is_some()).count();
    let pooled_plane = (paired
        .iter()
        .map(|p| p.board.plane_rms_m.powi(2))
        .sum::<f64>()
        / paired.len() as f64)
        .sqrt();
    let mut sigmas = [eo.rms_px.max(0.01), pooled_plane.max(1.0e-4), 0.3];
    let n_eo = 9 + 6 * eo.poses.len();
    let e = n_eo;
    let mut x: Vec<f64> = Vec::with_capacity(n_eo + 11);
    x.extend_from_slice(&eo.intrinsics);
    for p in &eo.poses {
        x.extend_from_slice(&params_from_pose(p));
    }
    x.extend_from_slice(&params_from_pose(&init.0));
    x.push(init.1);
    x.extend_from_slice(&[
        lidar_camera.fx,
        lidar_camera.fy,
        lidar_camera.cx,
        lidar_camera.cy,
    ]);
    let lidar_distortion = lidar_camera.distortion;
    let options = LmOptions {
        max_iterations: solver.max_iterations,
        ..LmOptions::default()
    };
    let mut last = None;
    for _pass in 0..2 {
        let problem = joint_problem(
            eo,
            paired,
            &rays,
            lidar_distortion,
            target,
            solver,
            sigmas,
            e,
        );
        let result = problem.solve(&x, &options);
        if !result.x.iter().all(|v| v.is_finite()) {
            return Err(CalibError::Diverged {
                stage: "joint EO-lidar refinement",
                detail: "non-finite parameters".into(),
            });
        }
        x.clone_from(&result.x);
        // Measured standard deviation of each class at this solution.
        let residuals = problem.residuals(&x);
        let mut sums = [0.0f64; 3];
        let mut counts = [0usize; 3];
        for (b, r) in problem.blocks.iter().zip(&residuals) {
            sums[b.class] += r.iter().map(|v| v * v).sum::<f64>();
            counts[b.class] += r.len();
        }
        for c in 0..3 {
            if counts[c] > 0 {
                sigmas[c] *= (sums[c] / counts[c] as f64).sqrt().max(1.0e-3);
            }
        }
        last = Some((result, problem.fixed.clone()));
    }
    let Some((result, fixed)) = last else {
        return Err(CalibError::Diverged {
            stage: "joint EO-lidar refinement",
            detail: "no solve ran".into(),
        });
    };
    // Step 4: the covariance; an extrinsic the data do not fix is refused.
    let cov = covariance(&result, &fixed);
    let std = |i: usize| cov[(i, i)].max(0.0).sqrt();
    let rotation_std_deg = [
        std(e).to_degrees(),
        std(e + 1).to_degrees(),
        std(e + 2).to_degrees(),
    ];
    let translation_std_m = [std(e + 3), std(e + 4), std(e + 5)];
    let worst_rot = rotation_std_deg.iter().copied().fold(0.0, f64::max);
    let worst_t = translation_std_m.iter().copied().fold(0.0, f64::max);
    if !(worst_rot <= MAX_ROTATION_STD_DEG && worst_t <= MAX_TRANSLATION_STD_M) {
        return Err(CalibError::ExtrinsicUnconstrained {
            what: format!(
                "the rotation's standard deviation is {worst_rot:.3} degrees (limit \
                 {MAX_ROTATION_STD_DEG}) and the translation's {:.1} mm (limit {:.1})",
                worst_t * 1e3,
                MAX_TRANSLATION_STD_M * 1e3
            ),
        });
    }
    // Step 5: the solution and its residuals.
    let mut eo_out = eo.clone();
    eo_out.intrinsics.copy_from_slice(&x[..9]);
    for i in 0..9 {
        eo_out.intrinsics_std[i] = std(i);
    }
    eo_out.camera = camera_of(eo.camera.width, eo.camera.height, &eo_out.intrinsics);
    eo_out.poses = (0..eo.poses.len())
        .map(|v| pose_from_params(&x[9 + 6 * v..15 + 6 * v]))
        .collect();
    eo_out.per_view = eo
        .data
        .iter()
        .zip(&eo_out.poses)
        .zip(&eo.per_view)
        .map(|(((ids, plane, image), pose), old)| {
            view_residual(old.view, &eo_out.intrinsics, pose, ids, plane, image)
        })
        .collect();
    let (sum, n) = eo_out.per_view.iter().fold((0.0, 0usize), |(s, n), v| {
        (
            s + v.residuals.iter().map(|r| r.2.norm_squared()).sum::<f64>(),
            n + v.residuals.len(),
        )
    });
    eo_out.rms_px = (sum / n.max(1) as f64).sqrt();
    let eo_from_lidar = pose_from_params(&x[e..e + 6]);
    let bias = x[e + 6];
    let mut lidar = lidar_camera.clone();
    if solver.estimate_lidar_intrinsics {
        lidar.fx = x[e + 7];
        lidar.fy = x[e + 8];
        lidar.cx = x[e + 9];
        lidar.cy = x[e + 10];
    }
    let lk = lidar_vector(&x[e + 7..e + 11], lidar_distortion);
    let per_view: Vec<LidarViewResidual> = paired
        .iter()
        .zip(&rays)
        .map(|(p, rays)| {
            let board_from_eo = eo_out.poses[p.observation].inverse();
            let d: Vec<f64> = p
                .board
                .pixels
                .iter()
                .zip(rays)
                .map(|(&(u, v, r), ray)| {
                    let ray = if solver.estimate_lidar_intrinsics {
                        ray_of(&lidar, u, v)
                    } else {
                        *ray
                    };
                    let pl = Point3::from(ray * (r - bias));
                    (board_from_eo * (eo_from_lidar * pl)).z
                })
                .collect();
            let n = d.len().max(1) as f64;
            let corner_rms_px = p.board.corners.as_ref().map(|c| {
                let lidar_from_board = eo_from_lidar.inverse() * eo_out.poses[p.observation];
                let errs: Vec<f64> = c
                    .iter()
                    .map(|(i, j, px)| {
                        let q = lidar_from_board * Point3::from(target.corner_point(i, j));
                        project(&lk, &q.coords)
                            .map_or(UNPROJECTABLE_PX, |q| (q - px).norm_squared())
                    })
                    .collect();
                (errs.iter().sum::<f64>() / errs.len().max(1) as f64).sqrt()
            });
            LidarViewResidual {
                view: p.board.view,
                plane_rms_m: (d.iter().map(|v| v * v).sum::<f64>() / n).sqrt(),
                plane_mean_m: d.iter().sum::<f64>() / n,
                corner_rms_px,
            }
        })
        .collect();
    let plane_rms_m = (per_view.iter().map(|v| v.plane_rms_m.powi(2)).sum::<f64>()
        / per_view.len().max(1) as f64)
        .sqrt();
    let corner: Vec<f64> = per_view.iter().filter_map(|v| v.corner_rms_px).collect();
    let corner_rms_px = (!corner.is_empty())
        .then(|| (corner.iter().map(|v| v * v).sum::<f64>() / corner.len() as f64).sqrt());
    Ok((
        eo_out,
        LidarSolution {
            eo_from_lidar,
            rotation_std_deg,
            translation_std_m,
            range_bias_m: bias,
            range_bias_std_m: std(e + 6),
            lidar,
            lidar_intrinsics_std: solver
                .estimate_lidar_intrinsics
                .then(|| [std(e + 7), std(e + 8), std(e + 9), std(e + 10)]),
            plane_rms_m,
            corner_rms_px,
            per_view,
            corner_views,
            iterations: result.iterations,
        },
    ))
}

fn ray_of(camera: &PinholeCamera, u: u32, v: u32) -> Vector3<f64> {
    camera
        .unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
        .unwrap_or_else(|_| Vector3::z())
}

/// Lidar intrinsic vector for [`project`] from `[fx, fy, cx, cy]` and its distortion.
fn lidar_vector(k: &[f64], distortion: Distortion) -> [f64; 9] {
    let d = match distortion {
        Distortion::PlumbBob(d) => d.to_array(),
        Distortion::None => [0.0; 5],
    };
    [k[0], k[1], k[2], k[3], d[0], d[1], d[2], d[3], d[4]]
}

/// Largest angle between the mean normal and any normal, degrees.
fn normal_spread_deg(normals: &[Vector3<f64>]) -> f64 {
    if normals.is_empty() {
        return 0.0;
    }
    let mut m = Matrix3::zeros();
    for n in normals {
        m += n * n.transpose();
    }
    let eig = SymmetricEigen::new(m / normals.len() as f64);
    // Second-largest eigenvalue: how far the normals leave a single direction.
    let mut ev: Vec<f64> = eig.eigenvalues.iter().copied().collect();
    ev.sort_by(f64::total_cmp);
    ev[1].max(0.0).sqrt().clamp(0.0, 1.0).asin().to_degrees() * 2.0
}

/// Kabsch on the normals, then the linear translation-and-bias system.
fn initial_extrinsic(
    eo: &EoSolution,
    paired: &[Paired<'_>],
    rays: &[Vec<Vector3<f64>>],
    estimate_bias: bool,
) -> Result<(Pose, f64), CalibError> {
    let mut h = Matrix3::zeros();
    for p in paired {
        let (n_e, _) = eo_plane(&eo.poses[p.observation]);
        h += n_e * p.board.plane.normal.transpose();
    }
    let rotation = nearest_rotation(&h).ok_or_else(|| CalibError::Diverged {
        stage: "extrinsic initialisation",
        detail: "non-finite plane normals".into(),
    })?;
    let unknowns = if estimate_bias { 4 } else { 3 };
    let mut a = DMatrix::zeros(paired.len(), unknowns);
    let mut rhs = DVector::zeros(paired.len());
    for (k, (p, rays)) in paired.iter().zip(rays).enumerate() {
        let (n_e, d_e) = eo_plane(&eo.poses[p.observation]);
        let n_l = p.board.plane.normal;
        let c = rays.iter().map(|r| n_l.dot(r)).sum::<f64>() / rays.len().max(1) as f64;
        for i in 0..3 {
            a[(k, i)] = n_e[i];
        }
        if estimate_bias {
            a[(k, 3)] = -c;
        }
        rhs[k] = d_e - p.board.plane.d;
    }
    let ata = a.transpose() * &a;
    let x = ata
        .clone()
        .try_inverse()
        .map(|inv| inv * (a.transpose() * rhs))
        .ok_or_else(|| CalibError::ExtrinsicUnconstrained {
            what: "the board planes do not fix the lidar's translation".into(),
        })?;
    let t = Vector3::new(x[0], x[1], x[2]);
    let bias = if estimate_bias { x[3] } else { 0.0 };
    if !(t.iter().all(|v| v.is_finite()) && bias.is_finite()) {
        return Err(CalibError::Diverged {
            stage: "extrinsic initialisation",
            detail: "non-finite translation".into(),
        });
    }
    Ok((Pose::from_parts(t.into(), rotation.into()), bias))
}

#[allow(clippy::too_many_arguments)]
fn joint_problem(
    eo: &EoSolution,
    paired: &[Paired<'_>],
    rays: &[Vec<Vector3<f64>>],
    lidar_distortion: Distortion,
    target: &TargetConfig,
    solver: &SolverConfig,
    sigmas: [f64; 3],
    e: usize,
) -> Problem<'static> {
    let n = e + 11;
    let mut fixed = vec![false; n];
    fixed[..9].copy_from_slice(&fixed_intrinsics(solver));
    fixed[e + 6] = !solver.estimate_range_bias;
    for f in fixed.iter_mut().skip(e + 7) {
        *f = !solver.estimate_lidar_intrinsics;
    }
    let mut scale = vec![0.1; n];
    for i in [0, 1, 2, 3, e + 7, e + 8, e + 9, e + 10] {
        scale[i] = 100.0;
    }
    for s in scale.iter_mut().take(9).skip(4) {
        *s = 1.0;
    }
    let mut blocks = eo_blocks(&eo.data, &eo.masks, sigmas[CLASS_EO]);
    let estimate_lidar = solver.estimate_lidar_intrinsics;
    for (p, rays) in paired.iter().zip(rays) {
        let v = p.observation;
        let mut params: Vec<usize> = (9 + 6 * v..15 + 6 * v).collect();
        params.extend(e..e + 11);
        // Evenly spread subset of the board pixels.
        let stride = p
            .board
            .pixels
            .len()
            .div_ceil(solver.max_lidar_points_per_view)
            .max(1);
        let samples: Vec<((u32, u32, f64), Vector3<f64>)> = p
            .board
            .pixels
            .iter()
            .copied()
            .zip(rays.iter().copied())
            .step_by(stride)
            .collect();
        let inv = 1.0 / sigmas[CLASS_PLANE];
        let base_camera = PinholeCamera {
            distortion: lidar_distortion,
            ..camera_shell()
        };
        blocks.push(Block {
            params: params.clone(),
            residuals: samples.len(),
            class: CLASS_PLANE,
            eval: Box::new(move |q: &[f64], r: &mut [f64]| {
                let board_from_eo = pose_from_params(&q[0..6]).inverse();
                let eo_from_lidar = pose_from_params(&q[6..12]);
                let bias = q[12];
                let m = board_from_eo * eo_from_lidar;
                let mut camera = base_camera.clone();
                if estimate_lidar {
                    camera.fx = q[13];
                    camera.fy = q[14];
                    camera.cx = q[15];
                    camera.cy = q[16];
                }
                for (k, ((u, v, range), ray)) in samples.iter().enumerate() {
                    let ray = if estimate_lidar {
                        ray_of(&camera, *u, *v)
                    } else {
                        *ray
                    };
                    let pl = Point3::from(ray * (range - bias));
                    r[k] = (m * pl).z * inv;
                }
            }),
        });
        if let Some(corners) = &p.board.corners {
            let pts: Vec<(Point3<f64>, Vector2<f64>)> = corners
                .iter()
                .map(|(i, j, px)| (Point3::from(target.corner_point(i, j)), px))
                .collect();
            let inv = 1.0 / sigmas[CLASS_LIDAR_CORNER];
            blocks.push(Block {
                params,
                residuals: 2 * pts.len(),
                class: CLASS_LIDAR_CORNER,
                eval: Box::new(move |q: &[f64], r: &mut [f64]| {
                    let eo_from_board = pose_from_params(&q[0..6]);
                    let lidar_from_eo = pose_from_params(&q[6..12]).inverse();
                    let m = lidar_from_eo * eo_from_board;
                    let k = lidar_vector(&q[13..17], lidar_distortion);
                    for (n, (b, px)) in pts.iter().enumerate() {
                        match project(&k, &(m * b).coords) {
                            Some(p) => {
                                r[2 * n] = (p.x - px.x) * inv;
                                r[2 * n + 1] = (p.y - px.y) * inv;
                            }
                            None => {
                                r[2 * n] = UNPROJECTABLE_PX;
                                r[2 * n + 1] = UNPROJECTABLE_PX;
                            }
                        }
                    }
                }),
            });
        }
    }
    Problem {
        blocks,
        scale,
        fixed,
    }
}

/// A camera shell whose intrinsics each evaluation overwrites.
fn camera_shell() -> PinholeCamera {
    PinholeCamera {
        width: 1,
        height: 1,
        fx: 1.0,
        fy: 1.0,
        cx: 0.0,
        cy: 0.0,
        skew: 0.0,
        distortion: Distortion::None,
    }
}
