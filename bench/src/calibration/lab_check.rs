//! The registration half of the calibration's acceptance check: a `lab` capture
//! rendered with the true sensor is fused and registered by the daemon's offline path
//! (`texeld register`, [`texel_register::capture::register_capture`]) twice: as
//! recorded, with the true sensor model it carries, and with a calibrated sensor model
//! put in its place. The two runs' trajectory errors against `/truth/pose` are
//! compared: the daemon's own figure (positions relative to the first frame, no
//! alignment) and the same after a rigid alignment of the two trajectories (Horn's
//! absolute orientation, as trajectory benchmarks do). The second leaves out a
//! difference of frame definitions: a calibrated EO frame turned by a small rotation
//! from the true one turns the whole registered trajectory about the first frame,
//! while the model's shape is the same.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};
use texel::capture::{
    CaptureError, CaptureReader, CaptureWriter, PoseTopic, TexelItem, WriterOptions,
    open_texel_frames, topics,
};
use texel::{Pose, SensorModel};
use texel_register::RegistrationConfig;
use texel_register::capture::{RegisterCommandError, RegisterReport, register_capture};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum LabCheckError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error(transparent)]
    Register(#[from] RegisterCommandError),
    #[error("cannot render the lab capture: {0}")]
    Render(#[from] sims::SimError),
    #[error(
        "{0}: registration gave no trajectory error (the capture has no /truth/pose, or \
         no frame registered)"
    )]
    NoTruth(String),
}

/// Topics that describe the sensor rather than carry frames.
const SENSOR_TOPICS: [&str; 4] = [
    topics::LIDAR_CALIBRATION,
    topics::EO_CALIBRATION,
    topics::TF_STATIC,
    topics::TEXEL_SENSOR,
];

/// Copies `src` to `dst` with every sensor-describing message (both calibrations, the
/// extrinsic, `/texel/sensor`) replaced by `sensor`'s, written once where the first of
/// them was (or before the first message if there was none). Frames, poses and
/// everything else are copied unchanged. Returns the number of messages dropped.
pub fn replace_sensor(src: &Path, dst: &Path, sensor: &SensorModel) -> Result<usize, CaptureError> {
    let mut reader = CaptureReader::open(src)?;
    let mut writer = CaptureWriter::create(
        dst,
        WriterOptions {
            sync_to_disk: false,
            ..WriterOptions::default()
        },
    )?;
    let (mut written, mut dropped) = (false, 0usize);
    while let Some(message) = reader.next_message() {
        let message = match message {
            Ok(m) => m,
            Err(e) if e.is_fatal() => return Err(e),
            Err(_) => continue,
        };
        if !written {
            writer.write_sensor(sensor, message.log_time)?;
            written = true;
        }
        if SENSOR_TOPICS.contains(&message.channel.topic.as_str()) {
            dropped += 1;
            continue;
        }
        writer.copy_message(&message)?;
    }
    writer.finish()?;
    Ok(dropped)
}

/// What one registration run achieved against the truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegistrationErrors {
    /// Absolute trajectory error (RMSE of positions relative to the first frame), mm:
    /// the daemon's figure.
    pub ate_rmse_mm: f64,
    /// The same after the rigid motion that best aligns the registered positions
    /// with the true ones, mm (NaN with fewer than 3 registered frames).
    pub aligned_ate_rmse_mm: f64,
    /// Mean relative pose error between consecutive frames, mm and degrees.
    pub rpe_translation_mm: f64,
    pub rpe_rotation_deg: f64,
    pub registered: usize,
    pub frames: usize,
}

impl RegistrationErrors {
    fn from_report(
        report: &RegisterReport,
        truth: &BTreeMap<u64, Pose>,
    ) -> Result<Self, LabCheckError> {
        let ate_rmse_mm = report
            .ate_rmse_mm
            .filter(|v| v.is_finite())
            .ok_or_else(|| LabCheckError::NoTruth(report.capture.clone()))?;
        let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = report
            .per_frame
            .iter()
            .filter_map(|f| {
                let p = f.world_from_scan?;
                let t = truth.get(&f.timestamp_ns)?;
                Some((Vector3::new(p[0], p[1], p[2]), t.translation.vector))
            })
            .collect();
        Ok(Self {
            ate_rmse_mm,
            aligned_ate_rmse_mm: aligned_rmse(&pairs).map_or(f64::NAN, |e| e * 1e3),
            rpe_translation_mm: report.rpe_translation_mean_mm.unwrap_or(f64::NAN),
            rpe_rotation_deg: report.rpe_rotation_mean_deg.unwrap_or(f64::NAN),
            registered: report.registered,
            frames: report.frames,
        })
    }
}

/// Registration of one capture with its true sensor and with a calibrated one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegistrationComparison {
    pub truth: RegistrationErrors,
    pub calibrated: RegistrationErrors,
}

impl RegistrationComparison {
    /// ATE with the calibrated sensor over ATE with the true one (infinite when the
    /// true sensor's ATE is zero and the calibrated one's is not).
    pub fn ate_ratio(&self) -> f64 {
        ratio(self.calibrated.ate_rmse_mm, self.truth.ate_rmse_mm)
    }

    /// The same for the aligned ATE.
    pub fn aligned_ate_ratio(&self) -> f64 {
        ratio(
            self.calibrated.aligned_ate_rmse_mm,
            self.truth.aligned_ate_rmse_mm,
        )
    }
}

