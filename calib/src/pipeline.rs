//! The calibration recipe: detect the board in every view (EO corners; lidar plate,
//! plane and intensity corners), calibrate the EO camera, refine EO and lidar
//! jointly, and assemble the sensor model.

use rayon::prelude::*;
use texel::{FramePair, PinholeCamera, SensorInfo, SensorModel};

use crate::config::CalibConfig;
use crate::detect::{BoardCorners, DetectParams, detect_board};
use crate::eo::{EoObservation, EoSolution, MIN_VIEWS, calibrate_eo};
use crate::error::CalibError;
use crate::extrinsic::{LidarSolution, Paired, calibrate_joint};
use crate::gray::GrayImage;
use crate::lidar::{LidarBoard, detect_lidar_board};

/// One texel frame of the target.
#[derive(Debug, Clone)]
pub struct CalibView {
    pub timestamp_ns: u64,
    pub pair: FramePair,
}

/// What a calibration is given.
#[derive(Debug, Clone)]
pub struct CalibInput {
    pub views: Vec<CalibView>,
    /// The lidar's intrinsics, taken as known (the capture's `/lidar/calibration`)
    /// unless the configuration asks to estimate them.
    pub lidar: PinholeCamera,
    /// Range noise, range limits and name carried into the sensor file.
    pub info: SensorInfo,
    /// Things worth knowing about the input (skipped messages, a truncated file).
    pub warnings: Vec<String>,
}

/// What was found in one view.
#[derive(Debug, Clone)]
pub struct ViewDetection {
    pub index: usize,
    pub timestamp_ns: u64,
    pub eo: Result<BoardCorners, String>,
    pub lidar: Result<LidarBoard, String>,
}

/// Stages reported to the progress callback.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    Detect,
    SolveEo,
    SolveJoint,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Self::Detect => "detecting the board",
            Self::SolveEo => "EO intrinsics",
            Self::SolveJoint => "joint EO-lidar refinement",
        }
    }
}

/// A finished calibration.
#[derive(Debug, Clone)]
pub struct Calibration {
    pub sensor: SensorModel,
    pub eo: EoSolution,
    pub lidar: LidarSolution,
    pub detections: Vec<ViewDetection>,
    /// EO-only solution before the joint refinement (for comparison).
    pub eo_only: EoSolution,
    pub seconds_detect: f64,
    pub seconds_solve: f64,
}

/// Detects the board in every view, `progress(done, total)` after each chunk.
pub fn detect_all(
    input: &CalibInput,
    config: &CalibConfig,
    progress: &mut dyn FnMut(usize, usize),
) -> Vec<ViewDetection> {
    let total = input.views.len();
    let chunk = rayon::current_num_threads().max(1) * 2;
    let mut out = Vec::with_capacity(total);
    for start in (0..total).step_by(chunk) {
        let end = (start + chunk).min(total);
        let part: Vec<ViewDetection> = (start..end)
            .into_par_iter()
            .map(|index| detect_view(input, config, index))
            .collect();
        out.extend(part);
        progress(end, total);
    }
    out
}

fn detect_view(input: &CalibInput, config: &CalibConfig, index: usize) -> ViewDetection {
    let view = &input.views[index];
    let eo = GrayImage::from_eo(&view.pair.eo)
        .ok_or_else(|| "the EO frame's buffer does not match its size".to_string())
        .and_then(|g| {
            detect_board(&g, &config.target, &DetectParams::eo(g.width, g.height))
                .map_err(|e| e.to_string())
        });
    let lidar = detect_lidar_board(&view.pair.range, &input.lidar, &config.target, index);
    ViewDetection {
        index,
        timestamp_ns: view.timestamp_ns,
        eo,
        lidar,
    }
}

/// Calibrates a texel camera from views of the target.
pub fn calibrate(
    input: &CalibInput,
    config: &CalibConfig,
    progress: &mut dyn FnMut(Stage, usize, usize),
) -> Result<Calibration, CalibError> {
    config.validate()?;
    let start = std::time::Instant::now();
    // Step 1: the board in every view, from pixels alone.
    let detections = detect_all(input, config, &mut |d, t| progress(Stage::Detect, d, t));
    let seconds_detect = start.elapsed().as_secs_f64();
    calibrate_detected(input, config, detections, seconds_detect, progress)
}

