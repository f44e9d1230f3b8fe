//! The registrar's record of every registered scan, kept compact because it grows
//! with the frames: the keyframe the scan hangs from, its pose relative to that
//! keyframe (its world pose is derived from the keyframe's), the pose last sent to
//! the model for it (to send a revision only when it moved beyond the thresholds),
//! and its timestamp.

use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use texel::Pose;
use texel::paged::{PageStore, PagedTable, Record};
use texel::pose::pose_difference;

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

impl Record for ScanRecord {
    /// Pose (7 f64), emitted pose (7 f32), timestamp, keyframe.
    const LEN: usize = 7 * 8 + 7 * 4 + 8 + 4;

    fn encode(&self, out: &mut [u8]) {
        let t = self.keyframe_from_scan.translation.vector;
        let q = self.keyframe_from_scan.rotation.quaternion().coords;
        let mut at = 0;
        for v in [t.x, t.y, t.z, q.x, q.y, q.z, q.w] {
            out[at..at + 8].copy_from_slice(&v.to_le_bytes());
            at += 8;
        }
        let e = &self.emitted;
        for v in e.translation_m.iter().chain(&e.rotation) {
            out[at..at + 4].copy_from_slice(&v.to_le_bytes());
            at += 4;
        }
        out[at..at + 8].copy_from_slice(&self.timestamp_ns.to_le_bytes());
        out[at + 8..at + 12].copy_from_slice(&self.keyframe.to_le_bytes());
    }

    fn decode(bytes: &[u8]) -> Option<Self> {
        if bytes.len() != Self::LEN {
            return None;
        }
        let f64_at = |i: usize| {
            Some(f64::from_le_bytes(
                bytes.get(8 * i..8 * i + 8)?.try_into().ok()?,
            ))
        };
        let f32_at = |i: usize| {
            let at = 56 + 4 * i;
            Some(f32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?))
        };
        let p: Vec<f64> = (0..7).map(f64_at).collect::<Option<_>>()?;
        let e: Vec<f32> = (0..7).map(f32_at).collect::<Option<_>>()?;
        if p.iter().any(|v| !v.is_finite()) || e.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let q = Quaternion::new(p[6], p[3], p[4], p[5]);
        if (q.norm() - 1.0).abs() > 1e-6 {
            return None;
        }
        Some(Self {
            // Written from a unit quaternion and checked: kept bit for bit.
            keyframe_from_scan: Pose::from_parts(
                Translation3::new(p[0], p[1], p[2]),
                UnitQuaternion::new_unchecked(q),
            ),
            emitted: CompactPose {
                translation_m: [e[0], e[1], e[2]],
                rotation: [e[3], e[4], e[5], e[6]],
            },
            timestamp_ns: u64::from_le_bytes(bytes.get(84..92)?.try_into().ok()?),
            keyframe: u32::from_le_bytes(bytes.get(92..96)?.try_into().ok()?),
        })
    }
}

/// Every registered scan by id (ids count from 0 without gaps), in memory or, given
/// a page store ([`ScanTable::page_to`]), in memory a few pages at a time: the
/// table grows with the frames, and a long session's old scans are read back only
/// when a revision reaches them.
#[derive(Debug, Default)]
pub struct ScanTable {
    records: PagedTable<ScanRecord>,
}

impl ScanTable {
    pub fn len(&self) -> usize {
        self.records.len()
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// An empty table in pages of `records_per_page` records.
    pub fn with_page_records(records_per_page: usize) -> Self {
        Self {
            records: PagedTable::with_page_records(records_per_page),
        }
    }

    /// Keeps at most `resident_pages` pages of records in memory, the rest in `store`.
    pub fn page_to(&mut self, store: Box<dyn PageStore>, resident_pages: usize) {
        self.records.page_to(store, resident_pages);
    }

    pub fn get(&self, id: usize) -> Option<ScanRecord> {
        self.records.get(id)
    }

    /// Changes record `id`; false when there is none.
    pub fn update(&mut self, id: usize, change: impl FnOnce(&mut ScanRecord)) -> bool {
        self.records.update(id, change)
    }

    /// Appends a record; returns its id.
    pub fn push(&mut self, record: ScanRecord) -> usize {
        self.records.push(record)
    }

    /// Every record, by id.
    pub fn to_vec(&self) -> Vec<ScanRecord> {
        self.records.to_vec()
    }

    /// The newest scan with this timestamp.
    pub fn newest_at(&self, timestamp_ns: u64) -> Option<ScanRecord> {
        self.records
            .find_from_newest(|r| r.timestamp_ns == timestamp_ns)
    }

    /// Heap bytes held (resident pages).
    pub fn heap_bytes(&self) -> usize {
        self.records.heap_bytes()
    }

    /// Page writes and reads that failed.
    pub fn page_errors(&self) -> u64 {
        self.records.errors()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_record_round_trips_bit_for_bit_and_refuses_damage() {
        let record = ScanRecord {
            keyframe_from_scan: Pose::from_parts(
                Translation3::new(-0.125, 3.5, 1e-12),
                UnitQuaternion::from_euler_angles(1.0, -0.5, 0.25),
            ),
            emitted: CompactPose::from_pose(&Pose::translation(100.0, -2.0, 0.5)),
            timestamp_ns: 1_700_000_000_123_456_789,
            keyframe: 4_000_000_000,
        };
        let mut bytes = vec![0u8; ScanRecord::LEN];
        record.encode(&mut bytes);
        let back = ScanRecord::decode(&bytes).unwrap();
        assert_eq!(back.keyframe_from_scan, record.keyframe_from_scan);
        assert_eq!(back.emitted, record.emitted);
        assert_eq!(
            (back.timestamp_ns, back.keyframe),
            (record.timestamp_ns, record.keyframe)
        );
        assert!(ScanRecord::decode(&bytes[1..]).is_none());
        bytes[0..8].copy_from_slice(&f64::NAN.to_le_bytes());
        assert!(ScanRecord::decode(&bytes).is_none());
    }

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