/// RMS distance between `b` and `a` moved by the rigid motion that best aligns
/// them (Horn 1987 / Kabsch: SVD of the cross-covariance of the centred sets, with
/// the reflection case excluded). `None` for fewer than 3 pairs or a failed SVD.
pub fn aligned_rmse(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> Option<f64> {
    if pairs.len() < 3 {
        return None;
    }
    let n = pairs.len() as f64;
    let mean_a = pairs.iter().map(|p| p.0).sum::<Vector3<f64>>() / n;
    let mean_b = pairs.iter().map(|p| p.1).sum::<Vector3<f64>>() / n;
    let cross: Matrix3<f64> = pairs
        .iter()
        .map(|(a, b)| (b - mean_b) * (a - mean_a).transpose())
        .sum();
    let svd = cross.try_svd(true, true, f64::EPSILON, 100)?;
    let (u, v_t) = (svd.u?, svd.v_t?);
    // The rotation u·diag(1, 1, ±1)·vᵀ with a positive determinant.
    let sign = if (u * v_t).determinant() < 0.0 {
        -1.0
    } else {
        1.0
    };
    let rotation = u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, sign)) * v_t;
    let sum: f64 = pairs
        .iter()
        .map(|(a, b)| (rotation * (a - mean_a) + mean_b - b).norm_squared())
        .sum();
    let rmse = (sum / n).sqrt();
    rmse.is_finite().then_some(rmse)
}

/// Every `/truth/pose` of a capture, by timestamp.
fn truth_poses(capture: &Path) -> Result<BTreeMap<u64, Pose>, CaptureError> {
    let mut out = BTreeMap::new();
    for item in open_texel_frames(capture)? {
        match item {
            Err(e) if e.is_fatal() => return Err(e),
            Ok(TexelItem::Pose {
                topic: PoseTopic::Truth,
                timestamp_ns,
                world_from_eo,
            }) => {
                out.insert(timestamp_ns, world_from_eo);
            }
            _ => {}
        }
    }
    Ok(out)
}

/// `a / b`, 1 when both are zero, infinite when only `b` is.
pub fn ratio(a: f64, b: f64) -> f64 {
    if b > 0.0 {
        a / b
    } else if a == 0.0 {
        1.0
    } else {
        f64::INFINITY
    }
}

/// Registers `lab_capture` (rendered with the true sensor, with `/truth/pose`) as it
/// is and with `calibrated` in place of its sensor model, writing the intermediate
/// captures into `work_dir`.
pub fn compare_registration(
    lab_capture: &Path,
    calibrated: &SensorModel,
    work_dir: &Path,
    config: &RegistrationConfig,
) -> Result<RegistrationComparison, LabCheckError> {
    let stem = lab_capture
        .file_stem()
        .map_or_else(|| "lab".into(), |s| s.to_string_lossy().into_owned());
    let in_dir = |suffix: &str| -> PathBuf { work_dir.join(format!("{stem}-{suffix}.mcap")) };
    let with_calibrated = in_dir("calibrated-sensor");
    replace_sensor(lab_capture, &with_calibrated, calibrated)?;
    let truth = register_capture(
        lab_capture,
        &in_dir("registered-true"),
        config.clone(),
        None,
        &mut |_| {},
    )?;
    let calib = register_capture(
        &with_calibrated,
        &in_dir("registered-calibrated"),
        config.clone(),
        None,
        &mut |_| {},
    )?;
    let poses = truth_poses(lab_capture)?;
    Ok(RegistrationComparison {
        truth: RegistrationErrors::from_report(&truth, &poses)?,
        calibrated: RegistrationErrors::from_report(&calib, &poses)?,
    })
}

/// Renders `frames` frames of `scene` (with its own sensor and effects) into a capture
/// at `path`, with `/truth/pose`.
pub fn render_lab_capture(
    scene: sims::Scene,
    seed: u64,
    frames: usize,
    path: &Path,
) -> Result<(), LabCheckError> {
    let sim = sims::Simulator::with_options(
        scene,
        &sims::SimOptions {
            seed,
            frames: Some(frames.max(2)),
            ..sims::SimOptions::default()
        },
    )?;
    let options = sims::CaptureOptions {
        writer: WriterOptions {
            sync_to_disk: false,
            ..WriterOptions::default()
        },
        ..sims::CaptureOptions::default()
    };
    sims::render_capture(&sim, path, &options, &mut |_, _| {})?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    #[test]
    fn alignment_removes_a_rigid_motion_and_keeps_the_rest() {
        let truth: Vec<Vector3<f64>> = (0..12)
            .map(|k| {
                let a = f64::from(k) * 0.5;
                Vector3::new(2.2 * a.cos(), 2.2 * a.sin(), 1.5 + 0.1 * a)
            })
            .collect();
        let r = Rotation3::from_euler_angles(0.01, -0.02, 0.03);
        let t = Vector3::new(0.3, -0.1, 0.2);
        let moved: Vec<_> = truth.iter().map(|p| (r * p + t, *p)).collect();
        assert!(aligned_rmse(&moved).unwrap() < 1e-12);
        // A 1 mm error on one axis of every other point survives the alignment
        // (mostly: the fit spreads it).
        let bent: Vec<_> = moved
            .iter()
            .enumerate()
            .map(|(k, (a, b))| (a + Vector3::x() * if k % 2 == 0 { 1e-3 } else { -1e-3 }, *b))
            .collect();
        let e = aligned_rmse(&bent).unwrap();
        assert!(e > 0.5e-3 && e <= 1.0e-3 + 1e-12, "{e}");
        assert!(aligned_rmse(&moved[..2]).is_none());
    }

    #[test]
    fn ratios_guard_zero() {
        assert_eq!(ratio(0.0, 0.0), 1.0);
        assert!(ratio(1.0, 0.0).is_infinite());
        assert_eq!(ratio(1.0, 2.0), 0.5);
    }
}
