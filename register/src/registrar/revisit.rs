//! Revisiting mapped ground: re-localisation on an existing keyframe instead of a new
//! one, loop closure from new keyframes, the bounded graph optimisation that follows
//! either, the revisions it sends, and the bound on resident keyframe pyramids.

use std::ops::Range;

use nalgebra::Vector3;
use texel::Pose;
use texel::model::{ModelEvent, ScanId};
use texel::pose::pose_difference;

use super::Registrar;
use crate::align::{AlignTarget, align};
use crate::graph::Edge;
use crate::pyramid::ScanPyramid;
use crate::result::Alignment;
use crate::scan_table::CompactPose;
use crate::se3;

/// Re-localisation considers keyframes up to this many keyframe thresholds away (the
/// larger of the translation and rotation ratios). A later pass a little off the
/// first sometimes finds none within one threshold and makes a keyframe, but
/// reaching further (1.2 and 1.5 tried, with an earlier weighting of the
/// re-localisation edge) attached scans to keyframes registration placed them
/// against poorly: 15 cm ATE on `register_long_walk` against 3.4 cm with 1.0.
const RELOCALISATION_REACH: f64 = 1.0;

/// Repeated loop measurements between the same two keyframes add up to at most this
/// many times one measurement's information.
const MAX_FUSION_GAIN: f64 = 8.0;

impl Registrar {
    /// Re-localisation of scan `id` (hanging from window keyframe `reference`, placed
    /// at `pose` by the window), which moved far enough to be a keyframe: resident
    /// keyframes outside the window within [`RELOCALISATION_REACH`] keyframe
    /// thresholds of it, nearest first, are verified by registration as loop closure
    /// verifies (and must overlap it by `keyframes.min_overlap`); the first that holds
    /// takes the scan. The window switches to it, and a loop edge joins it to
    /// `reference` when the two placements disagree beyond the revision thresholds
    /// (then the loop between them is optimised). `None` when no keyframe takes the
    /// scan (it becomes a keyframe); else the loop edges added (0 or 1). Off with
    /// global refinement off: then registration stays pure odometry.
    pub(super) fn relocalise(
        &mut self,
        id: usize,
        reference: usize,
        pyramid: &ScanPyramid,
        pose: &Pose,
    ) -> Option<u32> {
        if !self.config.global.enabled {
            return None;
        }
        let k = self.config.keyframes.clone();
        let max_angle_rad = k.rotation_deg.to_radians();
        let candidates = self.candidates(self.config.global.loop_max_candidates, |_, kf| {
            let (angle, dist) = pose_difference(kf, pose);
            // Distance in units of the keyframe thresholds, the larger of the two.
            let reach = (dist / k.translation_m).max(angle / max_angle_rad);
            (reach <= RELOCALISATION_REACH).then_some(reach)
        });
        let (ordinal, alignment) = candidates.into_iter().find_map(|o| {
            let alignment = self.verify(pyramid, o, pose)?;
            (alignment.fitness.overlap >= k.min_overlap).then_some((o, alignment))
        })?;
        let world_from_keyframe = self.keyframe_pose(ordinal);
        let keyframe_from_scan = world_from_keyframe.inverse() * alignment.world_from_source;
        let mut loops = 0;
        if self
            .thresholds()
            .exceeded(&alignment.world_from_source, pose)
            && let Some(edge) =
                self.relocalisation_edge(pyramid, ordinal, reference, &alignment, pose)
            && self.graph.upsert_edge(edge, MAX_FUSION_GAIN)
        {
            loops = 1;
        }
        self.attach(id, reference, ordinal, keyframe_from_scan);
        self.enter_window(ordinal);
        self.stats.relocalisations += 1;
        if loops > 0 {
            self.stats.loop_closures += 1;
            self.refine(ordinal.min(reference)..ordinal.max(reference) + 1, &[id]);
        } else {
            self.revise_scans(&[id]);
            self.revise_motion();
        }
        Some(loops)
    }

