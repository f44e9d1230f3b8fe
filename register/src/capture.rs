//! Offline registration of a whole capture: every texel frame fused and registered,
//! a copy of the capture written with `/texel/pose` added for every registered frame,
//! plus an optional JSON report (per-frame status, time, fitness and, where the
//! capture has `/truth/pose`, the errors against it). The one part of this crate that
//! reads and writes files; the registration itself stays I/O-free.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
use serde::Serialize;
use texel::capture::{
    CaptureError, CaptureReader, CaptureWriter, PoseTopic, SensorCache, TexelItem, WriterOptions,
    open_texel_frames, topics,
};
use texel::pose::pose_difference;
use texel::{FuseConfig, Pose};
use thiserror::Error;

use crate::clock::{Stopwatch, quantile};
use crate::{
    ConfigError, DegenerateDirection, Fitness, PhotometricSummary, Registrar, RegistrationConfig,
    RegistrationStatus,
};

#[derive(Debug, Error)]
pub enum RegisterCommandError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("{0}: the capture has no texel frames")]
    NoFrames(String),
    #[error("cannot write the report {path}: {message}")]
    Report { path: String, message: String },
}

/// One frame of the report.
#[derive(Debug, Clone, Serialize)]
pub struct FrameReport {
    pub index: usize,
    pub timestamp_ns: u64,
    #[serde(flatten)]
    pub status: RegistrationStatus,
    /// Retried later and registered then.
    pub recovered: bool,
    pub scan_id: Option<u64>,
    /// Fusion of the frame into a scan (not part of registration), wall time.
    pub fuse_ms: f64,
    /// Registration of the scan (pyramid, alignment, keyframes, loop closure, pose
    /// graph), wall time and the process's CPU time.
    pub time_ms: f64,
    pub cpu_ms: f64,
    pub iterations: u32,
    pub fitness: Fitness,
    pub degenerate: Vec<DegenerateDirection>,
    /// What the photometric term did: residuals, the smallest eigenvalue of the
    /// information before and after it, the brightness change.
    pub photometric: PhotometricSummary,
    pub keyframe: bool,
    pub loop_closures: u32,
    /// Final pose (after global refinement): `[x, y, z, qx, qy, qz, qw]`.
    pub world_from_scan: Option<[f64; 7]>,
    /// Against `/truth/pose` (both relative to the first frame): degrees and
    /// millimetres.
    pub rotation_error_deg: Option<f64>,
    pub translation_error_mm: Option<f64>,
    /// Relative pose error to the previous registered frame, degrees and mm.
    pub rpe_rotation_deg: Option<f64>,
    pub rpe_translation_mm: Option<f64>,
}

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct RegisterReport {
    pub capture: String,
    pub frames: usize,
    pub registered: usize,
    pub failed: usize,
    pub recovered: usize,
    pub keyframes: u64,
    pub loop_closures: u64,
    /// Registration time per frame (without fusion): wall...
    pub time_median_ms: f64,
    pub time_p95_ms: f64,
    /// ... and CPU time (all threads).
    pub cpu_median_ms: f64,
    pub cpu_p95_ms: f64,
    pub path_length_m: Option<f64>,
    /// Absolute trajectory error (RMSE of positions), millimetres.
    pub ate_rmse_mm: Option<f64>,
    /// Translation error of the last registered frame over the path length, percent.
    pub drift_percent: Option<f64>,
    pub rpe_rotation_mean_deg: Option<f64>,
    pub rpe_translation_mean_mm: Option<f64>,
    pub config: RegistrationConfig,
    pub per_frame: Vec<FrameReport>,
}

/// How far [`register_capture`] has come, for a caller's progress display.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Progress {
    /// The capture holds this many texel frames.
    Started { frames: usize },
    /// One more frame was fused and registered (or failed).
    Frame,
    /// Every frame is done; the output is being written.
    Finished,
}

/// The world frame when the capture has no truth to anchor to: the first camera
/// looks along world +x with its image up along world +z (the capture format's
/// world is z-up; the optical frame is y-down, z-forward).
pub fn default_anchor() -> Pose {
    let r = Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
    Pose::from_parts(
        nalgebra::Translation3::identity(),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)),
    )
}

