//! The registrar's record of every registered scan, kept compact because it grows
//! with the frames: the keyframe the scan hangs from, its pose relative to that
//! keyframe (its world pose is derived from the keyframe's), the pose last sent to
//! the model for it (to send a revision only when it moved beyond the thresholds),
//! and its timestamp.

use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use texel::Pose;
use texel::pose::pose_difference;

/// Records are appended in blocks of at least this many (and a quarter of what is
/// held), so the spare capacity stays under a quarter instead of doubling.
const MIN_GROWTH: usize = 32;

/// A pose in single precision, only ever compared with a threshold of millimetres
/// and hundredths of a degree (f32 holds a world position of 1 km to 0.06 mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompactPose {
    translation_m: [f32; 3],
    /// `(i, j, k, w)`.
    rotation: [f32; 4],
}

impl CompactPose {
    pub fn from_pose(pose: &Pose) -> Self {
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion().coords;
        Self {
            translation_m: [t.x as f32, t.y as f32, t.z as f32],
            rotation: [q.x as f32, q.y as f32, q.z as f32, q.w as f32],
        }
    }

    pub fn to_pose(self) -> Pose {
        let [x, y, z] = self.translation_m.map(f64::from);
        let [i, j, k, w] = self.rotation.map(f64::from);
        // Renormalised: the rounding to f32 leaves the norm a few 1e-8 off one (and a
        // zero quaternion, impossible from a unit one, becomes the identity).
        let q = Quaternion::new(w, i, j, k);
        let rotation = if q.norm() > 0.5 {
            UnitQuaternion::from_quaternion(q)
        } else {
            UnitQuaternion::identity()
        };
        Pose::from_parts(Translation3::new(x, y, z), rotation)
    }
}

/// One registered scan.
#[derive(Debug, Clone, Copy)]
pub struct ScanRecord {
    /// `keyframe⁻¹ · world_from_scan` when the scan was placed (identity for a
    /// keyframe itself).
    pub keyframe_from_scan: Pose,
    /// The pose the model was last told (`ScanAdded` or the last `PoseRevised`).
    pub emitted: CompactPose,
    pub timestamp_ns: u64,
    /// The graph node (keyframe ordinal) the scan hangs from.
    pub keyframe: u32,
}

/// Thresholds beyond which a derived pose is sent to the model again.
#[derive(Debug, Clone, Copy)]
pub struct RevisionThresholds {
    pub translation_m: f64,
    pub rotation_rad: f64,
}

impl RevisionThresholds {
    /// True when `a` and `b` differ by more than a threshold (or cannot be compared).
    pub fn exceeded(&self, a: &Pose, b: &Pose) -> bool {
        let (angle, dist) = pose_difference(a, b);
        !(angle <= self.rotation_rad && dist <= self.translation_m)
    }
}

/// Every registered scan by id (ids count from 0 without gaps).
#[derive(Debug, Clone, Default)]
pub struct ScanTable {
    records: Vec<ScanRecord>,
}

impl ScanTable {
    pub fn len(&self) -> usize {
        self.records.len()
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    pub fn get(&self, id: usize) -> Option<&ScanRecord> {
        self.records.get(id)
    }

    pub fn get_mut(&mut self, id: usize) -> Option<&mut ScanRecord> {
        self.records.get_mut(id)
    }

    /// Appends a record; returns its id.
    pub fn push(&mut self, record: ScanRecord) -> usize {
        if self.records.len() == self.records.capacity() {
            let extra = (self.records.len() / 4).max(MIN_GROWTH);
            self.records.reserve_exact(extra);
        }
        self.records.push(record);
        self.records.len() - 1
    }

    pub fn iter(&self) -> impl Iterator<Item = &ScanRecord> {
        self.records.iter()
    }

    /// The newest scan with this timestamp.
    pub fn newest_at(&self, timestamp_ns: u64) -> Option<&ScanRecord> {
        self.records
            .iter()
            .rev()
            .find(|r| r.timestamp_ns == timestamp_ns)
    }

    /// Heap bytes held (capacity included).
    pub fn heap_bytes(&self) -> usize {
        self.records.capacity() * std::mem::size_of::<ScanRecord>()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_compact_pose_round_trips_within_a_micrometre_near_the_origin() {
        let pose = Pose::from_parts(
            Translation3::new(12.345_678, -3.25, 1.5),
            UnitQuaternion::from_euler_angles(0.3, -1.2, 2.9),
        );
        let back = CompactPose::from_pose(&pose).to_pose();
        let (angle, dist) = pose_difference(&pose, &back);
        assert!(angle < 1e-6 && dist < 2e-6, "{angle} {dist}");
    }

    #[test]
    fn the_table_grows_by_a_quarter_not_by_doubling() {
        let mut t = ScanTable::default();
        let record = ScanRecord {
            keyframe_from_scan: Pose::identity(),
            emitted: CompactPose::from_pose(&Pose::identity()),
            timestamp_ns: 0,
            keyframe: 0,
        };
        for _ in 0..5000 {
            t.push(record);
        }
        let per_scan = t.heap_bytes() as f64 / t.len() as f64;
        assert!(
            per_scan <= 1.25 * std::mem::size_of::<ScanRecord>() as f64,
            "{per_scan}"
        );
    }
}
