//! Loading a capture into a texel model: every texel frame is fused with
//! `texel::fuse` and placed by its `/texel/pose` (registered) or, when the capture has
//! none, its `/truth/pose`. Damage to the file keeps everything read before it.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use texel::capture::{
    CaptureError, PoseTopic, RegisteredPoses, SensorCache, TexelItem, open_texel_frames,
};
use texel::model::{Model, ModelEvent};
use texel::{FuseConfig, PinholeCamera, Pose, TexelScan};

/// A pose is matched to a frame whose timestamp is within this of it.
pub const POSE_TOLERANCE_NS: u64 = 20_000_000;

/// Which pose topic placed the scans.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseSource {
    Registered,
    Truth,
}

impl PoseSource {
    pub fn topic(self) -> &'static str {
        match self {
            PoseSource::Registered => texel::capture::topics::TEXEL_POSE,
            PoseSource::Truth => texel::capture::topics::TRUTH_POSE,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error("{path}: no texel frames (range + EO pairs) in the capture")]
    NoFrames { path: String },
    #[error("{path}: {frames} texel frames but no /texel/pose or /truth/pose to place them")]
    NoPoses { path: String, frames: usize },
}

/// A capture's model and what was learned loading it.
#[derive(Debug, Clone)]
pub struct LoadedCapture {
    pub model: Model,
    pub pose_source: PoseSource,
    /// The EO camera of the first frame (the default virtual camera).
    pub eo_camera: PinholeCamera,
    /// The EO camera's response curve, where the capture's sensor model has one (what
    /// turns the frames that record their exposure into radiance).
    pub eo_response: Option<texel::radiance::EoResponse>,
    /// Frames fused but not placed (no pose within the tolerance).
    pub unplaced: usize,
    /// Problems met on the way (damaged messages, a truncated file, fusion errors).
    pub warnings: Vec<String>,
}

/// Reads, fuses and places every texel frame of a capture.
pub fn load_capture(path: &Path) -> Result<LoadedCapture, LoadError> {
    let display = path.display().to_string();
    let reader = open_texel_frames(path)?;
    let mut sensors = SensorCache::new();
    let mut scans: Vec<TexelScan> = Vec::new();
    let mut eo_camera = None;
    let mut eo_response = None;
    let mut registered = RegisteredPoses::default();
    let mut truth: BTreeMap<u64, Pose> = BTreeMap::new();
    let mut warnings = Vec::new();
    let config = FuseConfig::default();
    for item in reader {
        match item {
            Ok(TexelItem::Pair { pair, sensor }) => {
                eo_camera.get_or_insert_with(|| sensor.eo.clone());
                if eo_response.is_none() {
                    eo_response = sensor.eo_response.clone();
                }
                let timestamp_ns = pair.range.timestamp_ns;
                match sensors.fuse(pair, &sensor, &config) {
                    Ok(scan) => scans.push(scan),
                    Err(e) => warnings.push(format!(
                        "{display}: frame at {timestamp_ns} ns not fused: {e}"
                    )),
                }
            }
            Ok(TexelItem::Pose {
                topic,
                timestamp_ns,
                world_from_eo,
            }) => match topic {
                PoseTopic::Texel => registered.insert_pose(timestamp_ns, world_from_eo),
                PoseTopic::Truth => {
                    truth.insert(timestamp_ns, world_from_eo);
                }
            },
            Ok(TexelItem::Anchor(anchor)) => registered.insert_anchor(anchor),
            // A damaged message or file: keep what was read, say what happened.
            Err(e) => warnings.push(e.to_string()),
        }
    }
    let Some(eo_camera) = eo_camera else {
        return Err(LoadError::NoFrames { path: display });
    };
    let (pose_source, table) = if !registered.is_empty() {
        (PoseSource::Registered, registered.iter().collect())
    } else if !truth.is_empty() {
        (PoseSource::Truth, truth)
    } else {
        {
            return Err(LoadError::NoPoses {
                path: display,
                frames: scans.len(),
            });
        }
    };
    let mut model = Model::new();
    let mut unplaced = 0;
    for scan in scans {
        match pose_at(&table, scan.timestamp_ns)
            .or_else(|| pose_at(&table, scan.texture.timestamp_ns))
        {
            Some(world_from_scan) => {
                // Ids are assigned in order, so this cannot be out of order.
                let _ = model.apply(ModelEvent::ScanAdded {
                    id: model.next_id(),
                    scan: Arc::new(scan),
                    world_from_scan,
                });
            }
            None => unplaced += 1,
        }
    }
    Ok(LoadedCapture {
        model,
        pose_source,
        eo_camera,
        eo_response,
        unplaced,
        warnings,
    })
}

/// The pose nearest in time to `t`, if within [`POSE_TOLERANCE_NS`].
fn pose_at(table: &BTreeMap<u64, Pose>, t: u64) -> Option<Pose> {
    let before = table.range(..=t).next_back();
    let after = table.range(t..).next();
    [before, after]
        .into_iter()
        .flatten()
        .map(|(&ts, pose)| (ts.abs_diff(t), *pose))
        .filter(|(d, _)| *d <= POSE_TOLERANCE_NS)
        .min_by_key(|(d, _)| *d)
        .map(|(_, p)| p)
}
