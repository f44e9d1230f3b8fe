//! The shelf: where the retirement index keeps retired scans' entries beyond memory,
//! and the byte form of such an entry. The index holds served scans (and, during one
//! call, the retired scans the call touches); a long session's retired scans, most
//! of its scans, wait on the shelf until a revision or a witness's change needs them.
//! The trait keeps the index I/O-free: its owner chooses the storage (the daemon an
//! on-disk database, tests [`MemoryShelf`]).

use std::collections::HashMap;

use nalgebra::{Quaternion, Translation3, UnitQuaternion};

use crate::model::ScanId;
use crate::pose::Pose;

/// Why the shelf could not answer; the index keeps what it could not shelve in
/// memory, and serves again a scan it could not read back.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("retirement shelf: {0}")]
pub struct ShelfError(pub String);

/// Storage for retired scans' entries, by scan id, as opaque bytes.
pub trait Shelf: Send {
    /// The entries of `ids`, in order: `Ok(None)` for an id it does not hold, an
    /// error for one it holds but cannot give back.
    fn get(&self, ids: &[ScanId]) -> Vec<Result<Option<Vec<u8>>, ShelfError>>;
    /// Removes `removes`, then stores `puts` (replacing entries of the same ids).
    /// After an error a prefix of it may have happened: the caller keeps what it
    /// could not store and stores it again later (storing is idempotent).
    fn commit(&mut self, puts: &[(ScanId, Vec<u8>)], removes: &[ScanId]) -> Result<(), ShelfError>;
    /// Bytes it holds in memory (a cache, a buffer).
    fn heap_bytes(&self) -> usize;
}

/// A shelf in memory: for tests and for tools that want the index's decisions
/// without a database. It saves nothing but the index's open form's overhead.
#[derive(Debug, Default)]
pub struct MemoryShelf {
    entries: HashMap<ScanId, Vec<u8>>,
}

impl MemoryShelf {
    /// The number of entries it holds.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

impl Shelf for MemoryShelf {
    fn get(&self, ids: &[ScanId]) -> Vec<Result<Option<Vec<u8>>, ShelfError>> {
        ids.iter()
            .map(|id| Ok(self.entries.get(id).cloned()))
            .collect()
    }

    fn commit(&mut self, puts: &[(ScanId, Vec<u8>)], removes: &[ScanId]) -> Result<(), ShelfError> {
        for id in removes {
            self.entries.remove(id);
        }
        for (id, bytes) in puts {
            self.entries.insert(*id, bytes.clone());
        }
        Ok(())
    }

    fn heap_bytes(&self) -> usize {
        self.entries.values().map(Vec::len).sum::<usize>()
            + self.entries.capacity() * (std::mem::size_of::<(ScanId, Vec<u8>)>() + 1)
    }
}

/// A retired scan's entry as the index shelves it: the pose its offers were
/// computed at, its score, its witnesses and its packed offers.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct ShelvedEntry {
    pub world_from_scan: Pose,
    pub score: f64,
    pub witnesses: Box<[ScanId]>,
    pub packed_offers: Box<[u8]>,
}

/// Version of the byte form.
const VERSION: u8 = 1;
/// Version, translation (3 f64), rotation quaternion (4 f64), score, witness count.
const FIXED_LEN: usize = 1 + 8 * 3 + 8 * 4 + 8 + 4;
/// The CRC-32 that ends the form.
const CRC_LEN: usize = 4;

