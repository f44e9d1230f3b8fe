//! The registrar: registers each new scan against the model-side keyframe window,
//! keeps the motion model, the pose graph over keyframes (every other scan hangs from
//! a keyframe, its world pose derived from the keyframe's) and the failed scans
//! waiting for a retry, and reports what changes in the model as [`ModelEvent`]s.

mod restore;
mod revisit;

use std::collections::VecDeque;
use std::sync::Arc;

use nalgebra::Matrix6;
use texel::coverage::Shelf;
use texel::coverage::links::Dependents;
use texel::model::{ModelEvent, ScanId};
use texel::paged::PageStore;
use texel::pose::pose_difference;
use texel::{PinholeCamera, Pose, SensorModel, TexelScan};

use super::align::{AlignTarget, align};
use super::config::RegistrationConfig;
use super::graph::{Edge, PoseGraph};
use super::motion::MotionModel;
use super::pyramid::{PyramidOptions, ScanPyramid};
use super::result::{Alignment, FailureReason, Fitness, RegistrationResult, RegistrationStatus};
use super::scan_table::{CompactPose, RevisionThresholds, ScanRecord, ScanTable};

/// Fewest correspondences with one keyframe for the pair to become a graph edge.
const MIN_EDGE_CORRESPONDENCES: usize = 12;

/// Pages of per-scan records (1,024 scans, 96 bytes each, a page) a paged registrar
/// keeps in memory: the newest scans, where registration and most revisions are.
pub const RESIDENT_RECORD_PAGES: usize = 8;

/// A keyframe: a graph node (its ordinal is the node's index).
struct Keyframe {
    /// The id of the scan that is the keyframe.
    scan: u32,
    /// Built once when the scan arrived and kept for the window, loop closure and
    /// re-localisation; dropped when the keyframe has not been used for longest and
    /// more than `keyframes.max_resident` are held.
    pyramid: Option<Arc<ScanPyramid>>,
    /// The registration tick at which the window or loop closure last used it.
    last_used: u64,
    /// Ids of the scans that hang from it (their poses move with it): with a member
    /// shelf ([`Registrar::shelve_members`]) only the changes since the list was
    /// written to it, so that a keyframe revisited all session long holds a bounded
    /// share of its members in memory.
    members: Dependents,
}

/// A scan that failed, waiting for a later keyframe to register against.
struct Pending {
    scan: Arc<TexelScan>,
    pyramid: Arc<ScanPyramid>,
    retries: u32,
}

/// How a scan hangs in the pose graph: from the keyframe that is scan `keyframe`
/// (itself, for a keyframe), at `keyframe_from_scan`; its world pose is the
/// keyframe's times that, `world_from_scan` now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanAnchor {
    pub id: ScanId,
    pub keyframe: ScanId,
    pub keyframe_from_scan: Pose,
    pub world_from_scan: Pose,
}

/// Counters of what the registrar has done.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RegistrarStats {
    pub registered: u64,
    pub failed: u64,
    pub recovered: u64,
    pub given_up: u64,
    pub keyframes: u64,
    pub loop_closures: u64,
    pub loop_candidates_rejected: u64,
    pub graph_optimisations: u64,
    /// Scans that would have become keyframes and were attached to an existing
    /// keyframe of mapped ground instead.
    pub relocalisations: u64,
    /// Keyframe pyramids dropped to stay within `keyframes.max_resident`.
    pub pyramids_dropped: u64,
}

/// What the registrar holds, in heap bytes (capacity included).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RegistrarMemory {
    pub scans: usize,
    /// The per-scan records and keyframe membership lists.
    pub scan_bytes: usize,
    pub keyframes: usize,
    /// Keyframe records, graph nodes and edges (pyramids apart).
    pub keyframe_bytes: usize,
    pub resident_pyramids: usize,
    /// The resident pyramids with their scans (mesh and EO texture).
    pub pyramid_bytes: usize,
}

