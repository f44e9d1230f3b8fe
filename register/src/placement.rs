//! The registration stage's interface: a fused scan goes in; out come the scan's fate
//! (placed with an id, or refused with a reason) and every change to the model it
//! caused, in order: `ScanAdded` for it and for earlier failed scans a retry now
//! placed, `PoseRevised` for poses global refinement moved. The daemon's pipeline runs it
//! on its worker thread and knows nothing else about it; the viewer replays a capture
//! through it in-process.
//!
//! Two modes: [`RegistrarStage`] (`registration = "register"`) registers each scan
//! against the model so far (this crate); [`CapturePoses`]
//! (`registration = "capture-poses"`) places each scan at its capture's `/texel/pose`
//! (else `/truth/pose`) at the scan's timestamp.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use texel::capture::{
    CaptureError, CaptureEvent, CaptureReader, PoseTopic, RegisteredPoses, topics,
};
use texel::coverage::Shelf;
use texel::model::{ModelEvent, ScanId};
use texel::paged::PageStore;
use texel::{Pose, SensorModel, TexelScan};

use crate::{Registrar, RegistrationConfig, RegistrationStatus, ScanAnchor};

/// What the stage is given with a scan.
#[derive(Debug, Clone, Copy)]
pub struct ScanInput<'a> {
    /// The texel frame's timestamp (its range frame's).
    pub timestamp_ns: u64,
    /// The sensor (lidar and EO camera models) the scan was taken with.
    pub sensor: &'a SensorModel,
    /// The true pose at this timestamp when a simulator or capture knows it; only
    /// ever used to anchor the world frame at the first scan.
    pub truth: Option<Pose>,
}

/// Why a scan could not be placed; it stays recorded but does not join the model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlacementFailure {
    /// Short, stable, for logs: `no-pose`, `too-little-overlap`, `diverged`, ...
    pub kind: &'static str,
    pub reason: String,
}

/// The fate of the scan given to [`Registration::register`].
#[derive(Debug, Clone, PartialEq)]
pub enum Placement {
    /// It joined the model as scan `id`; `degenerate`: the solution was constrained
    /// in too few directions (kept at the prediction there) but accepted.
    Placed { id: ScanId, degenerate: bool },
    /// It did not (it may still join later, after a retry: a `ScanAdded` of a later
    /// call then carries it).
    Failed(PlacementFailure),
}

/// What one call changed.
#[derive(Debug, Clone)]
pub struct StageOutput {
    pub placement: Placement,
    /// Every change to the model, in order; ids count up from 0 without gaps.
    pub events: Vec<ModelEvent>,
    /// Earlier failed scans this call placed (their `ScanAdded` are in `events`).
    pub recovered: u32,
    /// How the scans this call placed or re-hung hang from their keyframes (empty
    /// for a stage without a pose graph): a scan's revisions follow from its
    /// keyframe's, so a recording need only record those of keyframes.
    pub anchors: Vec<ScanAnchor>,
}

/// A registration stage. Synchronous: the pipeline calls it from its worker thread.
pub trait Registration: Send {
    /// The mode's name for status and logs.
    fn name(&self) -> &str;

    /// Places one scan.
    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput;

    /// Takes a scan an earlier run placed as scan `id` at `world_from_scan` (a resumed
    /// session), without placing it again: later scans get later ids and register
    /// against it as if this run had placed it. Emits no events. The default keeps
    /// nothing: right only for stages that give no ids of their own.
    fn restore(
        &mut self,
        scan: &Arc<TexelScan>,
        input: ScanInput<'_>,
        id: ScanId,
        world_from_scan: Pose,
    ) {
        let _ = (scan, input, id, world_from_scan);
    }
}

/// Registration proper: a [`Registrar`] behind the stage interface. The world frame
/// is the first scan's true pose when one is known (a simulator's, or a capture's
/// `/truth/pose` at that timestamp), else [`crate::default_anchor`], as in
/// `texeld register`.
pub struct RegistrarStage {
    config: RegistrationConfig,
    registrar: Option<Registrar>,
    /// True poses by timestamp known before the session (a replayed capture's),
    /// consulted for the anchor only.
    truth: HashMap<u64, Pose>,
    /// Where the registrar's scan records go beyond a few pages, if anywhere.
    record_pages: Option<Box<dyn PageStore>>,
    /// Where the registrar's keyframe member lists wait, if anywhere.
    member_shelf: Option<Box<dyn Shelf>>,
}

