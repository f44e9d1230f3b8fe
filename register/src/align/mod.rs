//! Pairwise and scan-to-scans alignment: coarse-to-fine, projective association,
//! robust point-to-plane plus, where the geometry is weak, the direct photometric
//! term on the EO images; Gauss-Newton or Levenberg-Marquardt on SE(3) with
//! degeneracy-aware updates. Pure and synchronous.

mod photometric;

use nalgebra::{Matrix6, Vector3, Vector6};
use texel::Pose;
use texel::pose::pose_difference;

use self::photometric::PhotometricSums;
use super::associate::{Association, Gates, TargetView, associate, point_to_plane};
use super::config::{AlignConfig, Solver};
use super::kernel;
use super::normal_eq::{
    NormalEquations, PhotometricEquations, Step, covariance_and_information, map_chunks, map_each,
    solve_remapped, weak_directions,
};
use super::photometric::{EoPyramid, PhotometricMode};
use super::pyramid::{Level, ScanPyramid};
use super::result::{Alignment, FailureReason, Fitness, PhotometricSummary};
use super::se3;

/// MAD to standard deviation for Gaussian residuals.
const MAD_TO_SIGMA: f64 = 1.4826;
/// Smallest length scale for the degeneracy analysis (metres).
const MIN_LENGTH_SCALE_M: f64 = 0.05;
/// Levenberg-Marquardt: initial damping relative to the largest eigenvalue, and the
/// damping past which the step is considered stuck.
const LM_INITIAL_DAMPING: f64 = 1.0e-4;
const LM_MAX_DAMPING: f64 = 1.0e6;

/// An earlier scan to align against, with its pose in the common frame.
#[derive(Clone, Copy)]
pub struct AlignTarget<'a> {
    pub pyramid: &'a ScanPyramid,
    pub world_from_target: Pose,
}

/// Aligns `source` against one `target`; poses are expressed in the target's frame
/// (`initial` is the guess of `target_from_source`).
pub fn align_pair(
    source: &ScanPyramid,
    target: &ScanPyramid,
    initial: &Pose,
    config: &AlignConfig,
) -> Alignment {
    let targets = [AlignTarget {
        pyramid: target,
        world_from_target: Pose::identity(),
    }];
    align(source, &targets, initial, config)
}