    /// The loop edge between old keyframe `ordinal` (which placed the scan as
    /// `alignment` says) and window keyframe `reference`. The window's placement
    /// `pose` is a compromise between window keyframes that may not agree with each
    /// other yet (the drift this edge is about), so the scan is registered against
    /// `reference` alone for the other half of the edge (which must overlap it as
    /// much as a keyframe would, else no edge). The edge takes the old keyframe's
    /// information (its registration is the one that measures the revisit; halving it
    /// for the second half's uncertainty left a badly placed keyframe of the first
    /// pass in place: 3.1 cm ATE against 2.4 cm on the looping walk of
    /// `register_long_walk`), moved to `reference`'s tangent through the adjoint (a
    /// right perturbation δ of the reference is `Ad(scan_from_reference) δ` of the
    /// scan).
    fn relocalisation_edge(
        &mut self,
        pyramid: &ScanPyramid,
        ordinal: usize,
        reference: usize,
        alignment: &Alignment,
        pose: &Pose,
    ) -> Option<Edge> {
        let near_reference = self
            .verify(pyramid, reference, pose)
            .filter(|a| a.fitness.overlap >= self.config.keyframes.min_overlap)?;
        let world_from_reference = self.keyframe_pose(reference);
        let scan_from_reference = near_reference.world_from_source.inverse() * world_from_reference;
        let keyframe_from_scan =
            self.keyframe_pose(ordinal).inverse() * alignment.world_from_source;
        let ad = se3::adjoint(&scan_from_reference);
        Some(Edge {
            i: ordinal,
            j: reference,
            measured: keyframe_from_scan * scan_from_reference,
            information: ad.transpose() * alignment.information * ad,
            loop_closure: true,
        })
    }

    /// Loop closure on new keyframe `ordinal`: older resident keyframes (outside the
    /// window, `loop_min_gap_keyframes` back) within `loop_radius_m` whose optical axes
    /// differ by less than `loop_max_angle_deg`, nearest first, are verified by
    /// registration; each accepted one becomes a graph edge, and the loop is
    /// re-optimised. Returns the loops accepted.
    pub(super) fn close_loops(&mut self, ordinal: usize) -> u32 {
        let g = self.config.global.clone();
        // Rate limit: a closure was just made, the graph is consistent here.
        if self
            .last_loop_keyframe
            .is_some_and(|last| ordinal < last + g.loop_interval_keyframes as usize)
        {
            return 0;
        }
        let Some(pyramid) = self.keyframes.get(ordinal).and_then(|k| k.pyramid.clone()) else {
            return 0;
        };
        let current = self.keyframe_pose(ordinal);
        let axis = current.rotation * Vector3::z();
        let max_angle_rad = g.loop_max_angle_deg.to_radians();
        let candidates = self.candidates(g.loop_max_candidates, |o, kf| {
            let (_, dist) = pose_difference(kf, &current);
            // Viewing directions: the angle between the optical axes.
            let axis_angle = (kf.rotation * Vector3::z()).angle(&axis);
            (o + g.loop_min_gap_keyframes as usize <= ordinal
                && dist <= g.loop_radius_m
                && axis_angle <= max_angle_rad)
                .then_some(dist)
        });
        let mut accepted = 0;
        let mut oldest = ordinal;
        for old in candidates {
            let Some(alignment) = self.verify(&pyramid, old, &current) else {
                continue;
            };
            let edge = Edge {
                i: old,
                j: ordinal,
                measured: self.keyframe_pose(old).inverse() * alignment.world_from_source,
                information: alignment.information,
                loop_closure: true,
            };
            if self.graph.upsert_edge(edge, MAX_FUSION_GAIN) {
                accepted += 1;
                oldest = oldest.min(old);
            }
        }
        if accepted > 0 {
            self.last_loop_keyframe = Some(ordinal);
            self.stats.loop_closures += u64::from(accepted);
            self.refine(oldest..ordinal + 1, &[]);
        }
        accepted
    }

    /// Resident keyframes outside the window that `near` accepts (giving a distance),
    /// nearest first, at most `max`.
    fn candidates(&self, max: u32, near: impl Fn(usize, &Pose) -> Option<f64>) -> Vec<usize> {
        let mut found: Vec<(f64, usize)> = self
            .keyframes
            .iter()
            .enumerate()
            .filter(|(o, k)| k.pyramid.is_some() && !self.window.contains(o))
            .filter_map(|(o, _)| near(o, &self.keyframe_pose(o)).map(|d| (d, o)))
            .collect();
        found.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        found.truncate(max as usize);
        found.into_iter().map(|(_, o)| o).collect()
    }

