//! Restoring scans an earlier run registered (a resumed session): each is placed
//! where that run placed it, without aligning it again, and the registrar's state is
//! rebuilt as registering them would have left it: keyframes where the motion since
//! the newest keyframe passes the keyframe thresholds (with an odometry edge from
//! it), every other scan hanging from the newest keyframe, the motion model, the
//! next id.

use std::sync::Arc;

use nalgebra::Matrix6;
use texel::coverage::links::Dependents;
use texel::model::ScanId;
use texel::pose::pose_difference;
use texel::{Pose, SensorModel, TexelScan};

use super::{Keyframe, Registrar};
use crate::graph::Edge;
use crate::scan_table::{CompactPose, ScanRecord};

/// Information of a restored odometry edge, per unit of the `(ω, v)` perturbation
/// (rad, m): the earlier run's own edges are not recorded, so a restored edge holds
/// its keyframes about as firmly as a good alignment would (1 mrad, 1 mm).
const RESTORED_EDGE_INFORMATION: f64 = 1.0e6;

impl Registrar {
    /// Takes scan `id`, which an earlier run placed at `world_from_scan`. Ids not yet
    /// seen below `id` (scans restored out of order, or lost) are held by
    /// placeholders at this pose until their own scan comes. Emits no events.
    pub fn restore(
        &mut self,
        scan: Arc<TexelScan>,
        sensor: &SensorModel,
        id: ScanId,
        world_from_scan: Pose,
    ) {
        let Ok(id) = usize::try_from(id) else {
            return;
        };
        let timestamp_ns = scan.timestamp_ns;
        // 1. The first scan anchors the world where the earlier run had it.
        if self.keyframes.is_empty() {
            self.anchor = world_from_scan;
            self.graph.add_node(world_from_scan);
            let pyramid = self.pyramid_of(scan, sensor);
            self.keyframes.push(Keyframe {
                scan: id as u32,
                pyramid: Some(pyramid),
                last_used: self.tick,
                members: Dependents::default(),
            });
            self.resident += 1;
            self.enter_window(0);
            self.stats.keyframes += 1;
            self.place(id, 0, world_from_scan, timestamp_ns);
            self.motion.update(timestamp_ns, world_from_scan);
            return;
        }
        // 2. A keyframe where the live run would have made one.
        let newest = self.window.back().copied().unwrap_or(0);
        let world_from_newest = self.keyframe_pose(newest);
        let (angle, dist) = pose_difference(&world_from_newest, &world_from_scan);
        let k = &self.config.keyframes;
        let reference = if dist > k.translation_m || angle.to_degrees() > k.rotation_deg {
            let ordinal = self.graph.add_node(world_from_scan);
            self.graph.add_edge(Edge {
                i: newest,
                j: ordinal,
                measured: world_from_newest.inverse() * world_from_scan,
                information: Matrix6::identity() * RESTORED_EDGE_INFORMATION,
                loop_closure: false,
            });
            let pyramid = self.pyramid_of(scan, sensor);
            self.keyframes.push(Keyframe {
                scan: id as u32,
                pyramid: Some(pyramid),
                last_used: self.tick,
                members: Dependents::default(),
            });
            self.resident += 1;
            self.enter_window(ordinal);
            self.stats.keyframes += 1;
            ordinal
        } else {
            newest
        };
        // 3. The scan hangs from it; the motion model follows the restored path.
        self.place(id, reference, world_from_scan, timestamp_ns);
        // (The motion model ignores a scan older than its newest.)
        self.motion.update(timestamp_ns, world_from_scan);
    }

    /// Records scan `id` as hanging from keyframe `reference` at `world_from_scan`.
    fn place(&mut self, id: usize, reference: usize, world_from_scan: Pose, timestamp_ns: u64) {
        let record = ScanRecord {
            keyframe_from_scan: self.keyframe_pose(reference).inverse() * world_from_scan,
            emitted: CompactPose::from_pose(&world_from_scan),
            timestamp_ns,
            keyframe: reference as u32,
        };
        while self.scans.len() < id {
            // A placeholder for a scan restored later (or never): it hangs here.
            self.scans.push(record);
        }
        if id < self.scans.len() {
            self.scans.update(id, |r| *r = record);
        } else {
            self.scans.push(record);
        }
        self.add_member(reference, id);
        // This run's keyframes may not be the earlier run's: the recording learns
        // how the scan hangs now.
        self.rehung.push(id as u32);
        self.stats.registered += 1;
    }
}
