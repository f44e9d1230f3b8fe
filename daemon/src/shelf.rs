//! The model's shelf on disk: what the daemon knows of retired scans (retirement's
//! entries, the hub's listings and poses), so that memory holds the served model
//! whatever the session's length. Each table is a store (`store.rs`: append-only
//! entries with a CRC, found through a paged index) in an unlinked file beside the
//! model's store: a rewrite appends, a removal appends an empty entry. Nothing is
//! flushed to disk (the files live only as long as the daemon; a resumed session
//! rebuilds them from the recording), so a commit never waits for the disk. The
//! superseded entries stay in the file: about 0.5 kB per revision of a retired
//! scan, small beside the store's frame of about 1 MB per scan.

use std::path::Path;
use std::sync::Arc;

use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use texel::Pose;
use texel::coverage::{Shelf, ShelfError};
use texel::model::{ScanId, ScanListing};

use crate::store::{Store, StoreError};

/// Which of the shelf's tables.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ShelfTable {
    /// Retirement's entries of retired scans.
    Retirement,
    /// The hub's entries of retired scans.
    Hub,
    /// Served scans' lists of dependents (retirement's links).
    Links,
}

/// The shelf's tables.
#[derive(Debug)]
pub struct ShelfFiles {
    retirement: Arc<Store>,
    hub: Arc<Store>,
    links: Arc<Store>,
}

impl ShelfFiles {
    /// Creates the shelf's (empty, unlinked) files in `dir`.
    pub fn create_in(dir: &Path) -> Result<Arc<Self>, StoreError> {
        Ok(Arc::new(Self {
            retirement: Arc::new(Store::create_unlinked_in(dir, "shelf-retirement")?),
            hub: Arc::new(Store::create_unlinked_in(dir, "shelf-hub")?),
            links: Arc::new(Store::create_unlinked_in(dir, "shelf-links")?),
        }))
    }

    fn table(&self, table: ShelfTable) -> &Arc<Store> {
        match table {
            ShelfTable::Retirement => &self.retirement,
            ShelfTable::Hub => &self.hub,
            ShelfTable::Links => &self.links,
        }
    }
}

/// One table of the shelf as a [`Shelf`].
pub struct DiskShelf {
    store: Arc<Store>,
}

impl DiskShelf {
    pub fn new(files: Arc<ShelfFiles>, table: ShelfTable) -> Self {
        Self::over(Arc::clone(files.table(table)))
    }

    /// A shelf table of its own in `dir` (the registrar's keyframe member lists).
    pub fn create_in(dir: &Path, name: &str) -> Result<Self, StoreError> {
        Ok(Self::over(Arc::new(Store::create_unlinked_in(dir, name)?)))
    }

    fn over(store: Arc<Store>) -> Self {
        Self { store }
    }

    fn store(&self) -> &Store {
        &self.store
    }
}

impl Shelf for DiskShelf {
    fn get(&self, ids: &[ScanId]) -> Vec<Result<Option<Vec<u8>>, ShelfError>> {
        ids.iter()
            .map(|&id| match self.store().read(id) {
                // An empty entry is a removal.
                Ok(bytes) if bytes.is_empty() => Ok(None),
                Ok(bytes) => Ok(Some(bytes.to_vec())),
                Err(StoreError::Missing { .. }) => Ok(None),
                Err(e) => Err(ShelfError(e.to_string())),
            })
            .collect()
    }

    fn commit(&mut self, puts: &[(ScanId, Vec<u8>)], removes: &[ScanId]) -> Result<(), ShelfError> {
        let store = self.store();
        for &id in removes {
            store
                .append(id, &[])
                .map_err(|e| ShelfError(e.to_string()))?;
        }
        for (id, bytes) in puts {
            store
                .append(*id, bytes)
                .map_err(|e| ShelfError(e.to_string()))?;
        }
        Ok(())
    }

    fn heap_bytes(&self) -> usize {
        self.store().heap_bytes()
    }
}

/// What the hub keeps of a retired scan while it is shelved: its listing and current
/// pose, and whether the pose moved since its frame was encoded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShelvedListing {
    pub listing: ScanListing,
    pub world_from_scan: Pose,
    pub revised: bool,
}

/// Listing (8 + 13 x 4 + 8 bytes), pose (7 x 8), revised (1).
const LISTING_LEN: usize = 8 + 13 * 4 + 8 + 7 * 8 + 1;