/// Aligns `source` against `targets` (each source point pairs with the nearest
/// target point it projects onto), starting from `initial` (`world_from_source`).
/// At most [`MAX_TARGETS`] targets are used (the first ones); the registrar's window
/// is validated to that size.
///
/// The recipe, per pyramid level from coarse to fine:
/// 1. move the source samples by the current estimate and pair them by projective
///    association (Blais & Levine 1995; Newcombe et al. 2011, Sec. 3.5), gating
///    by distance and normal agreement;
/// 2. point-to-plane residuals (Chen & Medioni 1992), each normalised by its noise
///    sigma; where the geometry leaves a direction weak (or always, in the full
///    mode), the paired points' photometric residuals on the targets' EO images
///    (`photometric`), normalised by the intensity noise, after a brightness
///    compensation per target;
/// 3. estimate the residual scale robustly (MAD) and weight residuals with the
///    configured kernel (IRLS; Huber, Tukey or Geman-McClure weight functions);
/// 4. reduce the 6x6 normal equations in a fixed chunk order (bit-identical whatever
///    the thread count);
/// 5. solve in the observable subspace only (eigen-analysis and solution remapping,
///    Zhang, Kaess & Singh 2016) of the geometric information plus the photometric
///    information admitted in the weak subspace, damped under Levenberg-Marquardt;
/// 6. update on the right, `T ← T·exp(δ)`, until the step is below the thresholds.
///
/// Then one evaluation at the final pose gives fitness, covariance, per-target
/// information and degenerate directions (a direction fixed photometrically at one
/// of several equally good positions is reported ambiguous), and the checks that
/// turn a result into a failure: too few points, too little overlap, divergence,
/// poor fit.
pub fn align(
    source: &ScanPyramid,
    targets: &[AlignTarget<'_>],
    initial: &Pose,
    config: &AlignConfig,
) -> Alignment {
    let targets = &targets[..targets.len().min(MAX_TARGETS)];
    let levels = source
        .level_count()
        .min(config.pyramid_levels.max(1) as usize);
    let needed = config.min_correspondences as usize;
    let finest_samples = source
        .levels
        .first()
        .map(|l| l.samples(config.point_stride as usize))
        .unwrap_or_default();
    if finest_samples.len() < needed {
        return failed(
            initial,
            targets.len(),
            FailureReason::NoPoints {
                side: "scan",
                count: finest_samples.len(),
                needed,
            },
        );
    }
    let target_points: usize = targets
        .iter()
        .map(|t| t.pyramid.levels.first().map_or(0, Level::point_count))
        .sum();
    if targets.is_empty() {
        return failed(initial, 0, FailureReason::NoTargets);
    }
    if target_points < needed {
        return failed(
            initial,
            targets.len(),
            FailureReason::NoPoints {
                side: "model (the scans registered against)",
                count: target_points,
                needed,
            },
        );
    }

    let mut pose = *initial;
    let mut iterations = 0u32;
    let mut last: Option<(Problem<'_>, Evaluation)> = None;
    for level in (0..levels).rev() {
        let samples = if level == 0 {
            finest_samples.clone()
        } else {
            let l = &source.levels[level];
            l.samples(coarse_stride(l.width, l.height, config.point_stride))
        };
        let problem = Problem::new(source, targets, level, &samples, config);
        let outcome = problem.iterate(&mut pose, config);
        iterations += outcome.iterations;
        if level == 0 {
            last = outcome.converged_at.map(|e| (problem, e));
        }
    }

    // Fitness, covariance and information at the estimate, on the finest level: the
    // last linearisation when the finest level converged (its final step was below
    // the convergence thresholds), else a fresh evaluation.
    let (problem, evaluation) = match last {
        Some(last) => last,
        None => {
            let problem = Problem::new(source, targets, 0, &finest_samples, config);
            let evaluation = problem.evaluate(&pose, config, true);
            (problem, evaluation)
        }
    };
    finish(initial, pose, iterations, &problem, &evaluation, config)
}

/// The ambiguity check looks this many prior sigmas (of translation) either side of
/// the estimate: as far as the initial guess may plausibly be wrong.
const AMBIGUITY_SPAN_PRIOR_SIGMAS: f64 = 2.0;

/// Fewest sample positions a coarse level keeps (while its grid has them).
const MIN_COARSE_SAMPLES: usize = 1024;

/// The stride at a coarse level: the configured one while it leaves at least
/// [`MIN_COARSE_SAMPLES`] positions, else the largest smaller one that does (or 1).
/// Coarse levels then cost a fraction of the finest, yet keep enough points for the
/// large early moves to be well constrained.
fn coarse_stride(width: usize, height: usize, point_stride: u32) -> usize {
    let mut stride = point_stride.max(1) as usize;
    while stride > 1 && width.div_ceil(stride) * height.div_ceil(stride) < MIN_COARSE_SAMPLES {
        stride -= 1;
    }
    stride
}

fn failed(initial: &Pose, targets: usize, reason: FailureReason) -> Alignment {
    Alignment {
        world_from_source: *initial,
        initial: *initial,
        status: Err(reason),
        covariance: Matrix6::identity(),
        information: Matrix6::zeros(),
        target_information: vec![Matrix6::zeros(); targets],
        target_correspondences: vec![0; targets],
        fitness: Fitness::default(),
        degenerate: Vec::new(),
        iterations: 0,
        photometric: PhotometricSummary::default(),
    }
}

/// One source sample, unpacked once per level.
#[derive(Clone, Copy)]
struct SourceSample {
    p: Vector3<f64>,
    n: Vector3<f64>,
    sigma_m: f64,
    /// Its position in the problem's samples.
    index: u32,
}

/// One level's data: the source samples and the targets at that level.
struct Problem<'a> {
    targets: &'a [AlignTarget<'a>],
    level: usize,
    samples: Vec<SourceSample>,
    /// The source's EO pyramid, when the photometric term may run.
    source_eo: Option<&'a EoPyramid>,
    /// The EO pyramid level this alignment level reads.
    eo_level: usize,
    /// The source's EO value where each sample projects, at `eo_level`: read on the
    /// photometric term's first use (where the geometry suffices it never runs).
    source_intensities: std::sync::OnceLock<Vec<Option<f64>>>,
    gates: Gates,
    /// RMS distance of the samples from the source origin: converts rotation to
    /// metres for the degeneracy analysis.
    length_m: f64,
    /// Convergence thresholds at this level: the configured ones times `2^level`
    /// (a coarse level only has to bring the estimate within reach of the next).
    convergence_rotation_rad: f64,
    convergence_translation_m: f64,
}