/// Scan-to-model registration with global refinement.
pub struct Registrar {
    config: RegistrationConfig,
    anchor: Pose,
    scans: ScanTable,
    /// By ordinal, which is also the graph node index.
    keyframes: Vec<Keyframe>,
    /// Keyframe ordinals, oldest first; their pyramids are always resident.
    window: VecDeque<usize>,
    graph: PoseGraph,
    motion: MotionModel,
    pending: VecDeque<Pending>,
    events: Vec<ModelEvent>,
    /// Scans placed or re-hung since the last [`Registrar::take_anchors`].
    rehung: Vec<u32>,
    recovered: Vec<RegistrationResult>,
    stats: RegistrarStats,
    /// Keyframe ordinal of the last accepted loop closure.
    last_loop_keyframe: Option<usize>,
    /// The lidar and EO models of the last scan, shared by the scans that use the
    /// same ones.
    lidar: Option<Arc<PinholeCamera>>,
    eo: Option<Arc<PinholeCamera>>,
    /// Counts `register` calls: the clock of least-recently-used pyramid eviction.
    tick: u64,
    resident: usize,
    /// Where keyframes' member lists wait, if anywhere.
    member_shelf: Option<Box<dyn Shelf>>,
    /// Member lists that could not be written or read back.
    member_shelf_errors: u64,
    /// Changes a keyframe's member list holds in memory before it is written.
    member_flush_changes: usize,
}

impl Registrar {
    /// A registrar whose first scan defines the world frame.
    pub fn new(config: RegistrationConfig) -> Self {
        Self::with_anchor(config, Pose::identity())
    }

    /// A registrar that places its first scan at `world_from_first_scan`.
    pub fn with_anchor(config: RegistrationConfig, world_from_first_scan: Pose) -> Self {
        Self {
            config,
            anchor: world_from_first_scan,
            scans: ScanTable::default(),
            member_shelf: None,
            member_shelf_errors: 0,
            member_flush_changes: texel::coverage::links::FLUSH_CHANGES,
            keyframes: Vec::new(),
            window: VecDeque::new(),
            graph: PoseGraph::new(),
            motion: MotionModel::new(),
            pending: VecDeque::new(),
            events: Vec::new(),
            rehung: Vec::new(),
            recovered: Vec::new(),
            stats: RegistrarStats::default(),
            last_loop_keyframe: None,
            lidar: None,
            eo: None,
            tick: 0,
            resident: 0,
        }
    }

    pub fn config(&self) -> &RegistrationConfig {
        &self.config
    }

    /// Keeps at most [`RESIDENT_RECORD_PAGES`] pages of per-scan records in memory
    /// and the rest in `store`, so that the registrar's memory stops growing with
    /// the frames (all but a keyframe list entry, 4 bytes, per scan).
    pub fn page_scan_records(&mut self, store: Box<dyn PageStore>) {
        self.scans.page_to(store, RESIDENT_RECORD_PAGES);
    }

    /// Keeps the keyframes' member lists in `shelf`: memory holds each keyframe's
    /// changes since its list was last written (at most
    /// [`texel::coverage::links::FLUSH_CHANGES`]), so a scan costs memory no bytes
    /// of membership.
    pub fn shelve_members(&mut self, shelf: Box<dyn Shelf>) {
        self.shelve_members_with(shelf, texel::coverage::links::FLUSH_CHANGES);
    }

    /// [`Self::shelve_members`], writing a keyframe's list every `flush_changes`
    /// changes (tests write after a few).
    pub fn shelve_members_with(&mut self, shelf: Box<dyn Shelf>, flush_changes: usize) {
        self.member_shelf = Some(shelf);
        self.member_flush_changes = flush_changes.max(1);
    }

    /// Member lists that could not be written to or read back from the member shelf.
    pub fn member_shelf_errors(&self) -> u64 {
        self.member_shelf_errors
    }

    /// Scan `id` hangs from keyframe `keyframe`.
    pub(crate) fn add_member(&mut self, keyframe: usize, id: usize) {
        let Some(k) = self.keyframes.get_mut(keyframe) else {
            return;
        };
        k.members.insert(id as ScanId);
        if k.members.changes() >= self.member_flush_changes
            && let Some(shelf) = self.member_shelf.as_mut()
            && k.members.flush(keyframe as ScanId, shelf).is_err()
        {
            self.member_shelf_errors += 1;
        }
    }

    /// Scan `id` no longer hangs from keyframe `keyframe`.
    pub(crate) fn remove_member(&mut self, keyframe: usize, id: usize) {
        if let Some(k) = self.keyframes.get_mut(keyframe) {
            k.members.remove(id as ScanId);
        }
    }

    /// The scans that hang from keyframe `keyframe`, in id order.
    pub(crate) fn members_of(&mut self, keyframe: usize) -> Vec<ScanId> {
        let Some(k) = self.keyframes.get(keyframe) else {
            return Vec::new();
        };
        let (ids, error) = k
            .members
            .list(keyframe as ScanId, self.member_shelf.as_deref());
        if error.is_some() {
            self.member_shelf_errors += 1;
        }
        ids
    }