impl ShelvedListing {
    /// Fixed fields little-endian, then a CRC-32 of them.
    pub fn to_bytes(&self) -> Vec<u8> {
        let l = &self.listing;
        let mut out = Vec::with_capacity(LISTING_LEN + 4);
        out.extend_from_slice(&l.timestamp_ns.to_le_bytes());
        for v in l.bounds_min_m.iter().chain(&l.bounds_max_m).chain(&l.cop_m) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&l.priority.to_le_bytes());
        // Three spare f32 slots keep the layout's fields aligned to their sizes.
        out.extend_from_slice(&[0u8; 12]);
        out.extend_from_slice(&l.encoded_bytes.to_le_bytes());
        let t = self.world_from_scan.translation.vector;
        let q = self.world_from_scan.rotation.quaternion().coords;
        for v in [t.x, t.y, t.z, q.x, q.y, q.z, q.w] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.push(u8::from(self.revised));
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// The listing of a byte form; an error names what is wrong with it.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        if bytes.len() != LISTING_LEN + 4 {
            return Err(format!(
                "a shelved listing of {} bytes (expected {})",
                bytes.len(),
                LISTING_LEN + 4
            ));
        }
        let (body, crc) = bytes.split_at(LISTING_LEN);
        if crc32fast::hash(body) != u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]) {
            return Err("a shelved listing with a CRC mismatch".into());
        }
        let u64_at = |at: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&body[at..at + 8]);
            u64::from_le_bytes(b)
        };
        let f32_at = |i: usize| {
            let at = 8 + 4 * i;
            f32::from_le_bytes([body[at], body[at + 1], body[at + 2], body[at + 3]])
        };
        let f64_at = |i: usize| f64::from_bits(u64_at(8 + 13 * 4 + 8 + 8 * i));
        let pose: Vec<f64> = (0..7).map(f64_at).collect();
        if pose.iter().any(|v| !v.is_finite()) {
            return Err("a shelved listing with a non-finite pose".into());
        }
        let quaternion = Quaternion::new(pose[6], pose[3], pose[4], pose[5]);
        if (quaternion.norm() - 1.0).abs() > 1e-6 {
            return Err("a shelved listing whose rotation is not a unit quaternion".into());
        }
        Ok(Self {
            listing: ScanListing {
                timestamp_ns: u64_at(0),
                bounds_min_m: [f32_at(0), f32_at(1), f32_at(2)],
                bounds_max_m: [f32_at(3), f32_at(4), f32_at(5)],
                cop_m: [f32_at(6), f32_at(7), f32_at(8)],
                priority: f32_at(9),
                encoded_bytes: u64_at(8 + 13 * 4),
            },
            world_from_scan: Pose::from_parts(
                Translation3::new(pose[0], pose[1], pose[2]),
                UnitQuaternion::new_unchecked(quaternion),
            ),
            revised: body[LISTING_LEN - 1] != 0,
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

    use super::*;

    #[test]
    fn entries_round_trip_removals_hold_and_tables_are_apart() {
        let dir = tempfile::tempdir().unwrap();
        let files = ShelfFiles::create_in(dir.path()).unwrap();
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            0,
            "the files are unlinked"
        );
        let mut retirement = DiskShelf::new(Arc::clone(&files), ShelfTable::Retirement);
        let mut hub = DiskShelf::new(Arc::clone(&files), ShelfTable::Hub);
        let big: Vec<u8> = (0..5000u32).map(|i| (i * 7) as u8).collect();
        retirement
            .commit(&[(1, vec![1, 2, 3]), (1 << 40, big.clone())], &[])
            .unwrap();
        hub.commit(&[(1, vec![9])], &[]).unwrap();
        let got: Vec<_> = retirement
            .get(&[1, 2, 1 << 40])
            .into_iter()
            .map(Result::unwrap)
            .collect();
        assert_eq!(got, vec![Some(vec![1, 2, 3]), None, Some(big)]);
        assert_eq!(hub.get(&[1]).pop().unwrap().unwrap(), Some(vec![9]));
        retirement.commit(&[(2, vec![4])], &[1]).unwrap();
        let got: Vec<_> = retirement
            .get(&[1, 2])
            .into_iter()
            .map(Result::unwrap)
            .collect();
        assert_eq!(got, vec![None, Some(vec![4])]);
        assert_eq!(hub.get(&[1]).pop().unwrap().unwrap(), Some(vec![9]));
        // Put back after a removal, it is there again.
        retirement.commit(&[(1, vec![5])], &[]).unwrap();
        assert_eq!(retirement.get(&[1]).pop().unwrap().unwrap(), Some(vec![5]));
    }

    #[test]
    fn listings_round_trip_and_damage_is_named() {
        let shelved = ShelvedListing {
            listing: ScanListing {
                timestamp_ns: 123_456_789_012,
                bounds_min_m: [-1.0, -2.5, 0.25],
                bounds_max_m: [3.0, 4.0, f32::MAX],
                cop_m: [0.0, -0.0, 1e-7],
                priority: 42.5,
                encoded_bytes: 1 << 40,
            },
            world_from_scan: Pose::from_parts(
                Translation3::new(10.0, -20.0, 0.125),
                UnitQuaternion::from_euler_angles(0.3, 0.2, -1.0),
            ),
            revised: true,
        };
        let bytes = shelved.to_bytes();
        assert_eq!(ShelvedListing::from_bytes(&bytes).unwrap(), shelved);
        assert!(ShelvedListing::from_bytes(&bytes[..bytes.len() - 1]).is_err());
        let mut flipped = bytes.clone();
        flipped[30] ^= 1;
        assert!(
            ShelvedListing::from_bytes(&flipped)
                .unwrap_err()
                .contains("CRC")
        );
    }
}
