//! `texeld export`: one texel frame of a capture, fused and written as PLY or glTF, in
//! its own EO frame or placed in the world by the capture's `/texel/pose` (else
//! `/truth/pose`).

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use texel::capture::{CaptureError, PoseTopic, TexelItem, open_texel_frames};
use texel::export::{ExportError, ExportScan, write_gltf, write_ply};
use texel::fuse::FuseError;
use texel::{FuseConfig, Pose, Sensor, SensorModel, TexelScan, fuse};
use thiserror::Error;

/// Output formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExportFormat {
    Ply,
    Gltf,
}

#[derive(Debug, Error)]
pub enum ExportCommandError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error("{path} has {frames} texel frames; frame {index} does not exist")]
    NoSuchFrame {
        path: String,
        index: usize,
        frames: usize,
    },
    #[error(
        "{path}: no /texel/pose or /truth/pose at frame {index}'s timestamp {timestamp_ns} ns; export without --world"
    )]
    NoPose {
        path: String,
        index: usize,
        timestamp_ns: u64,
    },
    #[error("frame {index}: {source}")]
    Fuse { index: usize, source: FuseError },
    #[error(transparent)]
    Export(#[from] ExportError),
}

/// What was exported.
#[derive(Debug)]
pub struct ExportSummary {
    pub timestamp_ns: u64,
    pub vertices: usize,
    pub usable_triangles: usize,
    pub world_from_scan: Option<Pose>,
}

/// Reads frame `index` (0-based, in file order) and its poses.
fn read_frame(
    capture: &Path,
    index: usize,
    want_pose: bool,
) -> Result<(texel::FramePair, Arc<SensorModel>, Option<Pose>), ExportCommandError> {
    let path = capture.display().to_string();
    let mut found = None;
    let mut frames = 0;
    // Poses may come before or after their frame; keep them by timestamp.
    let mut poses: HashMap<(u64, bool), Pose> = HashMap::new();
    for item in open_texel_frames(capture)? {
        match item {
            Err(e) if e.is_fatal() => return Err(e.into()),
            // A bad message elsewhere in the capture does not stop an export.
            Err(_) => continue,
            Ok(TexelItem::Pair { pair, sensor }) => {
                if frames == index {
                    found = Some((pair, sensor));
                    if !want_pose {
                        break;
                    }
                }
                frames += 1;
            }
            Ok(TexelItem::Pose {
                topic,
                timestamp_ns,
                world_from_eo,
            }) => {
                poses.insert((timestamp_ns, topic == PoseTopic::Texel), world_from_eo);
            }
        }
        if let Some((pair, _)) = &found {
            let t = pair.timestamp_ns();
            if poses.contains_key(&(t, true)) {
                break;
            }
        }
    }
    let Some((pair, sensor)) = found else {
        return Err(ExportCommandError::NoSuchFrame {
            path,
            index,
            frames,
        });
    };
    let t = pair.timestamp_ns();
    let pose = poses
        .get(&(t, true))
        .or_else(|| poses.get(&(t, false)))
        .copied();
    Ok((pair, sensor, pose))
}

/// Fuses frame `index` of `capture` and writes it to `out`.
pub fn export_frame(
    capture: &Path,
    index: usize,
    format: ExportFormat,
    world: bool,
    out: &Path,
) -> Result<ExportSummary, ExportCommandError> {
    let (pair, sensor_model, pose) = read_frame(capture, index, world)?;
    let timestamp_ns = pair.timestamp_ns();
    let world_from_scan = match (world, pose) {
        (false, _) => None,
        (true, Some(p)) => Some(p),
        (true, None) => {
            return Err(ExportCommandError::NoPose {
                path: capture.display().to_string(),
                index,
                timestamp_ns,
            });
        }
    };
    let sensor = Sensor::new((*sensor_model).clone());
    let scan: TexelScan = fuse(&pair.range, pair.eo, &sensor, &FuseConfig::default())
        .map_err(|source| ExportCommandError::Fuse { index, source })?;
    let scans = [ExportScan {
        scan: &scan,
        world_from_scan,
    }];
    match format {
        ExportFormat::Ply => write_ply(&scans, out)?,
        ExportFormat::Gltf => write_gltf(&scans, out)?,
    }
    Ok(ExportSummary {
        timestamp_ns,
        vertices: scan.vertex_count(),
        usable_triangles: scan.usable_triangle_count(),
        world_from_scan,
    })
}