/// One residual, already divided by its sigma (so `j` and `r` are unitless).
#[derive(Clone, Copy)]
struct Residual {
    j: [f64; 6],
    r: f64,
    target: u8,
}

/// Per-chunk association output.
#[derive(Default)]
struct Associated {
    residuals: Vec<Residual>,
    /// (sample, target) of each pair, for the photometric pass.
    pairs: Vec<(u32, u8)>,
    overlapping: usize,
    correspondences: usize,
    inliers: usize,
    inlier_sq_sum_m2: f64,
}

/// The normal equations and statistics of one pose.
struct Evaluation {
    total: NormalEquations,
    /// Every pair with weight 1: what the geometry alone constrains.
    geometry: NormalEquations,
    /// Per target (only for the final evaluation).
    per_target_geometry: Vec<NormalEquations>,
    per_target: Vec<NormalEquations>,
    per_target_count: Vec<usize>,
    overlapping: usize,
    correspondences: usize,
    inliers: usize,
    inlier_sq_sum_m2: f64,
    geometric_scale: f64,
    /// The photometric term, when it ran, and the pairs it observed.
    photometric: Option<PhotometricSums>,
    pairs: Vec<(u32, u8)>,
}

/// How a level's iterations ended.
struct Outcome {
    iterations: u32,
    /// The last evaluation, when the final step was below the thresholds.
    converged_at: Option<Evaluation>,
}

/// Most targets per alignment (per-target sums live on the stack).
pub const MAX_TARGETS: usize = 16;

