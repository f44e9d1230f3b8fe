//! The registration stage's interface: a fused scan goes in, a pose (or a failure with
//! its reason) comes out, and later pose revisions of earlier scans may follow. The
//! pipeline runs it on a blocking thread and knows nothing else about it.
//!
//! [`CapturePoses`] is the mode for replaying captures that already carry poses
//! (`registration = "capture-poses"`): each scan is placed at its capture's
//! `/texel/pose` (else `/truth/pose`) at the scan's timestamp.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use texel::capture::{CaptureError, CaptureEvent, CaptureReader, PoseTopic};
use texel::model::ScanId;
use texel::{Pose, TexelScan};

/// A registered scan's pose, and whether the solution was degenerate (constrained in
/// too few directions) though accepted.
#[derive(Debug, Clone, PartialEq)]
pub struct Placement {
    pub world_from_scan: Pose,
    pub degenerate: bool,
    /// Revisions of earlier scans found while placing this one.
    pub revisions: Vec<PoseRevision>,
}

/// A better pose for a scan already in the model.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseRevision {
    pub id: ScanId,
    pub world_from_scan: Pose,
}

/// Why a scan could not be placed; it stays recorded but does not join the model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlacementFailure {
    /// Short, stable, for counters: `no-pose`, `no-overlap`, `degenerate`, ...
    pub kind: &'static str,
    pub reason: String,
}

/// A registration stage. Synchronous: the pipeline calls it from its own thread.
pub trait Registration: Send {
    /// The mode's name for status and logs.
    fn name(&self) -> &str;

    /// Places scan `id` (the id it gets in the model if placed; ids of failed scans
    /// are reused) taken at `timestamp_ns`.
    fn register(
        &mut self,
        id: ScanId,
        scan: &Arc<TexelScan>,
        timestamp_ns: u64,
    ) -> Result<Placement, PlacementFailure>;

    /// Revisions found in the background since the last call (global refinement);
    /// polled by the pipeline after every scan and when idle.
    fn take_revisions(&mut self) -> Vec<PoseRevision> {
        Vec::new()
    }
}

/// Places scans at the poses a capture carries.
#[derive(Debug, Clone, Default)]
pub struct CapturePoses {
    texel: HashMap<u64, Pose>,
    truth: HashMap<u64, Pose>,
}

impl CapturePoses {
    /// Reads every pose of a capture (only the pose topics are decoded). A capture
    /// damaged part-way keeps the poses before the damage.
    pub fn from_capture(path: &Path) -> Result<Self, CaptureError> {
        let mut reader = CaptureReader::open(path)?;
        let mut poses = Self::default();
        while let Some(next) = reader.next_message() {
            let Ok(message) = next else {
                break;
            };
            let topic = message.channel.topic.as_str();
            if topic != PoseTopic::Texel.topic() && topic != PoseTopic::Truth.topic() {
                continue;
            }
            if let Ok(CaptureEvent::Pose {
                topic,
                timestamp_ns,
                world_from_eo,
            }) = reader.decode(&message)
            {
                poses.insert(topic, timestamp_ns, world_from_eo);
            }
        }
        Ok(poses)
    }

    /// Adds a pose; a later `/texel/pose` at the same timestamp is a revision and wins.
    pub fn insert(&mut self, topic: PoseTopic, timestamp_ns: u64, world_from_eo: Pose) {
        match topic {
            PoseTopic::Texel => self.texel.insert(timestamp_ns, world_from_eo),
            PoseTopic::Truth => self.truth.insert(timestamp_ns, world_from_eo),
        };
    }

    pub fn len(&self) -> usize {
        self.texel.len().max(self.truth.len())
    }

    pub fn is_empty(&self) -> bool {
        self.texel.is_empty() && self.truth.is_empty()
    }

    fn lookup(&self, t: u64) -> Option<Pose> {
        self.texel.get(&t).or_else(|| self.truth.get(&t)).copied()
    }
}

impl Registration for CapturePoses {
    fn name(&self) -> &str {
        "capture-poses"
    }

    fn register(
        &mut self,
        _id: ScanId,
        scan: &Arc<TexelScan>,
        timestamp_ns: u64,
    ) -> Result<Placement, PlacementFailure> {
        // The scan frame is the EO frame, so the capture's world_from_eo is the scan's
        // pose. A live pair may carry the EO timestamp instead of the lidar's.
        let pose = self
            .lookup(timestamp_ns)
            .or_else(|| self.lookup(scan.texture.timestamp_ns));
        match pose {
            Some(world_from_scan) => Ok(Placement {
                world_from_scan,
                degenerate: false,
                revisions: Vec::new(),
            }),
            None => Err(PlacementFailure {
                kind: "no-pose",
                reason: format!(
                    "no /texel/pose or /truth/pose at {timestamp_ns} ns in the pose capture"
                ),
            }),
        }
    }
}
