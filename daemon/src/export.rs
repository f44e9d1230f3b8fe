//! `texeld export`: one texel frame of a capture, fused and written as PLY or glTF, in
//! its own EO frame or placed in the world by the capture's `/texel/pose` (else
//! `/truth/pose`); or the whole registered model: every frame placed by its
//! `/texel/pose` (the last one of its timestamp: revisions come later), or, when the
//! capture has none, registered on the fly. See `model_export.rs`.

use std::path::Path;
use std::sync::Arc;

use texel::capture::{CaptureError, SensorCache, TexelItem, open_texel_frames};

use crate::pipeline::placement::CapturePoses;
use texel::export::{ExportError, ExportScan, write_gltf, write_ply};
use texel::fuse::FuseError;
use texel::{FuseConfig, Pose, SensorModel, TexelScan};
use thiserror::Error;

/// Output formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExportFormat {
    Ply,
    Gltf,
    /// An OGC 3D Tiles 1.1 tileset of the level-of-detail hierarchy (a folder).
    #[value(name = "3dtiles")]
    Tiles3d,
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
    #[error("{path}: none of its {frames} texel frames has a pose (none registered)")]
    NothingToExport { path: String, frames: usize },
    #[error("frame {index}: {source}")]
    Fuse { index: usize, source: FuseError },
    #[error(transparent)]
    Export(#[from] ExportError),
    #[error("--format 3dtiles exports the whole model as a tileset folder; drop --frame")]
    WholeModelOnly,
    #[error("level of detail: {0}")]
    Lod(#[from] texel_lod::LodError),
    #[error("3D Tiles: {0}")]
    Tiles(#[from] texel_lod::TilesError),
    #[error("{}: {source}", path.display())]
    Io {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
}

/// What was exported.
#[derive(Debug)]
pub struct ExportSummary {
    pub timestamp_ns: u64,
    pub vertices: usize,
    pub usable_triangles: usize,
    pub world_from_scan: Option<Pose>,
}

/// Reads frame `index` (0-based, in file order) and its pose: the last `/texel/pose`
/// of its timestamp (a revision supersedes the first), else its `/truth/pose`.
fn read_frame(
    capture: &Path,
    index: usize,
    want_pose: bool,
) -> Result<(texel::FramePair, Arc<SensorModel>, Option<Pose>), ExportCommandError> {
    let path = capture.display().to_string();
    let mut found = None;
    let mut frames = 0;
    for item in open_texel_frames(capture)? {
        match item {
            Err(e) if e.is_fatal() => return Err(e.into()),
            // A bad message elsewhere in the capture does not stop an export.
            Err(_) => continue,
            Ok(TexelItem::Pair { pair, sensor }) => {
                if frames == index {
                    found = Some((pair, sensor));
                    break;
                }
                frames += 1;
            }
            Ok(TexelItem::Pose { .. } | TexelItem::Anchor(_)) => {}
        }
    }
    let Some((pair, sensor)) = found else {
        return Err(ExportCommandError::NoSuchFrame {
            path,
            index,
            frames,
        });
    };
    let pose = if want_pose {
        let poses = CapturePoses::from_capture(capture)?;
        poses.pose_at(pair.timestamp_ns())
    } else {
        None
    };
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
    if format == ExportFormat::Tiles3d {
        return Err(ExportCommandError::WholeModelOnly);
    }
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
    let scan: TexelScan = SensorCache::new()
        .fuse(pair, &sensor_model, &FuseConfig::default())
        .map_err(|source| ExportCommandError::Fuse { index, source })?;
    let scans = [ExportScan {
        scan: &scan,
        world_from_scan,
    }];
    match format {
        ExportFormat::Ply => write_ply(&scans, out)?,
        ExportFormat::Gltf => write_gltf(&scans, out)?,
        ExportFormat::Tiles3d => return Err(ExportCommandError::WholeModelOnly),
    }
    Ok(ExportSummary {
        timestamp_ns,
        vertices: scan.vertex_count(),
        usable_triangles: scan.usable_triangle_count(),
        world_from_scan,
    })
}