impl<'a> Problem<'a> {
    fn new(
        source: &'a ScanPyramid,
        targets: &'a [AlignTarget<'a>],
        level: usize,
        indices: &[u32],
        config: &AlignConfig,
    ) -> Self {
        let source_level = &source.levels[level];
        let source_eo = source.eo.as_ref().filter(|_| config.photometric.enabled());
        let eo_level = source_eo.map_or(0, |eo| {
            eo_level_for(
                level,
                source.level_count(),
                eo.level_count(),
                config.photometric.finest_eo_level as usize,
            )
        });
        let samples: Vec<SourceSample> = indices
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                let i = i as usize;
                SourceSample {
                    p: source_level.point(i),
                    n: source_level.normal(i),
                    sigma_m: f64::from(source_level.sigma_m(i)),
                    index: k as u32,
                }
            })
            .collect();
        let sum_sq: f64 = samples.iter().map(|s| s.p.norm_squared()).sum();
        let length_m = if samples.is_empty() {
            1.0
        } else {
            (sum_sq / samples.len() as f64)
                .sqrt()
                .max(MIN_LENGTH_SCALE_M)
        };
        let level_scale = f64::from(1u32 << level.min(16));
        Self {
            targets,
            level,
            samples,
            source_eo,
            eo_level,
            source_intensities: std::sync::OnceLock::new(),
            gates: Gates {
                max_distance_m: config.max_correspondence_distance_m * level_scale,
                min_normal_cosine: config.max_normal_angle_deg.to_radians().cos(),
            },
            length_m,
            convergence_rotation_rad: config.convergence_rotation_rad * level_scale,
            convergence_translation_m: config.convergence_translation_m * level_scale,
        }
    }

    fn views(&self, world_from_source: &Pose) -> Vec<TargetView<'a>> {
        self.targets
            .iter()
            .map(|t| {
                let level = &t.pyramid.levels[self.level.min(t.pyramid.level_count() - 1)];
                let target_from_source = t.world_from_target.inverse() * world_from_source;
                TargetView::new(level, &t.pyramid.projector, &target_from_source)
            })
            .collect()
    }

    /// Steps 1-4 of the recipe at one pose; `per_target` also keeps the sums of each
    /// target apart (for the pose graph's edges).
    fn evaluate(
        &self,
        world_from_source: &Pose,
        config: &AlignConfig,
        per_target: bool,
    ) -> Evaluation {
        let views = self.views(world_from_source);
        let keep_pairs = self.source_eo.is_some();
        let inlier_sigmas = config.inlier_sigmas;
        // Steps 1-2: associate and form residuals, chunk by chunk.
        let chunks = map_chunks(&self.samples, config.parallel, |chunk| {
            let mut out = Associated::default();
            out.residuals.reserve(chunk.len());
            for sample in chunk {
                let pair = match associate(&sample.p, &sample.n, &views, &self.gates) {
                    Association::Outside => continue,
                    Association::Rejected => {
                        out.overlapping += 1;
                        continue;
                    }
                    Association::Paired(pair) => pair,
                };
                out.overlapping += 1;
                out.correspondences += 1;
                let view = &views[pair.target];
                let sigma = {
                    let (a, b) = (sample.sigma_m, f64::from(view.level.sigma_m(pair.index)));
                    (a * a + b * b).sqrt().max(1.0e-6)
                };
                let (r, j) = point_to_plane(&pair, &sample.p, &view.rotation);
                if r.abs() <= inlier_sigmas * sigma {
                    out.inliers += 1;
                    out.inlier_sq_sum_m2 += r * r;
                }
                let inv_sigma = 1.0 / sigma;
                out.residuals.push(Residual {
                    j: j.map(|x| x * inv_sigma),
                    r: r * inv_sigma,
                    target: pair.target as u8,
                });
                if keep_pairs {
                    out.pairs.push((sample.index, pair.target as u8));
                }
            }
            out
        });
        let (mut overlapping, mut correspondences, mut inliers, mut inlier_sq_sum_m2) =
            (0, 0, 0, 0.0);
        for c in &chunks {
            overlapping += c.overlapping;
            correspondences += c.correspondences;
            inliers += c.inliers;
            inlier_sq_sum_m2 += c.inlier_sq_sum_m2;
        }
        // Step 3: robust scale (never below the noise: scale 1 in sigma units).
        let geometric_scale =
            robust_scale_of(chunks.iter().flat_map(|c| c.residuals.iter().map(|r| r.r)));
        // Step 4: weighted normal equations, per target, in fixed chunk order.
        let n_targets = self.targets.len().min(MAX_TARGETS);
        let kernel_k = config.kernel_threshold();
        let kernel_kind = config.kernel;
        let per_chunk = map_each(&chunks, config.parallel, |group| {
            let mut weighted = [NormalEquations::default(); MAX_TARGETS];
            let mut geometry = [NormalEquations::default(); MAX_TARGETS];
            for res in &group.residuals {
                let s = geometric_scale;
                let e = res.r / s;
                let w = kernel::weight(kernel_kind, kernel_k, e);
                let cost = kernel::cost(kernel_kind, kernel_k, e) * s * s;
                let t = usize::from(res.target).min(MAX_TARGETS - 1);
                weighted[t].add(&res.j, res.r, w, cost);
                geometry[t].add(&res.j, res.r, 1.0, 0.0);
            }
            (weighted, geometry)
        });
        let mut per_target_weighted = vec![NormalEquations::default(); n_targets];
        let mut per_target_geometry = vec![NormalEquations::default(); n_targets];
        for (weighted, geometry) in &per_chunk {
            for t in 0..n_targets {
                per_target_weighted[t].merge(&weighted[t]);
                per_target_geometry[t].merge(&geometry[t]);
            }
        }
        let mut total = NormalEquations::default();
        let mut geometry = NormalEquations::default();
        for t in 0..n_targets {
            total.merge(&per_target_weighted[t]);
            geometry.merge(&per_target_geometry[t]);
        }
        let per_target_count = per_target_geometry.iter().map(|e| e.count).collect();
        // The photometric pass: under the selective mode only while the geometry
        // leaves a direction weak.
        let wanted = match config.photometric.mode {
            PhotometricMode::Off => false,
            PhotometricMode::Full => true,
            PhotometricMode::Selective => {
                !weak_directions(&geometry, self.length_m, config.photometric.weak_ratio).is_empty()
            }
        };
        let pairs: Vec<(u32, u8)> = if wanted {
            chunks
                .iter()
                .flat_map(|c| c.pairs.iter().copied())
                .collect()
        } else {
            Vec::new()
        };
        let mut photometric = (wanted && self.source_eo.is_some())
            .then(|| self.photometric_sums(&views, &pairs, geometric_scale, config));
        if !per_target {
            per_target_weighted.clear();
            per_target_geometry.clear();
            if let Some(p) = photometric.as_mut() {
                p.per_target.clear();
            }
        }
        Evaluation {
            total,
            geometry,
            per_target_geometry,
            per_target: per_target_weighted,
            per_target_count,
            overlapping,
            correspondences,
            inliers,
            inlier_sq_sum_m2,
            geometric_scale,
            photometric,
            pairs: if per_target { pairs } else { Vec::new() },
        }
    }

    /// Steps 5-6, repeated until a step is below the level's thresholds or the
    /// iterations run out.
    fn iterate(&self, pose: &mut Pose, config: &AlignConfig) -> Outcome {
        let mut iterations = 0;
        let mut damping = LM_INITIAL_DAMPING;
        let mut previous: Option<(Pose, Evaluation)> = None;
        let finest = self.level == 0;
        while iterations < config.max_iterations {
            let mut evaluation = self.evaluate(pose, config, finest);
            iterations += 1;
            if evaluation.total.count < 6 {
                // Nothing to constrain the pose at this level: keep it.
                break;
            }
            if config.solver == Solver::LevenbergMarquardt
                && let Some((prev_pose, prev_eval)) = previous.take()
            {
                if mean_cost(&evaluation) > mean_cost(&prev_eval) {
                    // The step raised the cost: go back and damp harder.
                    *pose = prev_pose;
                    evaluation = prev_eval;
                    damping *= 10.0;
                    if damping > LM_MAX_DAMPING {
                        break;
                    }
                } else {
                    damping = (damping / 3.0).max(1.0e-9);
                }
            }
            let step = self.solve(&evaluation, config, damping);
            let (angle, dist) = se3::tangent_size(&step.delta);
            let converged =
                angle < self.convergence_rotation_rad && dist < self.convergence_translation_m;
            let before = *pose;
            *pose *= se3::exp(&step.delta);
            if converged {
                // A step below the thresholds: the evaluation it came from describes
                // the estimate (fitness, covariance) up to that step.
                return Outcome {
                    iterations,
                    converged_at: Some(evaluation),
                };
            }
            if config.solver == Solver::LevenbergMarquardt {
                previous = Some((before, evaluation));
            }
        }
        Outcome {
            iterations,
            converged_at: None,
        }
    }

    fn solve(&self, evaluation: &Evaluation, config: &AlignConfig, damping: f64) -> Step {
        let lm = config.solver == Solver::LevenbergMarquardt;
        // Damping relative to the largest scaled eigenvalue: computed inside by
        // scaling with the trace, which bounds it.
        let damping = if lm {
            let h = evaluation.total.hessian();
            let d = Vector6::new(self.length_m, self.length_m, self.length_m, 1.0, 1.0, 1.0);
            let trace: f64 = (0..6).map(|i| h[(i, i)] / (d[i] * d[i])).sum();
            damping * trace
        } else {
            0.0
        };
        solve_remapped(
            &evaluation.total,
            &evaluation.geometry,
            evaluation
                .photometric
                .as_ref()
                .map(|p| photometric_equations(&p.total, config)),
            self.length_m,
            config.degeneracy_threshold,
            damping,
        )
    }
}