/// Registers `capture` and writes `out` (and `report`, if given).
pub fn register_capture(
    capture: &Path,
    out: &Path,
    config: RegistrationConfig,
    report_path: Option<&Path>,
    progress: &mut dyn FnMut(Progress),
) -> Result<RegisterReport, RegisterCommandError> {
    let display = capture.display().to_string();
    // Pass 1: truth poses and a frame count, for the anchor and the progress bar.
    let mut truth: BTreeMap<u64, Pose> = BTreeMap::new();
    let mut frame_count = 0usize;
    for item in open_texel_frames(capture)? {
        match item {
            Err(e) if e.is_fatal() => return Err(e.into()),
            Err(_) => {}
            Ok(TexelItem::Pair { .. }) => frame_count += 1,
            Ok(TexelItem::Pose {
                topic: PoseTopic::Truth,
                timestamp_ns,
                world_from_eo,
            }) => {
                truth.insert(timestamp_ns, world_from_eo);
            }
            Ok(TexelItem::Pose { .. } | TexelItem::Anchor(_)) => {}
        }
    }
    if frame_count == 0 {
        return Err(RegisterCommandError::NoFrames(display));
    }
    progress(Progress::Started {
        frames: frame_count,
    });

    // Pass 2: fuse and register every frame.
    let mut registrar: Option<Registrar> = None;
    let mut sensors = SensorCache::new();
    let mut frames: Vec<FrameReport> = Vec::with_capacity(frame_count);
    let mut index_of_id: BTreeMap<u64, usize> = BTreeMap::new();
    let fuse_config = FuseConfig::default();
    for item in open_texel_frames(capture)? {
        let (pair, model) = match item {
            Err(e) if e.is_fatal() => return Err(e.into()),
            Ok(TexelItem::Pair { pair, sensor }) => (pair, sensor),
            _ => continue,
        };
        let index = frames.len();
        let timestamp_ns = pair.timestamp_ns();
        let registrar = registrar.get_or_insert_with(|| {
            let anchor = truth
                .get(&timestamp_ns)
                .copied()
                .unwrap_or_else(default_anchor);
            Registrar::with_anchor(config.clone(), anchor)
        });
        let started = Instant::now();
        let scan = match sensors.fuse(pair, &model, &fuse_config) {
            Ok(scan) => Arc::new(scan),
            Err(_) => {
                frames.push(failed_frame(index, timestamp_ns));
                progress(Progress::Frame);
                continue;
            }
        };
        let fuse_ms = started.elapsed().as_secs_f64() * 1000.0;
        let watch = Stopwatch::start();
        let result = registrar.register(scan, &model);
        let elapsed = watch.elapsed();
        if let Some(id) = result.scan_id {
            index_of_id.insert(id, index);
        }
        for recovered in registrar.take_recovered() {
            if let (Some(id), Some(i)) = (
                recovered.scan_id,
                frames
                    .iter()
                    .position(|f| f.timestamp_ns == recovered.timestamp_ns),
            ) {
                index_of_id.insert(id, i);
                frames[i].recovered = true;
                frames[i].scan_id = Some(id);
            }
        }
        registrar.take_events();
        registrar.take_anchors();
        frames.push(FrameReport {
            index,
            timestamp_ns,
            status: result.status.clone(),
            recovered: false,
            scan_id: result.scan_id,
            fuse_ms,
            time_ms: elapsed.wall_ms,
            cpu_ms: elapsed.cpu_ms,
            iterations: result.iterations,
            fitness: result.fitness,
            degenerate: result.degenerate.clone(),
            photometric: result.photometric,
            keyframe: result.keyframe,
            loop_closures: result.loop_closures,
            world_from_scan: None,
            rotation_error_deg: None,
            translation_error_mm: None,
            rpe_rotation_deg: None,
            rpe_translation_mm: None,
        });
        progress(Progress::Frame);
    }
    progress(Progress::Finished);

    // Final poses (after all refinement), by timestamp.
    let mut poses: BTreeMap<u64, Pose> = BTreeMap::new();
    if let Some(reg) = &registrar {
        for (&id, &i) in &index_of_id {
            if let Some(p) = reg.pose(id) {
                poses.insert(frames[i].timestamp_ns, p);
                let (t, q) = texel::pose::pose_to_parts(&p);
                frames[i].world_from_scan = Some([t[0], t[1], t[2], q[0], q[1], q[2], q[3]]);
            }
        }
    }
    write_output(capture, out, &poses)?;
    let report = summarise(&display, frames, &truth, &poses, registrar.as_ref(), config);
    if let Some(path) = report_path {
        let text =
            serde_json::to_string_pretty(&report).map_err(|e| RegisterCommandError::Report {
                path: path.display().to_string(),
                message: e.to_string(),
            })?;
        std::fs::write(path, text).map_err(|e| RegisterCommandError::Report {
            path: path.display().to_string(),
            message: e.to_string(),
        })?;
    }
    Ok(report)
}

/// A frame that could not even be fused (its sizes disagree with the sensor).
fn failed_frame(index: usize, timestamp_ns: u64) -> FrameReport {
    FrameReport {
        index,
        timestamp_ns,
        status: RegistrationStatus::Failed {
            reason: crate::FailureReason::NoPoints {
                side: "scan (fusion refused the frame)",
                count: 0,
                needed: 0,
            },
        },
        recovered: false,
        scan_id: None,
        fuse_ms: 0.0,
        time_ms: 0.0,
        cpu_ms: 0.0,
        iterations: 0,
        fitness: Fitness::default(),
        degenerate: Vec::new(),
        photometric: PhotometricSummary::default(),
        keyframe: false,
        loop_closures: 0,
        world_from_scan: None,
        rotation_error_deg: None,
        translation_error_mm: None,
        rpe_rotation_deg: None,
        rpe_translation_mm: None,
    }
}