/// [`calibrate`] from detections already made.
pub fn calibrate_detected(
    input: &CalibInput,
    config: &CalibConfig,
    detections: Vec<ViewDetection>,
    seconds_detect: f64,
    progress: &mut dyn FnMut(Stage, usize, usize),
) -> Result<Calibration, CalibError> {
    let solve_start = std::time::Instant::now();
    let (width, height) = input
        .views
        .first()
        .map(|v| (v.pair.eo.width, v.pair.eo.height))
        .ok_or_else(|| CalibError::Input("the capture has no texel frames".into()))?;
    if let Some(v) = input
        .views
        .iter()
        .find(|v| (v.pair.eo.width, v.pair.eo.height) != (width, height))
    {
        return Err(CalibError::Input(format!(
            "EO frames change size within the capture ({width}x{height}, then {}x{} at {} ns)",
            v.pair.eo.width, v.pair.eo.height, v.timestamp_ns
        )));
    }
    // Step 2: EO intrinsics and distortion from the views that show the whole board.
    let observations: Vec<EoObservation> = detections
        .iter()
        .filter_map(|d| {
            d.eo.as_ref().ok().map(|c| EoObservation {
                view: d.index,
                corners: c.clone(),
            })
        })
        .collect();
    if observations.len() < MIN_VIEWS {
        let reasons: String = detections
            .iter()
            .filter_map(|d| {
                d.eo.as_ref()
                    .err()
                    .map(|e| format!("; frame {}: {e}", d.index))
            })
            .take(5)
            .collect();
        return Err(CalibError::TooFewViews {
            usable: observations.len(),
            total: detections.len(),
            needed: MIN_VIEWS,
            nx: config.target.nx(),
            ny: config.target.ny(),
            reasons,
        });
    }
    progress(Stage::SolveEo, 0, 1);
    let eo_only = calibrate_eo(&observations, &config.target, width, height, &config.solver)?;
    progress(Stage::SolveEo, 1, 1);
    // Step 3: lidar views of the whole plate, paired with their EO observation.
    let paired: Vec<Paired<'_>> = observations
        .iter()
        .enumerate()
        .filter_map(|(o, obs)| {
            detections[obs.view]
                .lidar
                .as_ref()
                .ok()
                .map(|board| Paired {
                    observation: o,
                    board,
                })
        })
        .collect();
    if paired.is_empty() {
        let mut reasons: Vec<String> = detections
            .iter()
            .filter_map(|d| {
                d.lidar
                    .as_ref()
                    .err()
                    .map(|e| format!("frame {}: {e}", d.index))
            })
            .take(4)
            .collect();
        if reasons.is_empty() {
            reasons.push("no frame shows the board to both cameras".into());
        }
        return Err(CalibError::LidarNeverSawTarget {
            views: detections.len(),
            reasons: reasons.join("; "),
        });
    }
    // Step 4: EO and lidar refined together (extrinsic, range bias, lidar intrinsics
    // when asked).
    progress(Stage::SolveJoint, 0, 1);
    let (eo, lidar) = calibrate_joint(
        &eo_only,
        &paired,
        &input.lidar,
        &config.target,
        &config.solver,
    )?;
    progress(Stage::SolveJoint, 1, 1);
    let sensor = SensorModel::from_capture_parts(
        lidar.lidar.clone(),
        eo.camera.clone(),
        lidar.eo_from_lidar,
        &input.info,
    );
    Ok(Calibration {
        sensor,
        eo,
        lidar,
        detections,
        eo_only,
        seconds_detect,
        seconds_solve: solve_start.elapsed().as_secs_f64(),
    })
}

impl Calibration {
    /// The sensor file text, with a header recording how it was made and the range
    /// bias (which the sensor file format has no field for).
    pub fn sensor_file_text(&self, source: &str) -> String {
        let used = self.eo.per_view.len();
        format!(
            "# Calibrated by texel-calib from {source}: {used} EO views (reprojection RMS \
             {:.3} px), {} lidar views.\n# Estimated range bias: {:+.2} mm ± {:.2} mm \
             (not applied: the sensor file has no range-bias field).\n{}",
            self.eo.rms_px,
            self.lidar.per_view.len(),
            self.lidar.range_bias_m * 1e3,
            self.lidar.range_bias_std_m * 1e3,
            self.sensor.to_toml_string()
        )
    }
}