    /// [`Self::page_scan_records`] with other page sizes, for a registrar that has
    /// registered nothing yet (tests page a few dozen scans this way); a registrar
    /// that has keeps its page size.
    pub fn page_scan_records_with(
        &mut self,
        store: Box<dyn PageStore>,
        resident_pages: usize,
        records_per_page: usize,
    ) {
        if self.scans.is_empty() {
            self.scans = ScanTable::with_page_records(records_per_page);
        }
        self.scans.page_to(store, resident_pages);
    }

    /// The current pose of a registered scan: its keyframe's pose times its pose
    /// relative to the keyframe.
    pub fn pose(&self, id: ScanId) -> Option<Pose> {
        let record = usize::try_from(id).ok().and_then(|i| self.scans.get(i))?;
        self.derived_pose(&record)
    }

    /// Current poses of all registered scans, by id.
    pub fn poses(&self) -> Vec<Pose> {
        self.scans
            .to_vec()
            .iter()
            .map(|r| self.derived_pose(r).unwrap_or(r.keyframe_from_scan))
            .collect()
    }

    /// The number of registered scans.
    pub fn scan_count(&self) -> usize {
        self.scans.len()
    }

    /// Timestamp of a registered scan.
    pub fn timestamp_ns(&self, id: ScanId) -> Option<u64> {
        usize::try_from(id)
            .ok()
            .and_then(|i| self.scans.get(i))
            .map(|r| r.timestamp_ns)
    }

    pub fn stats(&self) -> RegistrarStats {
        self.stats
    }

    /// The pose graph: one node per keyframe, by keyframe ordinal.
    pub fn graph(&self) -> &PoseGraph {
        &self.graph
    }

    /// The keyframe ordinal (graph node) a registered scan hangs from.
    pub fn keyframe_of(&self, id: ScanId) -> Option<usize> {
        usize::try_from(id)
            .ok()
            .and_then(|i| self.scans.get(i))
            .map(|r| r.keyframe as usize)
    }

    /// What the registrar holds in memory.
    pub fn heap_bytes(&self) -> RegistrarMemory {
        use std::mem::size_of;
        let members: usize = self.keyframes.iter().map(|k| k.members.heap_bytes()).sum();
        let pyramid_bytes = self
            .keyframes
            .iter()
            .filter_map(|k| k.pyramid.as_ref())
            .map(|p| p.heap_bytes())
            .sum();
        RegistrarMemory {
            scans: self.scans.len(),
            scan_bytes: self.scans.heap_bytes() + members,
            keyframes: self.keyframes.len(),
            keyframe_bytes: self.keyframes.capacity() * size_of::<Keyframe>()
                + std::mem::size_of_val(self.graph.poses())
                + std::mem::size_of_val(self.graph.edges()),
            resident_pyramids: self.resident,
            pyramid_bytes,
        }
    }

    /// Model events since the last call, in order: `ScanAdded` for every scan that
    /// entered the model (new ones and recovered ones), `PoseRevised` for every scan
    /// whose derived pose global refinement moved beyond the revision thresholds from
    /// the pose last sent for it.
    pub fn take_events(&mut self) -> Vec<ModelEvent> {
        std::mem::take(&mut self.events)
    }

    /// The scans placed or re-hung from another keyframe since the last call (each
    /// once, as it hangs now), in id order: what a recording needs to derive every
    /// scan's pose from its keyframe's, so that a revision of a keyframe need not be
    /// followed by one for every scan hanging from it.
    pub fn take_anchors(&mut self) -> Vec<ScanAnchor> {
        let mut ids = std::mem::take(&mut self.rehung);
        ids.sort_unstable();
        ids.dedup();
        ids.into_iter()
            .filter_map(|id| {
                let record = self.scans.get(id as usize)?;
                let keyframe = self.keyframes.get(record.keyframe as usize)?;
                Some(ScanAnchor {
                    id: ScanId::from(id),
                    keyframe: ScanId::from(keyframe.scan),
                    keyframe_from_scan: record.keyframe_from_scan,
                    world_from_scan: self.derived_pose(&record)?,
                })
            })
            .collect()
    }

    /// Results of earlier failed scans that a later retry registered.
    pub fn take_recovered(&mut self) -> Vec<RegistrationResult> {
        std::mem::take(&mut self.recovered)
    }