fn mean_cost(e: &Evaluation) -> f64 {
    if e.total.count == 0 {
        f64::MAX
    } else {
        e.total.cost / e.total.count as f64
    }
}

/// The photometric equations as the solver takes them, with where they may act.
fn photometric_equations<'e>(
    equations: &'e NormalEquations,
    config: &AlignConfig,
) -> PhotometricEquations<'e> {
    PhotometricEquations {
        equations,
        weak_ratio: (config.photometric.mode == PhotometricMode::Selective)
            .then_some(config.photometric.weak_ratio),
    }
}

/// The EO level alignment level `level` (of `levels`) reads: `finest` at the
/// finest, the coarsest at the coarsest, spread evenly between.
fn eo_level_for(level: usize, levels: usize, eo_levels: usize, finest: usize) -> usize {
    let top = eo_levels.saturating_sub(1);
    let finest = finest.min(top);
    if levels <= 1 || top == finest {
        return finest;
    }
    let span = top - finest;
    (finest + (level * span + (levels - 1) / 2) / (levels - 1)).min(top)
}

/// `max(1, 1.4826 · median |r|)` of sigma-normalised residuals: the noise sigma when
/// the fit is good, wider while far from it.
fn robust_scale_of(residuals: impl Iterator<Item = f64>) -> f64 {
    let mut abs: Vec<f64> = residuals.map(f64::abs).collect();
    if abs.is_empty() {
        return 1.0;
    }
    let mid = abs.len() / 2;
    let (_, median, _) = abs.select_nth_unstable_by(mid, f64::total_cmp);
    let s = MAD_TO_SIGMA * *median;
    if s.is_finite() { s.max(1.0) } else { 1.0 }
}

