//! `texeld export CAPTURE --format gltf|ply --out PATH` without `--frame`: the whole
//! registered model in the world frame. Every texel frame is fused and placed by its
//! `/texel/pose` (the last one of its timestamp, so revisions win); frames without
//! one were not registered and are left out. A capture with no `/texel/pose` at all is
//! registered on the fly (as `texeld register` does: the world anchored at the first
//! frame's `/truth/pose` when there is one), and its final poses are used.

use std::path::Path;
use std::sync::Arc;

use texel::capture::{SensorCache, TexelItem, open_texel_frames};
use texel::export::{ExportScan, write_gltf, write_ply};
use texel::model::ModelEvent;
use texel::{FuseConfig, Pose, TexelScan};

use crate::export::{ExportCommandError, ExportFormat};
use crate::pipeline::placement::CapturePoses;
use texel_register::{Registrar, RegistrationConfig};

/// Where the poses of an exported model came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseSource {
    /// The capture's `/texel/pose`.
    Capture,
    /// Registered during the export.
    Registered,
    /// The capture's `/truth/pose` (a simulated capture's ground truth).
    Truth,
}

/// Which poses place the scans of an export.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum PoseChoice {
    /// `/texel/pose`, or registered now when the capture has none.
    #[default]
    Texel,
    /// `/truth/pose`: the simulator's ground truth, to look at a model apart from
    /// registration.
    Truth,
}

/// What was exported.
#[derive(Debug)]
pub struct ModelExportSummary {
    pub frames: usize,
    pub scans: usize,
    pub vertices: usize,
    pub usable_triangles: usize,
    pub poses: PoseSource,
    /// Frames left out (no pose: registration failed, or fusion refused them).
    pub left_out: usize,
}

/// How the placed scans of a capture were found.
#[derive(Debug, Clone, Copy)]
pub struct Placement {
    pub frames: usize,
    pub scans: usize,
    pub poses: PoseSource,
}

/// Calls `visit` with every scan of `capture` placed in the world. With `/texel/pose`
/// in the capture the scans stream through one at a time; without, the capture is
/// registered first and the scans are visited with their final poses.
pub fn for_each_placed(
    capture: &Path,
    registration: &RegistrationConfig,
    visit: &mut dyn FnMut(&Arc<TexelScan>, &Pose),
) -> Result<Placement, ExportCommandError> {
    for_each_placed_by(capture, registration, PoseChoice::Texel, visit)
}

/// [`for_each_placed`] with the poses chosen: with [`PoseChoice::Truth`] every frame
/// with a `/truth/pose` streams through placed by it.
pub fn for_each_placed_by(
    capture: &Path,
    registration: &RegistrationConfig,
    choice: PoseChoice,
    visit: &mut dyn FnMut(&Arc<TexelScan>, &Pose),
) -> Result<Placement, ExportCommandError> {
    let poses = CapturePoses::from_capture(capture)?;
    let source = match choice {
        PoseChoice::Truth => PoseSource::Truth,
        PoseChoice::Texel if poses.texel_count() > 0 => PoseSource::Capture,
        PoseChoice::Texel => PoseSource::Registered,
    };
    // The pose a frame is placed by, unless the capture is registered now.
    let given = |timestamp_ns: u64| match source {
        PoseSource::Truth => poses.truth_poses().get(&timestamp_ns).copied(),
        PoseSource::Capture => poses.texel_pose(timestamp_ns),
        PoseSource::Registered => None,
    };
    let mut sensors = SensorCache::new();
    let mut registrar: Option<Registrar> = None;
    let mut scans_by_id: Vec<Arc<TexelScan>> = Vec::new();
    let mut frames = 0usize;
    let mut placed = 0usize;
    let fuse_config = FuseConfig::default();
    for item in open_texel_frames(capture)? {
        let (pair, model) = match item {
            Err(e) if e.is_fatal() => return Err(e.into()),
            Ok(TexelItem::Pair { pair, sensor }) => (pair, sensor),
            _ => continue,
        };
        let index = frames;
        frames += 1;
        let timestamp_ns = pair.timestamp_ns();
        let pose = given(timestamp_ns);
        if source != PoseSource::Registered && pose.is_none() {
            continue;
        }
        let scan = match sensors.fuse(pair, &model, &fuse_config) {
            Ok(scan) => Arc::new(scan),
            Err(e) => {
                tracing::warn!("frame {index} not fused: {e}");
                continue;
            }
        };
        if let Some(pose) = pose {
            visit(&scan, &pose);
            placed += 1;
            continue;
        }
        let registrar = registrar.get_or_insert_with(|| {
            let anchor = poses
                .truth_poses()
                .get(&timestamp_ns)
                .copied()
                .unwrap_or_else(texel_register::default_anchor);
            Registrar::with_anchor(registration.clone(), anchor)
        });
        registrar.register(scan, &model);
        // A whole-capture export records no anchors.
        registrar.take_anchors();
        for event in registrar.take_events() {
            if let ModelEvent::ScanAdded { scan, .. } = event {
                scans_by_id.push(scan);
            }
        }
        registrar.take_recovered();
    }
    if let Some(registrar) = &registrar {
        // Final poses, after every refinement.
        for (scan, pose) in scans_by_id.iter().zip(registrar.poses().iter()) {
            visit(scan, pose);
            placed += 1;
        }
    }
    if placed == 0 {
        return Err(ExportCommandError::NothingToExport {
            path: capture.display().to_string(),
            frames,
        });
    }
    Ok(Placement {
        frames,
        scans: placed,
        poses: source,
    })
}

/// Exports the registered model of `capture` to `out` as PLY or glTF (3D Tiles goes
/// through `tiles_export`).
pub fn export_model(
    capture: &Path,
    format: ExportFormat,
    out: &Path,
    registration: &RegistrationConfig,
    poses: PoseChoice,
) -> Result<ModelExportSummary, ExportCommandError> {
    let mut placed: Vec<(Arc<TexelScan>, Pose)> = Vec::new();
    let placement = for_each_placed_by(capture, registration, poses, &mut |scan, pose| {
        placed.push((Arc::clone(scan), *pose));
    })?;
    let scans: Vec<ExportScan<'_>> = placed
        .iter()
        .map(|(scan, pose)| ExportScan {
            scan,
            world_from_scan: Some(*pose),
        })
        .collect();
    match format {
        ExportFormat::Ply => write_ply(&scans, out)?,
        ExportFormat::Gltf => write_gltf(&scans, out)?,
        ExportFormat::Tiles3d => return Err(ExportCommandError::WholeModelOnly),
    }
    Ok(ModelExportSummary {
        frames: placement.frames,
        scans: placed.len(),
        vertices: placed.iter().map(|(s, _)| s.vertex_count()).sum(),
        usable_triangles: placed.iter().map(|(s, _)| s.usable_triangle_count()).sum(),
        poses: placement.poses,
        left_out: placement.frames - placed.len(),
    })
}