impl ShelvedEntry {
    /// The byte form: the fixed fields little-endian, the witnesses, the packed
    /// offers, then a CRC-32 of everything before it.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(
            FIXED_LEN + self.witnesses.len() * 8 + self.packed_offers.len() + CRC_LEN,
        );
        out.push(VERSION);
        let t = self.world_from_scan.translation.vector;
        let q = self.world_from_scan.rotation.quaternion().coords;
        for v in [t.x, t.y, t.z, q.x, q.y, q.z, q.w, self.score] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let count = u32::try_from(self.witnesses.len()).unwrap_or(u32::MAX);
        out.extend_from_slice(&count.to_le_bytes());
        for w in self.witnesses.iter().take(count as usize) {
            out.extend_from_slice(&w.to_le_bytes());
        }
        out.extend_from_slice(&self.packed_offers);
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// The entry of a byte form; an error names what is wrong with it.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, ShelfError> {
        let bad =
            |what: &str| ShelfError(format!("shelved entry of {} bytes: {what}", bytes.len()));
        if bytes.len() < FIXED_LEN + CRC_LEN {
            return Err(bad("shorter than its fixed fields"));
        }
        let (body, crc) = bytes.split_at(bytes.len() - CRC_LEN);
        let crc = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
        if crc32fast::hash(body) != crc {
            return Err(bad("CRC mismatch"));
        }
        if body[0] != VERSION {
            return Err(bad(&format!(
                "version {} (this build reads {VERSION})",
                body[0]
            )));
        }
        let f64_at = |i: usize| {
            let at = 1 + 8 * i;
            let mut b = [0u8; 8];
            b.copy_from_slice(&body[at..at + 8]);
            f64::from_le_bytes(b)
        };
        let values: Vec<f64> = (0..8).map(f64_at).collect();
        if values.iter().any(|v| !v.is_finite()) {
            return Err(bad("a non-finite pose or score"));
        }
        let quaternion = Quaternion::new(values[6], values[3], values[4], values[5]);
        let norm = quaternion.norm();
        if (norm - 1.0).abs() > 1e-6 {
            return Err(bad(&format!("a rotation quaternion of norm {norm}")));
        }
        let at = 1 + 8 * 8;
        let count =
            u32::from_le_bytes([body[at], body[at + 1], body[at + 2], body[at + 3]]) as usize;
        let witnesses_end = count
            .checked_mul(8)
            .and_then(|n| n.checked_add(FIXED_LEN))
            .filter(|&end| end <= body.len())
            .ok_or_else(|| bad(&format!("{count} witnesses do not fit")))?;
        let witnesses = body[FIXED_LEN..witnesses_end]
            .chunks_exact(8)
            .map(|c| {
                let mut b = [0u8; 8];
                b.copy_from_slice(c);
                ScanId::from_le_bytes(b)
            })
            .collect();
        Ok(Self {
            world_from_scan: Pose::from_parts(
                Translation3::new(values[0], values[1], values[2]),
                // Written from a unit quaternion and checked above: kept bit for bit.
                UnitQuaternion::new_unchecked(quaternion),
            ),
            score: values[7],
            witnesses,
            packed_offers: body[witnesses_end..].into(),
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

    use super::*;

    fn entry() -> ShelvedEntry {
        ShelvedEntry {
            world_from_scan: Pose::from_parts(
                Translation3::new(1.25, -3.5, 1e-9),
                UnitQuaternion::from_euler_angles(0.1, -0.7, 2.9),
            ),
            score: 17.5,
            witnesses: vec![3, 99, u64::MAX].into(),
            packed_offers: vec![1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11].into(),
        }
    }

    #[test]
    fn entries_round_trip_bit_for_bit() {
        let e = entry();
        let back = ShelvedEntry::from_bytes(&e.to_bytes()).unwrap();
        assert_eq!(back, e);
        let empty = ShelvedEntry {
            witnesses: Box::default(),
            packed_offers: Box::default(),
            ..entry()
        };
        assert_eq!(ShelvedEntry::from_bytes(&empty.to_bytes()).unwrap(), empty);
    }

    #[test]
    fn damaged_entries_are_refused_by_name() {
        let bytes = entry().to_bytes();
        for cut in [0, 5, FIXED_LEN, bytes.len() - 1] {
            assert!(
                ShelvedEntry::from_bytes(&bytes[..cut]).is_err(),
                "cut at {cut}"
            );
        }
        for at in 0..bytes.len() {
            let mut flipped = bytes.clone();
            flipped[at] ^= 0x10;
            let err = ShelvedEntry::from_bytes(&flipped).unwrap_err();
            assert!(err.0.contains("CRC"), "byte {at}: {err}");
        }
    }
}