/// Fitness, covariance, degenerate directions and the failure checks.
fn finish(
    initial: &Pose,
    pose: Pose,
    iterations: u32,
    problem: &Problem<'_>,
    evaluation: &Evaluation,
    config: &AlignConfig,
) -> Alignment {
    let samples = problem.samples.len();
    let fraction = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
    let fitness = Fitness {
        samples,
        overlap: fraction(evaluation.overlapping, samples),
        correspondences: evaluation.correspondences,
        inlier_ratio: fraction(evaluation.inliers, samples),
        inlier_ratio_of_overlap: fraction(evaluation.inliers, evaluation.overlapping),
        rms_residual_m: if evaluation.inliers == 0 {
            0.0
        } else {
            (evaluation.inlier_sq_sum_m2 / evaluation.inliers as f64).sqrt()
        },
    };
    let prior = Vector6::new(
        config.prior_sigma_rotation_deg.to_radians(),
        config.prior_sigma_rotation_deg.to_radians(),
        config.prior_sigma_rotation_deg.to_radians(),
        config.prior_sigma_translation_m,
        config.prior_sigma_translation_m,
        config.prior_sigma_translation_m,
    );
    let mut step = problem.solve(evaluation, config, 0.0);
    // A direction fixed photometrically at one of several equally good positions
    // keeps the prior's uncertainty and is named.
    let ambiguous = if config.photometric.ambiguity_check && !step.photometric_subspace.is_empty() {
        problem.check_ambiguity(
            &pose,
            &mut step,
            evaluation,
            config,
            AMBIGUITY_SPAN_PRIOR_SIGMAS * config.prior_sigma_translation_m,
        )
    } else {
        Vec::new()
    };
    let (covariance, information) =
        covariance_and_information(&step, problem.length_m, evaluation.geometric_scale, &prior);
    let no_photometric = Vec::new();
    let per_target_photometric = evaluation
        .photometric
        .as_ref()
        .map_or(&no_photometric, |p| &p.per_target);
    let target_information = evaluation
        .per_target
        .iter()
        .zip(&evaluation.per_target_geometry)
        .enumerate()
        .map(|(t, (eq, geometry))| {
            let mut s = solve_remapped(
                eq,
                geometry,
                per_target_photometric
                    .get(t)
                    .map(|p| photometric_equations(p, config)),
                problem.length_m,
                config.degeneracy_threshold,
                0.0,
            );
            for a in &ambiguous {
                photometric::demote(&mut s, &Vector6::from_column_slice(&a.direction));
            }
            covariance_and_information(&s, problem.length_m, evaluation.geometric_scale, &prior).1
        })
        .collect();
    let summary = PhotometricSummary {
        residuals: evaluation.photometric.as_ref().map_or(0, |p| p.residuals),
        geometry_min_eigenvalue: step.geometry_min_eigenvalue,
        min_eigenvalue: step.min_eigenvalue,
        admitted_directions: step.photometric_subspace.len(),
        brightness_gain: evaluation
            .photometric
            .as_ref()
            .and_then(|p| p.brightness.first())
            .map_or(1.0, |b| b.gain),
        brightness_bias: evaluation
            .photometric
            .as_ref()
            .and_then(|p| p.brightness.first())
            .map_or(0.0, |b| b.bias),
    };
    let mut degenerate = step.degenerate;
    degenerate.extend(ambiguous);
    let status = check(initial, &pose, &fitness, config);
    Alignment {
        world_from_source: pose,
        initial: *initial,
        status,
        covariance,
        information,
        target_information,
        target_correspondences: evaluation.per_target_count.clone(),
        fitness,
        degenerate,
        iterations,
        photometric: summary,
    }
}