    /// Registers one scan, taken with the lidar model `lidar`.
    ///
    /// 1. Build the scan's range-image pyramid.
    /// 2. The first scan anchors the world frame.
    /// 3. Initial guess from the constant-velocity motion model.
    /// 4. Align against the keyframe window (`align`).
    /// 5. On failure: keep the scan for a retry; the model does not change.
    /// 6. On success: the scan hangs from the window keyframe it overlaps most; when
    ///    it moved far enough to be a keyframe, either it re-localises on an existing
    ///    keyframe of mapped ground or it becomes a new keyframe (a graph node), which
    ///    looks for loop closures; then retry the failed scans against the window.
    pub fn register(&mut self, scan: Arc<TexelScan>, sensor: &SensorModel) -> RegistrationResult {
        self.tick += 1;
        let timestamp_ns = scan.timestamp_ns;
        let seq = scan.seq;
        let pyramid = self.pyramid_of(Arc::clone(&scan), sensor);
        if self.scans.is_empty() {
            return self.anchor_first(scan, pyramid);
        }
        let initial = self.motion.predict(timestamp_ns);
        let alignment = self.align_to_window(&pyramid, &initial);
        self.touch_window();
        if let Err(reason) = &alignment.status {
            self.stats.failed += 1;
            self.keep_for_retry(scan, Arc::clone(&pyramid));
            return failed_result(timestamp_ns, seq, &alignment, reason.clone());
        }
        let mut result = self.insert(scan, pyramid, &alignment, true);
        self.stats.registered += 1;
        self.retry_pending();
        result.world_from_scan = result
            .scan_id
            .and_then(|id| self.pose(id))
            .unwrap_or(result.world_from_scan);
        result
    }

    fn derived_pose(&self, record: &ScanRecord) -> Option<Pose> {
        let world_from_keyframe = self.graph.poses().get(record.keyframe as usize)?;
        Some(world_from_keyframe * record.keyframe_from_scan)
    }

    fn keyframe_pose(&self, ordinal: usize) -> Pose {
        self.graph
            .poses()
            .get(ordinal)
            .copied()
            .unwrap_or(self.anchor)
    }

    fn thresholds(&self) -> RevisionThresholds {
        RevisionThresholds {
            translation_m: self.config.global.revision_translation_m,
            rotation_rad: self.config.global.revision_rotation_deg.to_radians(),
        }
    }

    /// The scan's pyramid, with its EO luminance pyramid when the photometric term
    /// is on.
    fn pyramid_of(&mut self, scan: Arc<TexelScan>, sensor: &SensorModel) -> Arc<ScanPyramid> {
        let lidar = shared(&mut self.lidar, &sensor.lidar);
        let eo = shared(&mut self.eo, &sensor.eo);
        let photometric = &self.config.align.photometric;
        Arc::new(ScanPyramid::build_with(
            scan,
            &lidar,
            Some(&eo),
            PyramidOptions {
                levels: self.config.align.pyramid_levels,
                eo_levels: if photometric.enabled() {
                    photometric.eo_levels
                } else {
                    0
                },
                first_eo_level: photometric.finest_eo_level,
            },
        ))
    }

    fn anchor_first(
        &mut self,
        scan: Arc<TexelScan>,
        pyramid: Arc<ScanPyramid>,
    ) -> RegistrationResult {
        let ordinal = self.graph.add_node(self.anchor);
        let id = self.scans.push(ScanRecord {
            keyframe_from_scan: Pose::identity(),
            emitted: CompactPose::from_pose(&self.anchor),
            timestamp_ns: scan.timestamp_ns,
            keyframe: 0,
        });
        self.keyframes.push(Keyframe {
            scan: id as u32,
            pyramid: Some(pyramid),
            last_used: self.tick,
            members: Dependents::with(id as ScanId),
        });
        self.rehung.push(id as u32);
        self.resident += 1;
        self.window.push_back(ordinal);
        self.motion.update(scan.timestamp_ns, self.anchor);
        self.stats.keyframes += 1;
        self.stats.registered += 1;
        self.events.push(ModelEvent::ScanAdded {
            id: id as ScanId,
            scan: Arc::clone(&scan),
            world_from_scan: self.anchor,
        });
        RegistrationResult {
            timestamp_ns: scan.timestamp_ns,
            seq: scan.seq,
            status: RegistrationStatus::Anchor,
            scan_id: Some(id as ScanId),
            world_from_scan: self.anchor,
            covariance: Matrix6::zeros(),
            fitness: Fitness::default(),
            degenerate: Vec::new(),
            iterations: 0,
            keyframe: true,
            loop_closures: 0,
            photometric: Default::default(),
        }
    }

