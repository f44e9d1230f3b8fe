//! The registrar: registers each new scan against the model-side keyframe window,
//! keeps the motion model, the pose graph and the failed scans waiting for a retry,
//! and reports what changes in the model as [`ModelEvent`]s.

use std::collections::VecDeque;
use std::sync::Arc;

use nalgebra::Matrix6;
use texel::model::{ModelEvent, ScanId};
use texel::pose::pose_difference;
use texel::{PinholeCamera, Pose, TexelScan};

use super::align::{AlignTarget, align};
use super::config::RegistrationConfig;
use super::graph::{Edge, PoseGraph};
use super::motion::MotionModel;
use super::pyramid::{PyramidOptions, ScanPyramid};
use super::result::{Alignment, FailureReason, Fitness, RegistrationResult, RegistrationStatus};

/// Fewest correspondences with one keyframe for the pair to become a graph edge.
const MIN_EDGE_CORRESPONDENCES: usize = 12;

/// A registered scan.
struct Node {
    lidar: Arc<PinholeCamera>,
    timestamp_ns: u64,
    /// Its position in the keyframe sequence, if it is a keyframe.
    keyframe: Option<usize>,
    /// A keyframe's pyramid, built once when the scan arrived and kept for loop
    /// closure (never rebuilt per registration).
    pyramid: Option<Arc<ScanPyramid>>,
}

/// A keyframe of the window, with its pyramid.
struct WindowEntry {
    node: usize,
    pyramid: Arc<ScanPyramid>,
}

/// A scan that failed, waiting for a later keyframe to register against.
struct Pending {
    pyramid: Arc<ScanPyramid>,
    lidar: Arc<PinholeCamera>,
    retries: u32,
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
}