fn check(
    initial: &Pose,
    pose: &Pose,
    fitness: &Fitness,
    config: &AlignConfig,
) -> Result<(), FailureReason> {
    if !se3::is_finite(pose) {
        return Err(FailureReason::NonFinite);
    }
    let (angle, dist) = pose_difference(initial, pose);
    let (rotation_deg, translation_m) = (angle.to_degrees(), dist);
    if rotation_deg > config.max_rotation_change_deg
        || translation_m > config.max_translation_change_m
    {
        return Err(FailureReason::Diverged {
            rotation_deg,
            translation_m,
            max_rotation_deg: config.max_rotation_change_deg,
            max_translation_m: config.max_translation_change_m,
        });
    }
    let needed = config.min_correspondences as usize;
    if fitness.correspondences < needed || fitness.overlap < config.min_overlap {
        return Err(FailureReason::TooLittleOverlap {
            correspondences: fitness.correspondences,
            overlap_percent: 100.0 * fitness.overlap,
            needed_correspondences: needed,
            needed_percent: 100.0 * config.min_overlap,
        });
    }
    if fitness.inlier_ratio_of_overlap < config.min_inlier_ratio {
        return Err(FailureReason::PoorFit {
            inlier_percent: 100.0 * fitness.inlier_ratio_of_overlap,
            needed_percent: 100.0 * config.min_inlier_ratio,
            rms_residual_m: fitness.rms_residual_m,
        });
    }
    Ok(())
}