    fn align_to_window(&self, pyramid: &ScanPyramid, initial: &Pose) -> Alignment {
        let targets = self.window_targets();
        align(pyramid, &targets, initial, &self.config.align)
    }

    /// The window's keyframes as alignment targets, in window order (a window
    /// keyframe's pyramid is always resident).
    fn window_targets(&self) -> Vec<AlignTarget<'_>> {
        self.window
            .iter()
            .filter_map(|&o| {
                let pyramid = self.keyframes.get(o)?.pyramid.as_deref()?;
                Some(AlignTarget {
                    pyramid,
                    world_from_target: self.keyframe_pose(o),
                })
            })
            .collect()
    }

    fn touch_window(&mut self) {
        for &o in &self.window {
            if let Some(k) = self.keyframes.get_mut(o) {
                k.last_used = self.tick;
            }
        }
    }

    /// Adds a registered scan to the model, hanging from the window keyframe it
    /// overlaps most; `live` scans (not recovered ones) update the motion model and
    /// may re-localise or become keyframes.
    fn insert(
        &mut self,
        scan: Arc<TexelScan>,
        pyramid: Arc<ScanPyramid>,
        alignment: &Alignment,
        live: bool,
    ) -> RegistrationResult {
        let pose = alignment.world_from_source;
        let reference = self.reference_keyframe(alignment);
        let id = self.scans.push(ScanRecord {
            keyframe_from_scan: self.keyframe_pose(reference).inverse() * pose,
            emitted: CompactPose::from_pose(&pose),
            timestamp_ns: scan.timestamp_ns,
            keyframe: reference as u32,
        });
        self.add_member(reference, id);
        self.rehung.push(id as u32);
        self.events.push(ModelEvent::ScanAdded {
            id: id as ScanId,
            scan: Arc::clone(&scan),
            world_from_scan: pose,
        });
        let mut loop_closures = 0;
        let mut keyframe = false;
        if live {
            self.motion.update(scan.timestamp_ns, pose);
            if self.is_new_keyframe(&pose, &alignment.fitness) {
                match self.relocalise(id, reference, &pyramid, &pose) {
                    Some(loops) => loop_closures = loops,
                    None if self.keyframes.len() < u32::MAX as usize => {
                        keyframe = true;
                        let ordinal = self.add_keyframe(id, reference, pyramid, alignment);
                        if self.config.global.enabled {
                            loop_closures = self.close_loops(ordinal);
                        }
                    }
                    None => {}
                }
            }
        }
        RegistrationResult {
            timestamp_ns: scan.timestamp_ns,
            seq: scan.seq,
            status: RegistrationStatus::Registered,
            scan_id: Some(id as ScanId),
            world_from_scan: pose,
            covariance: alignment.covariance,
            fitness: alignment.fitness,
            degenerate: alignment.degenerate.clone(),
            iterations: alignment.iterations,
            keyframe,
            loop_closures,
            photometric: alignment.photometric,
        }
    }

    /// The window keyframe with the most correspondences (the newest on a tie).
    fn reference_keyframe(&self, alignment: &Alignment) -> usize {
        let newest = self.window.back().copied().unwrap_or(0);
        self.window
            .iter()
            .enumerate()
            .map(|(k, &o)| {
                let count = alignment
                    .target_correspondences
                    .get(k)
                    .copied()
                    .unwrap_or(0);
                (count, k, o)
            })
            .max_by_key(|&(count, k, _)| (count, k))
            .filter(|&(count, _, _)| count > 0)
            .map_or(newest, |(_, _, o)| o)
    }

    fn is_new_keyframe(&self, pose: &Pose, fitness: &Fitness) -> bool {
        let k = &self.config.keyframes;
        let Some(&newest) = self.window.back() else {
            return true;
        };
        let (angle, dist) = pose_difference(&self.keyframe_pose(newest), pose);
        dist > k.translation_m
            || angle.to_degrees() > k.rotation_deg
            || fitness.overlap < k.min_overlap
    }

    /// Makes scan `id` (hanging from `reference`) a keyframe: a graph node with one
    /// edge per window keyframe it overlaps. Returns its ordinal.
    fn add_keyframe(
        &mut self,
        id: usize,
        reference: usize,
        pyramid: Arc<ScanPyramid>,
        alignment: &Alignment,
    ) -> usize {
        let pose = alignment.world_from_source;
        let ordinal = self.graph.add_node(pose);
        let mut edges = 0;
        for (k, &o) in self.window.iter().enumerate() {
            let count = alignment
                .target_correspondences
                .get(k)
                .copied()
                .unwrap_or(0);
            let Some(information) = alignment.target_information.get(k) else {
                continue;
            };
            if count >= MIN_EDGE_CORRESPONDENCES {
                let before = self.graph.edges().len();
                self.graph.add_edge(Edge {
                    i: o,
                    j: ordinal,
                    measured: self.keyframe_pose(o).inverse() * pose,
                    information: *information,
                    loop_closure: false,
                });
                edges += self.graph.edges().len() - before;
            }
        }
        if edges == 0 {
            // Keep the node tied to the map: the whole alignment against its reference.
            self.graph.add_edge(Edge {
                i: reference,
                j: ordinal,
                measured: self.keyframe_pose(reference).inverse() * pose,
                information: alignment.information,
                loop_closure: false,
            });
        }
        // The scan now hangs from itself.
        if self
            .scans
            .get(id)
            .is_some_and(|r| r.keyframe as usize == reference)
        {
            self.remove_member(reference, id);
        }
        self.scans.update(id, |r| {
            r.keyframe = ordinal as u32;
            r.keyframe_from_scan = Pose::identity();
        });
        self.keyframes.push(Keyframe {
            scan: id as u32,
            pyramid: Some(pyramid),
            last_used: self.tick,
            members: Dependents::with(id as ScanId),
        });
        self.rehung.push(id as u32);
        self.resident += 1;
        self.enter_window(ordinal);
        self.stats.keyframes += 1;
        ordinal
    }

    /// Makes `ordinal` the newest keyframe of the window, then drops the pyramids the
    /// residency bound no longer allows.
    fn enter_window(&mut self, ordinal: usize) {
        self.window.retain(|&o| o != ordinal);
        self.window.push_back(ordinal);
        while self.window.len() > self.config.keyframes.window as usize {
            self.window.pop_front();
        }
        if let Some(k) = self.keyframes.get_mut(ordinal) {
            k.last_used = self.tick;
        }
        self.evict();
    }

    fn keep_for_retry(&mut self, scan: Arc<TexelScan>, pyramid: Arc<ScanPyramid>) {
        if self.config.retry.max_pending == 0 || self.config.retry.max_retries == 0 {
            return;
        }
        self.pending.push_back(Pending {
            scan,
            pyramid,
            retries: 0,
        });
        while self.pending.len() > self.config.retry.max_pending as usize {
            self.pending.pop_front();
            self.stats.given_up += 1;
        }
    }

    /// Tries the failed scans again against the current window, starting from the
    /// newest registered pose (the camera was last seen there).
    fn retry_pending(&mut self) {
        if self.pending.is_empty() {
            return;
        }
        let Some(guess) = self
            .scans
            .len()
            .checked_sub(1)
            .and_then(|i| self.pose(i as ScanId))
        else {
            return;
        };
        let mut still = VecDeque::new();
        while let Some(mut p) = self.pending.pop_front() {
            let alignment = self.align_to_window(&p.pyramid, &guess);
            if alignment.is_ok() {
                let result = self.insert(
                    Arc::clone(&p.scan),
                    Arc::clone(&p.pyramid),
                    &alignment,
                    false,
                );
                self.stats.recovered += 1;
                self.recovered.push(result);
            } else {
                p.retries += 1;
                if p.retries >= self.config.retry.max_retries {
                    self.stats.given_up += 1;
                } else {
                    still.push_back(p);
                }
            }
        }
        self.pending = still;
    }
}

fn failed_result(
    timestamp_ns: u64,
    seq: u32,
    alignment: &Alignment,
    reason: FailureReason,
) -> RegistrationResult {
    RegistrationResult {
        timestamp_ns,
        seq,
        status: RegistrationStatus::Failed { reason },
        scan_id: None,
        world_from_scan: alignment.world_from_source,
        covariance: alignment.covariance,
        fitness: alignment.fitness,
        degenerate: alignment.degenerate.clone(),
        iterations: alignment.iterations,
        keyframe: false,
        loop_closures: 0,
        photometric: alignment.photometric,
    }
}

/// The camera in `slot` when it equals `camera`, else `camera` shared from now on.
fn shared(slot: &mut Option<Arc<PinholeCamera>>, camera: &PinholeCamera) -> Arc<PinholeCamera> {
    match slot {
        Some(c) if **c == *camera => Arc::clone(c),
        _ => {
            let c = Arc::new(camera.clone());
            *slot = Some(Arc::clone(&c));
            c
        }
    }
}