impl RegistrarStage {
    pub fn new(config: RegistrationConfig) -> Self {
        Self {
            config,
            registrar: None,
            truth: HashMap::new(),
            record_pages: None,
            member_shelf: None,
        }
    }

    /// Keeps the registrar's per-scan records in `store` beyond a few pages
    /// ([`Registrar::page_scan_records`]).
    pub fn with_record_pages(mut self, store: Box<dyn PageStore>) -> Self {
        self.record_pages = Some(store);
        self
    }

    /// Keeps the registrar's keyframe member lists in `shelf`
    /// ([`Registrar::shelve_members`]).
    pub fn with_member_shelf(mut self, shelf: Box<dyn Shelf>) -> Self {
        self.member_shelf = Some(shelf);
        self
    }

    fn make_registrar(&mut self, anchor: Pose) -> Registrar {
        let mut registrar = Registrar::with_anchor(self.config.clone(), anchor);
        if let Some(store) = self.record_pages.take() {
            registrar.page_scan_records(store);
        }
        if let Some(shelf) = self.member_shelf.take() {
            registrar.shelve_members(shelf);
        }
        registrar
    }

    /// Knows the true poses a capture carries, to anchor the world where the capture's
    /// truth has it (a replay sends its truth after the frame it belongs to).
    pub fn with_truth(mut self, truth: HashMap<u64, Pose>) -> Self {
        self.truth = truth;
        self
    }

    /// The registrar, once the first scan has arrived.
    pub fn registrar(&self) -> Option<&Registrar> {
        self.registrar.as_ref()
    }
}

impl Registration for RegistrarStage {
    fn name(&self) -> &str {
        "register"
    }

    fn restore(
        &mut self,
        scan: &Arc<TexelScan>,
        input: ScanInput<'_>,
        id: ScanId,
        world_from_scan: Pose,
    ) {
        if self.registrar.is_none() {
            self.registrar = Some(self.make_registrar(world_from_scan));
        }
        if let Some(r) = self.registrar.as_mut() {
            r.restore(Arc::clone(scan), input.sensor, id, world_from_scan);
        }
    }

    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput {
        let registrar = match &mut self.registrar {
            Some(r) => r,
            None => {
                let anchor = input
                    .truth
                    .or_else(|| self.truth.get(&input.timestamp_ns).copied())
                    .unwrap_or_else(crate::default_anchor);
                self.truth = HashMap::new();
                let registrar = self.make_registrar(anchor);
                self.registrar.insert(registrar)
            }
        };
        let result = registrar.register(Arc::clone(scan), input.sensor);
        let recovered = registrar.take_recovered().len() as u32;
        let events = registrar.take_events();
        let anchors = registrar.take_anchors();
        let placement = match (&result.status, result.scan_id) {
            (RegistrationStatus::Failed { reason }, _) => Placement::Failed(PlacementFailure {
                kind: failure_kind(reason),
                reason: reason.to_string(),
            }),
            (_, Some(id)) => Placement::Placed {
                id,
                degenerate: !result.degenerate.is_empty(),
            },
            (_, None) => Placement::Failed(PlacementFailure {
                kind: "no-id",
                reason: "the registrar gave the scan no id".into(),
            }),
        };
        StageOutput {
            placement,
            events,
            recovered,
            anchors,
        }
    }
}

fn failure_kind(reason: &crate::FailureReason) -> &'static str {
    use crate::FailureReason as F;
    match reason {
        F::NoPoints { .. } => "no-points",
        F::TooLittleOverlap { .. } => "too-little-overlap",
        F::Diverged { .. } => "diverged",
        F::NonFinite => "non-finite",
        F::PoorFit { .. } => "poor-fit",
        F::NoTargets => "no-targets",
    }
}

/// Places scans at the poses a capture carries.
#[derive(Debug, Clone, Default)]
pub struct CapturePoses {
    texel: RegisteredPoses,
    truth: HashMap<u64, Pose>,
    next_id: ScanId,
}