    /// Registers `pyramid` against keyframe `ordinal` alone from `guess`; the
    /// alignment when it holds (`loop_min_inlier_ratio` of the overlapping samples
    /// are inliers).
    fn verify(&mut self, pyramid: &ScanPyramid, ordinal: usize, guess: &Pose) -> Option<Alignment> {
        let target = self.keyframes.get(ordinal)?.pyramid.clone()?;
        let targets = [AlignTarget {
            pyramid: &target,
            world_from_target: self.keyframe_pose(ordinal),
        }];
        let alignment = align(pyramid, &targets, guess, &self.config.align);
        if let Some(k) = self.keyframes.get_mut(ordinal) {
            k.last_used = self.tick;
        }
        let good = alignment.is_ok()
            && alignment.fitness.inlier_ratio_of_overlap
                >= self.config.global.loop_min_inlier_ratio;
        if !good {
            self.stats.loop_candidates_rejected += 1;
        }
        good.then_some(alignment)
    }

    /// Moves scan `id` from keyframe `from` to keyframe `to`.
    fn attach(&mut self, id: usize, from: usize, to: usize, keyframe_from_scan: Pose) {
        self.remove_member(from, id);
        self.add_member(to, id);
        self.scans.update(id, |r| {
            r.keyframe = to as u32;
            r.keyframe_from_scan = keyframe_from_scan;
        });
        self.rehung.push(id as u32);
    }

    /// Global refinement of the keyframes in `loop_range` (the newest
    /// `max_optimised_keyframes` of them; every other keyframe held fixed), then a
    /// revision for every scan of a moved keyframe, and the scans in `also`, whose
    /// derived pose left the revision thresholds of the pose last sent.
    fn refine(&mut self, loop_range: Range<usize>, also: &[usize]) {
        let g = &self.config.global;
        let end = loop_range.end.min(self.graph.len());
        let start = loop_range
            .start
            .max(end.saturating_sub(g.max_optimised_keyframes as usize));
        self.graph.optimise_range(start..end, g.max_iterations);
        self.stats.graph_optimisations += 1;
        self.revise_keyframes(start..end);
        self.revise_scans(also);
        self.revise_motion();
    }

    /// Revisions for the scans of the keyframes in `range`.
    fn revise_keyframes(&mut self, range: Range<usize>) {
        let thresholds = self.thresholds();
        for o in range {
            let Some(world_from_keyframe) = self.graph.poses().get(o).copied() else {
                continue;
            };
            for id in self.members_of(o) {
                let mut revised = None;
                self.scans.update(id as usize, |r| {
                    let derived = world_from_keyframe * r.keyframe_from_scan;
                    if thresholds.exceeded(&derived, &r.emitted.to_pose()) {
                        r.emitted = CompactPose::from_pose(&derived);
                        revised = Some(derived);
                    }
                });
                if let Some(world_from_scan) = revised {
                    self.events.push(ModelEvent::PoseRevised {
                        id: ScanId::from(id),
                        world_from_scan,
                    });
                }
            }
        }
    }

    /// Revisions for the scans `ids`.
    fn revise_scans(&mut self, ids: &[usize]) {
        let thresholds = self.thresholds();
        for &id in ids {
            let Some(derived) = self.pose(id as ScanId) else {
                continue;
            };
            let mut revised = false;
            self.scans.update(id, |r| {
                if thresholds.exceeded(&derived, &r.emitted.to_pose()) {
                    r.emitted = CompactPose::from_pose(&derived);
                    revised = true;
                }
            });
            if revised {
                self.events.push(ModelEvent::PoseRevised {
                    id: id as ScanId,
                    world_from_scan: derived,
                });
            }
        }
    }

    /// The motion model follows the derived pose of the last scan it recorded,
    /// keeping its velocity.
    fn revise_motion(&mut self) {
        let Some(t) = self.motion.last_timestamp_ns() else {
            return;
        };
        let Some(pose) = self.scans.newest_at(t).and_then(|r| self.derived_pose(&r)) else {
            return;
        };
        self.motion.rebase(pose);
    }

    /// Drops the pyramids of the least recently used keyframes outside the window
    /// while more than `keyframes.max_resident` are held (their nodes and poses stay;
    /// they are no longer re-localisation or loop-closure candidates: rebuilding one
    /// would need its scan, which is what dropping it frees).
    pub(super) fn evict(&mut self) {
        let max = self.config.keyframes.max_resident as usize;
        while self.resident > max {
            let victim = self
                .keyframes
                .iter()
                .enumerate()
                .filter(|(o, k)| k.pyramid.is_some() && !self.window.contains(o))
                .min_by_key(|(o, k)| (k.last_used, *o))
                .map(|(o, _)| o);
            let Some(v) = victim else { break };
            if let Some(k) = self.keyframes.get_mut(v) {
                k.pyramid = None;
            }
            self.resident -= 1;
            self.stats.pyramids_dropped += 1;
        }
    }
}