/// Scan-to-model registration with global refinement.
pub struct Registrar {
    config: RegistrationConfig,
    anchor: Pose,
    nodes: Vec<Node>,
    /// Keyframe node of each keyframe ordinal.
    keyframes: Vec<usize>,
    window: VecDeque<WindowEntry>,
    graph: PoseGraph,
    motion: MotionModel,
    pending: VecDeque<Pending>,
    events: Vec<ModelEvent>,
    recovered: Vec<RegistrationResult>,
    stats: RegistrarStats,
    /// Keyframe ordinal of the last accepted loop closure.
    last_loop_keyframe: Option<usize>,
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
            nodes: Vec::new(),
            keyframes: Vec::new(),
            window: VecDeque::new(),
            graph: PoseGraph::new(),
            motion: MotionModel::new(),
            pending: VecDeque::new(),
            events: Vec::new(),
            recovered: Vec::new(),
            stats: RegistrarStats::default(),
            last_loop_keyframe: None,
        }
    }

    pub fn config(&self) -> &RegistrationConfig {
        &self.config
    }

    /// The current pose of a registered scan.
    pub fn pose(&self, id: ScanId) -> Option<Pose> {
        usize::try_from(id)
            .ok()
            .and_then(|i| self.graph.poses().get(i).copied())
    }

    /// Current poses of all registered scans, by id.
    pub fn poses(&self) -> &[Pose] {
        self.graph.poses()
    }

    /// Timestamp of a registered scan.
    pub fn timestamp_ns(&self, id: ScanId) -> Option<u64> {
        usize::try_from(id)
            .ok()
            .and_then(|i| self.nodes.get(i))
            .map(|n| n.timestamp_ns)
    }

    pub fn stats(&self) -> RegistrarStats {
        self.stats
    }

    pub fn graph(&self) -> &PoseGraph {
        &self.graph
    }

    /// Model events since the last call, in order: `ScanAdded` for every scan that
    /// entered the model (new ones and recovered ones), `PoseRevised` for every pose
    /// global refinement moved.
    pub fn take_events(&mut self) -> Vec<ModelEvent> {
        std::mem::take(&mut self.events)
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
    /// 6. On success: a new graph node with one edge per keyframe it overlaps; maybe
    ///    a new keyframe, which looks for loop closures and, on one, re-optimises the
    ///    graph; then retry the failed scans against the updated window.
    pub fn register(&mut self, scan: Arc<TexelScan>, lidar: &PinholeCamera) -> RegistrationResult {
        let lidar = self.shared_camera(lidar);
        let timestamp_ns = scan.timestamp_ns;
        let seq = scan.seq;
        let pyramid = Arc::new(ScanPyramid::build_with(
            scan,
            &lidar,
            PyramidOptions {
                levels: self.config.align.pyramid_levels,
                gradients: self.config.align.photometric_weight > 0.0,
            },
        ));
        if self.nodes.is_empty() {
            return self.anchor_first(pyramid, lidar);
        }
        let initial = self.motion.predict(timestamp_ns);
        let alignment = self.align_to_window(&pyramid, &initial);
        if let Err(reason) = &alignment.status {
            self.stats.failed += 1;
            self.keep_for_retry(Arc::clone(&pyramid), lidar);
            return failed_result(timestamp_ns, seq, &alignment, reason.clone());
        }
        let mut result = self.insert(pyramid, lidar, &alignment, true);
        self.stats.registered += 1;
        self.retry_pending();
        result.world_from_scan = result
            .scan_id
            .and_then(|id| self.pose(id))
            .unwrap_or(result.world_from_scan);
        result
    }

    fn shared_camera(&self, lidar: &PinholeCamera) -> Arc<PinholeCamera> {
        match self.nodes.last() {
            Some(n) if *n.lidar == *lidar => Arc::clone(&n.lidar),
            _ => Arc::new(lidar.clone()),
        }
    }

    fn anchor_first(
        &mut self,
        pyramid: Arc<ScanPyramid>,
        lidar: Arc<PinholeCamera>,
    ) -> RegistrationResult {
        let scan = Arc::clone(&pyramid.scan);
        let id = self.graph.add_node(self.anchor);
        self.nodes.push(Node {
            lidar,
            timestamp_ns: scan.timestamp_ns,
            keyframe: Some(0),
            pyramid: Some(Arc::clone(&pyramid)),
        });
        self.keyframes.push(id);
        self.window.push_back(WindowEntry { node: id, pyramid });
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
        }
    }

    fn align_to_window(&self, pyramid: &ScanPyramid, initial: &Pose) -> Alignment {
        let poses = self.graph.poses();
        let targets: Vec<AlignTarget<'_>> = self
            .window
            .iter()
            .map(|w| AlignTarget {
                pyramid: &w.pyramid,
                world_from_target: poses[w.node],
            })
            .collect();
        align(pyramid, &targets, initial, &self.config.align)
    }

    /// Adds a registered scan to the graph and the model; `live` scans (not
    /// recovered ones) update the motion model and may become keyframes.
    fn insert(
        &mut self,
        pyramid: Arc<ScanPyramid>,
        lidar: Arc<PinholeCamera>,
        alignment: &Alignment,
        live: bool,
    ) -> RegistrationResult {
        let scan = Arc::clone(&pyramid.scan);
        let pose = alignment.world_from_source;
        let id = self.graph.add_node(pose);
        // One edge per overlapping keyframe of the window.
        let window_nodes: Vec<usize> = self.window.iter().map(|w| w.node).collect();
        for (k, &node) in window_nodes.iter().enumerate() {
            let count = alignment
                .target_correspondences
                .get(k)
                .copied()
                .unwrap_or(0);
            let Some(information) = alignment.target_information.get(k) else {
                continue;
            };
            if count >= MIN_EDGE_CORRESPONDENCES {
                let measured = self.graph.poses()[node].inverse() * pose;
                self.graph.add_edge(Edge {
                    i: node,
                    j: id,
                    measured,
                    information: *information,
                    loop_closure: false,
                });
            }
        }
        self.nodes.push(Node {
            lidar,
            timestamp_ns: scan.timestamp_ns,
            keyframe: None,
            pyramid: None,
        });
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
                keyframe = true;
                self.add_keyframe(id, Arc::clone(&pyramid));
                if self.config.global.enabled {
                    loop_closures = self.close_loops(id, &pyramid);
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
        }
    }

    fn is_new_keyframe(&self, pose: &Pose, fitness: &Fitness) -> bool {
        let k = &self.config.keyframes;
        let Some(newest) = self.window.back() else {
            return true;
        };
        let (angle, dist) = pose_difference(&self.graph.poses()[newest.node], pose);
        dist > k.translation_m
            || angle.to_degrees() > k.rotation_deg
            || fitness.overlap < k.min_overlap
    }

    fn add_keyframe(&mut self, node: usize, pyramid: Arc<ScanPyramid>) {
        let ordinal = self.keyframes.len();
        self.keyframes.push(node);
        if let Some(n) = self.nodes.get_mut(node) {
            n.keyframe = Some(ordinal);
            n.pyramid = Some(Arc::clone(&pyramid));
        }
        self.window.push_back(WindowEntry { node, pyramid });
        while self.window.len() > self.config.keyframes.window as usize {
            self.window.pop_front();
        }
        self.stats.keyframes += 1;
    }

    /// Loop closure: older keyframes near the new one (by pose) are verified by
    /// registration; each accepted one becomes a graph edge, and the graph is
    /// re-optimised. Returns the loops accepted.
    fn close_loops(&mut self, node: usize, pyramid: &ScanPyramid) -> u32 {
        let g = self.config.global.clone();
        let poses = self.graph.poses();
        let current = poses[node];
        let Some(ordinal) = self.nodes[node].keyframe else {
            return 0;
        };
        // Rate limit: a closure was just made, the graph is consistent here.
        if self
            .last_loop_keyframe
            .is_some_and(|last| ordinal < last + g.loop_interval_keyframes as usize)
        {
            return 0;
        }
        let in_window: Vec<usize> = self.window.iter().map(|w| w.node).collect();
        let mut candidates: Vec<(f64, usize)> = self
            .keyframes
            .iter()
            .enumerate()
            .filter(|&(o, &n)| {
                o + (g.loop_min_gap_keyframes as usize) <= ordinal && !in_window.contains(&n)
            })
            .filter_map(|(_, &n)| {
                let (_, dist) = pose_difference(&poses[n], &current);
                // Viewing directions: the angle between the optical axes.
                let axis_angle = (poses[n].rotation * nalgebra::Vector3::z())
                    .angle(&(current.rotation * nalgebra::Vector3::z()));
                (dist <= g.loop_radius_m && axis_angle.to_degrees() <= g.loop_max_angle_deg)
                    .then_some((dist, n))
            })
            .collect();
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        candidates.truncate(g.loop_max_candidates as usize);
        let mut accepted = 0;
        for (_, old) in candidates {
            let Some(old_pyramid) = self.nodes[old].pyramid.clone() else {
                continue;
            };
            let world_from_old = self.graph.poses()[old];
            let targets = [AlignTarget {
                pyramid: &old_pyramid,
                world_from_target: world_from_old,
            }];
            let alignment = align(pyramid, &targets, &current, &self.config.align);
            let good = alignment.is_ok()
                && alignment.fitness.inlier_ratio_of_overlap >= g.loop_min_inlier_ratio;
            if !good {
                self.stats.loop_candidates_rejected += 1;
                continue;
            }
            let measured = world_from_old.inverse() * alignment.world_from_source;
            self.graph.add_edge(Edge {
                i: old,
                j: node,
                measured,
                information: alignment.information,
                loop_closure: true,
            });
            accepted += 1;
        }
        if accepted > 0 {
            self.last_loop_keyframe = Some(ordinal);
            self.stats.loop_closures += u64::from(accepted);
            self.refine();
        }
        accepted
    }

    /// Global refinement: optimise the graph and report every pose that moved.
    fn refine(&mut self) {
        let before = self.graph.poses().to_vec();
        self.graph.optimise(self.config.global.max_iterations);
        self.stats.graph_optimisations += 1;
        let eps = self.config.global.revision_epsilon;
        let after = self.graph.poses().to_vec();
        for (id, (a, b)) in before.iter().zip(after.iter()).enumerate() {
            let (angle, dist) = pose_difference(a, b);
            if angle > eps || dist > eps {
                self.events.push(ModelEvent::PoseRevised {
                    id: id as ScanId,
                    world_from_scan: *b,
                });
            }
        }
        let nodes = &self.nodes;
        self.motion.revise(|t| {
            nodes
                .iter()
                .rposition(|n| n.timestamp_ns == t)
                .map(|i| after[i])
        });
    }

    fn keep_for_retry(&mut self, pyramid: Arc<ScanPyramid>, lidar: Arc<PinholeCamera>) {
        if self.config.retry.max_pending == 0 || self.config.retry.max_retries == 0 {
            return;
        }
        self.pending.push_back(Pending {
            pyramid,
            lidar,
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
        let Some(&guess) = self.graph.poses().last() else {
            return;
        };
        let mut still = VecDeque::new();
        while let Some(mut p) = self.pending.pop_front() {
            let alignment = self.align_to_window(&p.pyramid, &guess);
            if alignment.is_ok() {
                let result = self.insert(Arc::clone(&p.pyramid), p.lidar, &alignment, false);
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
    }
}