/// The stage a replay of a capture uses when the session does not choose one (the
/// daemon's `registration = "auto"`): the capture's own `/texel/pose` when it carries
/// them, else registration anchored at the capture's `/truth/pose`.
pub fn replay_stage(poses: CapturePoses, config: &RegistrationConfig) -> Box<dyn Registration> {
    if poses.texel_count() > 0 {
        Box::new(poses)
    } else {
        Box::new(RegistrarStage::new(config.clone()).with_truth(poses.into_truth()))
    }
}

impl CapturePoses {
    /// Reads every pose of a capture (only the pose topics are decoded). A capture
    /// damaged part-way keeps the poses before the damage.
    pub fn from_capture(path: &Path) -> Result<Self, CaptureError> {
        let mut reader = CaptureReader::open(path)?;
        let mut poses = Self::default();
        let wanted = [
            PoseTopic::Texel.topic(),
            PoseTopic::Truth.topic(),
            topics::TEXEL_ANCHOR,
        ];
        reader.for_each_event(&wanted, |event| match event {
            CaptureEvent::Pose {
                topic,
                timestamp_ns,
                world_from_eo,
            } => poses.insert(topic, timestamp_ns, world_from_eo),
            CaptureEvent::Anchor(anchor) => poses.texel.insert_anchor(anchor),
            _ => {}
        });
        Ok(poses)
    }

    /// Adds a pose; a later `/texel/pose` at the same timestamp is a revision and wins.
    pub fn insert(&mut self, topic: PoseTopic, timestamp_ns: u64, world_from_eo: Pose) {
        match topic {
            PoseTopic::Texel => self.texel.insert_pose(timestamp_ns, world_from_eo),
            PoseTopic::Truth => {
                self.truth.insert(timestamp_ns, world_from_eo);
            }
        }
    }

    pub fn len(&self) -> usize {
        self.texel.len().max(self.truth.len())
    }

    pub fn is_empty(&self) -> bool {
        self.texel.is_empty() && self.truth.is_empty()
    }

    /// Timestamps with a `/texel/pose` (a registered capture).
    pub fn texel_count(&self) -> usize {
        self.texel.len()
    }

    /// The `/truth/pose` table alone.
    pub fn into_truth(self) -> HashMap<u64, Pose> {
        self.truth
    }

    /// The pose at a timestamp: `/texel/pose` (the last one), else `/truth/pose`.
    pub fn pose_at(&self, t: u64) -> Option<Pose> {
        self.lookup(t)
    }

    /// The registered pose at a timestamp (`/texel/pose` and `/texel/anchor`).
    pub fn texel_pose(&self, t: u64) -> Option<Pose> {
        self.texel.get(t)
    }

    /// The `/truth/pose` table alone.
    pub fn truth_poses(&self) -> &HashMap<u64, Pose> {
        &self.truth
    }

    fn lookup(&self, t: u64) -> Option<Pose> {
        self.texel.get(t).or_else(|| self.truth.get(&t).copied())
    }
}

impl Registration for CapturePoses {
    fn name(&self) -> &str {
        "capture-poses"
    }

    fn restore(&mut self, _: &Arc<TexelScan>, _: ScanInput<'_>, id: ScanId, _: Pose) {
        self.next_id = self.next_id.max(id.saturating_add(1));
    }

    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput {
        // The scan frame is the EO frame, so the capture's world_from_eo is the scan's
        // pose. A live pair may carry the EO timestamp instead of the lidar's.
        let timestamp_ns = input.timestamp_ns;
        let pose = self
            .lookup(timestamp_ns)
            .or_else(|| self.lookup(scan.texture.timestamp_ns));
        match pose {
            Some(world_from_scan) => {
                let id = self.next_id;
                self.next_id += 1;
                StageOutput {
                    placement: Placement::Placed {
                        id,
                        degenerate: false,
                    },
                    events: vec![ModelEvent::ScanAdded {
                        id,
                        scan: Arc::clone(scan),
                        world_from_scan,
                    }],
                    recovered: 0,
                    anchors: Vec::new(),
                }
            }
            None => StageOutput {
                placement: Placement::Failed(PlacementFailure {
                    kind: "no-pose",
                    reason: format!(
                        "no /texel/pose or /truth/pose at {timestamp_ns} ns in the pose capture"
                    ),
                }),
                events: Vec::new(),
                recovered: 0,
                anchors: Vec::new(),
            },
        }
    }
}