/// Copies every message of `capture` except old `/texel/pose` ones, inserting each
/// frame's pose after the last message at or before its timestamp.
fn write_output(
    capture: &Path,
    out: &Path,
    poses: &BTreeMap<u64, Pose>,
) -> Result<(), RegisterCommandError> {
    let mut reader = CaptureReader::open(capture)?;
    let mut writer = CaptureWriter::create(out, WriterOptions::default())?;
    let mut pending = poses.iter().peekable();
    while let Some(message) = reader.next_message() {
        let message = match message {
            Ok(m) => m,
            Err(e) if e.is_fatal() => return Err(e.into()),
            Err(_) => continue,
        };
        while let Some(&(&t, pose)) = pending.peek() {
            if t < message.log_time {
                writer.write_pose(PoseTopic::Texel, t, pose)?;
                pending.next();
            } else {
                break;
            }
        }
        // The earlier registration's poses and anchors are replaced as a whole: an
        // old anchor composed with a new keyframe pose would place a frame wrongly.
        if message.channel.topic == topics::TEXEL_POSE
            || message.channel.topic == topics::TEXEL_ANCHOR
        {
            continue;
        }
        writer.copy_message(&message)?;
    }
    for (&t, pose) in pending {
        writer.write_pose(PoseTopic::Texel, t, pose)?;
    }
    writer.finish()?;
    Ok(())
}

fn summarise(
    capture: &str,
    mut frames: Vec<FrameReport>,
    truth: &BTreeMap<u64, Pose>,
    poses: &BTreeMap<u64, Pose>,
    registrar: Option<&Registrar>,
    config: RegistrationConfig,
) -> RegisterReport {
    // Errors relative to the first registered frame that has truth.
    let first = poses
        .iter()
        .find_map(|(t, p)| truth.get(t).map(|tr| (*p, *tr)));
    let mut sq_sum = 0.0;
    let mut count = 0usize;
    let mut rpe = (0.0, 0.0, 0usize);
    let mut previous: Option<(Pose, Pose)> = None;
    let mut path = 0.0;
    let mut last_error_m = None;
    if let Some((est0, truth0)) = first {
        for f in frames.iter_mut() {
            let (Some(est), Some(tr)) = (poses.get(&f.timestamp_ns), truth.get(&f.timestamp_ns))
            else {
                continue;
            };
            let est_rel = est0.inverse() * est;
            let tr_rel = truth0.inverse() * tr;
            let (angle, dist) = pose_difference(&est_rel, &tr_rel);
            f.rotation_error_deg = Some(angle.to_degrees());
            f.translation_error_mm = Some(dist * 1000.0);
            sq_sum += dist * dist;
            count += 1;
            last_error_m = Some(dist);
            if let Some((pe, pt)) = previous {
                let (a, d) = pose_difference(&(pe.inverse() * est), &(pt.inverse() * tr));
                f.rpe_rotation_deg = Some(a.to_degrees());
                f.rpe_translation_mm = Some(d * 1000.0);
                rpe = (rpe.0 + a.to_degrees(), rpe.1 + d * 1000.0, rpe.2 + 1);
                path += (pt.translation.vector - tr.translation.vector).norm();
            }
            previous = Some((*est, *tr));
        }
    }
    let timed = || {
        frames
            .iter()
            .filter(|f| f.status.is_registered() && f.iterations > 0)
    };
    let times: Vec<f64> = timed().map(|f| f.time_ms).collect();
    let cpu: Vec<f64> = timed().map(|f| f.cpu_ms).collect();
    let stats = registrar.map(|r| r.stats()).unwrap_or_default();
    let has_truth = count > 0;
    RegisterReport {
        capture: capture.to_string(),
        frames: frames.len(),
        registered: frames
            .iter()
            .filter(|f| f.status.is_registered() || f.recovered)
            .count(),
        failed: frames
            .iter()
            .filter(|f| !f.status.is_registered() && !f.recovered)
            .count(),
        recovered: frames.iter().filter(|f| f.recovered).count(),
        keyframes: stats.keyframes,
        loop_closures: stats.loop_closures,
        time_median_ms: quantile(&times, 0.5),
        time_p95_ms: quantile(&times, 0.95),
        cpu_median_ms: quantile(&cpu, 0.5),
        cpu_p95_ms: quantile(&cpu, 0.95),
        path_length_m: has_truth.then_some(path),
        ate_rmse_mm: has_truth.then(|| (sq_sum / count as f64).sqrt() * 1000.0),
        drift_percent: match last_error_m {
            Some(e) if path > 0.0 => Some(100.0 * e / path),
            _ => None,
        },
        rpe_rotation_mean_deg: (rpe.2 > 0).then(|| rpe.0 / rpe.2 as f64),
        rpe_translation_mean_mm: (rpe.2 > 0).then(|| rpe.1 / rpe.2 as f64),
        config,
        per_frame: frames,
    }
}
