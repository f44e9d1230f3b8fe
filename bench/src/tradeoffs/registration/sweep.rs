//! The sweep: each setting registers each sequence on one core, and the result is
//! measured against the simulator's truth: absolute trajectory error, relative pose
//! error per frame, end drift over the path length, time per scan.

use std::collections::BTreeMap;
use std::sync::Arc;

use serde::Serialize;
use texel::Pose;
use texel::pose::pose_difference;

use super::data::Sequence;
use texel_register::clock::{Stopwatch, quantile};
use texel_register::{PhotometricMode, Registrar, RegistrationConfig, RobustKernel, Solver};

/// A named configuration.
#[derive(Debug, Clone)]
pub struct Setting {
    pub name: String,
    pub config: RegistrationConfig,
}

fn setting(name: &str, edit: impl FnOnce(&mut RegistrationConfig)) -> Setting {
    let mut config = RegistrationConfig::default();
    // One core: the reductions run on the calling thread (bit-identical anyway).
    config.align.parallel = false;
    edit(&mut config);
    Setting {
        name: name.to_string(),
        config,
    }
}

/// The settings swept: the defaults, then one knob at a time.
pub fn settings(quick: bool) -> Vec<Setting> {
    let mut out = vec![
        setting("defaults", |_| {}),
        setting("photometric off", |c| {
            c.align.photometric.mode = PhotometricMode::Off
        }),
        setting("global refinement off", |c| c.global.enabled = false),
        setting("pyramid levels 1", |c| c.align.pyramid_levels = 1),
        setting("point stride 4", |c| c.align.point_stride = 4),
        setting("iterations 3", |c| c.align.max_iterations = 3),
    ];
    if quick {
        return out;
    }
    out.extend([
        setting("pyramid levels 2", |c| c.align.pyramid_levels = 2),
        setting("pyramid levels 4", |c| c.align.pyramid_levels = 4),
        setting("iterations 5", |c| c.align.max_iterations = 5),
        setting("iterations 20", |c| c.align.max_iterations = 20),
        setting("point stride 1", |c| c.align.point_stride = 1),
        setting("kernel tukey", |c| c.align.kernel = RobustKernel::Tukey),
        setting("kernel geman-mcclure", |c| {
            c.align.kernel = RobustKernel::GemanMcclure
        }),
        setting("photometric full", |c| {
            c.align.photometric.mode = PhotometricMode::Full
        }),
        setting("levenberg-marquardt", |c| {
            c.align.solver = Solver::LevenbergMarquardt
        }),
        setting("keyframe window 1", |c| c.keyframes.window = 1),
        setting("loop interval 4 keyframes", |c| {
            c.global.loop_interval_keyframes = 4
        }),
    ]);
    out
}

/// What one setting did on one sequence.
#[derive(Debug, Clone, Serialize)]
pub struct RunMetrics {
    pub scene: String,
    pub setting: String,
    pub frames: usize,
    pub registered: usize,
    pub failed: usize,
    pub keyframes: u64,
    pub loop_closures: u64,
    pub path_length_m: f64,
    /// RMSE of the position errors relative to the first frame, millimetres.
    pub ate_rmse_mm: f64,
    /// Error of the last registered frame over the path length, percent.
    pub drift_percent: f64,
    /// Mean relative pose error between consecutive registered frames.
    pub rpe_deg: f64,
    pub rpe_mm: f64,
    /// Registration CPU time per scan (one core), milliseconds.
    pub time_median_ms: f64,
    pub time_p95_ms: f64,
    /// Wall time per scan on this (shared) machine.
    pub wall_median_ms: f64,
    /// Registered frames whose result names a direction neither sensor fixed (or
    /// fixed ambiguously).
    pub degenerate_frames: usize,
    /// Per registered frame: the smallest eigenvalue of the alignment's
    /// information, geometry alone and with the photometric term (kept for the
    /// corridor's figure only; empty otherwise).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub min_eigenvalues: Vec<[f64; 2]>,
}

