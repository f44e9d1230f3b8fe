//! The registration half of the calibration's acceptance check: a `lab` capture
//! rendered with the true sensor is fused and registered by the daemon's offline path
//! (`texeld register`, [`texel_daemon::register_cli::register_capture`]) twice: as
//! recorded, with the true sensor model it carries, and with a calibrated sensor model
//! put in its place. The two runs' trajectory errors against `/truth/pose` are
//! compared.

use std::path::{Path, PathBuf};

use texel::SensorModel;
use texel::capture::{CaptureError, CaptureReader, CaptureWriter, WriterOptions, topics};
use texel_daemon::register::RegistrationConfig;
use texel_daemon::register_cli::{RegisterCommandError, RegisterReport, register_capture};
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
    /// Absolute trajectory error (RMSE of positions relative to the first frame), mm.
    pub ate_rmse_mm: f64,
    /// Mean relative pose error between consecutive frames, mm and degrees.
    pub rpe_translation_mm: f64,
    pub rpe_rotation_deg: f64,
    pub registered: usize,
    pub frames: usize,
}

impl RegistrationErrors {
    fn from_report(report: &RegisterReport) -> Result<Self, LabCheckError> {
        let ate_rmse_mm = report
            .ate_rmse_mm
            .filter(|v| v.is_finite())
            .ok_or_else(|| LabCheckError::NoTruth(report.capture.clone()))?;
        Ok(Self {
            ate_rmse_mm,
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
        false,
    )?;
    let calib = register_capture(
        &with_calibrated,
        &in_dir("registered-calibrated"),
        config.clone(),
        None,
        false,
    )?;
    Ok(RegistrationComparison {
        truth: RegistrationErrors::from_report(&truth)?,
        calibrated: RegistrationErrors::from_report(&calib)?,
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