/// Registers `sequence` with `setting` (anchored at the first true pose) and
/// measures it.
pub fn run(sequence: &Sequence, setting: &Setting) -> RunMetrics {
    let anchor = sequence
        .truth
        .first()
        .copied()
        .unwrap_or_else(Pose::identity);
    let mut registrar = Registrar::with_anchor(setting.config.clone(), anchor);
    let mut frame_of_id: BTreeMap<u64, usize> = BTreeMap::new();
    let mut frame_of_time: BTreeMap<u64, usize> = BTreeMap::new();
    let (mut cpu, mut wall) = (Vec::new(), Vec::new());
    let (mut degenerate_frames, mut min_eigenvalues) = (0, Vec::new());
    for (frame, scan) in sequence.scans.iter().enumerate() {
        frame_of_time.insert(scan.timestamp_ns, frame);
        let watch = Stopwatch::start();
        let result = registrar.register(Arc::clone(scan), &sequence.sensor);
        let elapsed = watch.elapsed();
        if frame > 0 {
            cpu.push(elapsed.cpu_ms);
            wall.push(elapsed.wall_ms);
        }
        if let Some(id) = result.scan_id {
            frame_of_id.insert(id, frame);
            if frame > 0 {
                degenerate_frames += usize::from(!result.degenerate.is_empty());
                min_eigenvalues.push([
                    result.photometric.geometry_min_eigenvalue,
                    result.photometric.min_eigenvalue,
                ]);
            }
        }
        for recovered in registrar.take_recovered() {
            if let (Some(id), Some(&f)) = (
                recovered.scan_id,
                frame_of_time.get(&recovered.timestamp_ns),
            ) {
                frame_of_id.insert(id, f);
            }
        }
        registrar.take_events();
        registrar.take_anchors();
    }
    // Final poses by frame (after all refinement).
    let mut estimate: BTreeMap<usize, Pose> = BTreeMap::new();
    for (&id, &frame) in &frame_of_id {
        if let Some(p) = registrar.pose(id) {
            estimate.insert(frame, p);
        }
    }
    let errors = trajectory_errors(&estimate, &sequence.truth);
    let stats = registrar.stats();
    RunMetrics {
        scene: sequence.scene.clone(),
        setting: setting.name.clone(),
        frames: sequence.scans.len(),
        registered: estimate.len(),
        failed: sequence.scans.len() - estimate.len(),
        keyframes: stats.keyframes,
        loop_closures: stats.loop_closures,
        path_length_m: sequence.path_length_m,
        ate_rmse_mm: errors.ate_rmse_m * 1000.0,
        drift_percent: if sequence.path_length_m > 0.0 {
            100.0 * errors.end_error_m / sequence.path_length_m
        } else {
            0.0
        },
        rpe_deg: errors.rpe_rad.to_degrees(),
        rpe_mm: errors.rpe_m * 1000.0,
        time_median_ms: quantile(&cpu, 0.5),
        time_p95_ms: quantile(&cpu, 0.95),
        wall_median_ms: quantile(&wall, 0.5),
        degenerate_frames,
        min_eigenvalues,
    }
}

/// Trajectory errors of an estimate against the truth, both taken relative to the
/// first estimated frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TrajectoryErrors {
    pub ate_rmse_m: f64,
    pub end_error_m: f64,
    /// Mean over consecutive estimated frames.
    pub rpe_rad: f64,
    pub rpe_m: f64,
}

pub fn trajectory_errors(estimate: &BTreeMap<usize, Pose>, truth: &[Pose]) -> TrajectoryErrors {
    let Some((&f0, e0)) = estimate.iter().next() else {
        return TrajectoryErrors::default();
    };
    let Some(t0) = truth.get(f0) else {
        return TrajectoryErrors::default();
    };
    let (mut sq, mut n, mut end) = (0.0, 0usize, 0.0);
    let (mut rpe_r, mut rpe_t, mut m) = (0.0, 0.0, 0usize);
    let mut previous: Option<(Pose, Pose)> = None;
    for (&f, est) in estimate {
        let Some(tr) = truth.get(f) else { continue };
        let (_, d) = pose_difference(&(e0.inverse() * est), &(t0.inverse() * tr));
        sq += d * d;
        n += 1;
        end = d;
        if let Some((pe, pt)) = previous {
            let (a, d) = pose_difference(&(pe.inverse() * est), &(pt.inverse() * tr));
            rpe_r += a;
            rpe_t += d;
            m += 1;
        }
        previous = Some((*est, *tr));
    }
    TrajectoryErrors {
        ate_rmse_m: if n > 0 { (sq / n as f64).sqrt() } else { 0.0 },
        end_error_m: end,
        rpe_rad: if m > 0 { rpe_r / m as f64 } else { 0.0 },
        rpe_m: if m > 0 { rpe_t / m as f64 } else { 0.0 },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_of_a_shifted_and_a_drifting_trajectory() {
        let truth: Vec<Pose> = (0..5)
            .map(|k| Pose::translation(k as f64, 0.0, 0.0))
            .collect();
        // The same trajectory elsewhere in the world: no error relative to frame 0.
        let shifted: BTreeMap<usize, Pose> = truth
            .iter()
            .enumerate()
            .map(|(k, p)| (k, Pose::translation(0.0, 5.0, 0.0) * p))
            .collect();
        let e = trajectory_errors(&shifted, &truth);
        assert!(e.ate_rmse_m < 1e-12 && e.end_error_m < 1e-12 && e.rpe_m < 1e-12);
        // 1 cm too long per step: errors 0, 1, 2, 3, 4 cm.
        let drifting: BTreeMap<usize, Pose> = (0..5)
            .map(|k| (k, Pose::translation(k as f64 * 1.01, 0.0, 0.0)))
            .collect();
        let e = trajectory_errors(&drifting, &truth);
        assert!((e.end_error_m - 0.04).abs() < 1e-9);
        assert!((e.rpe_m - 0.01).abs() < 1e-9);
        let rmse = ((0.0 + 1.0 + 4.0 + 9.0 + 16.0) / 5.0f64).sqrt() * 0.01;
        assert!((e.ate_rmse_m - rmse).abs() < 1e-9);
        assert_eq!(
            trajectory_errors(&BTreeMap::new(), &truth),
            TrajectoryErrors::default()
        );
    }
}
