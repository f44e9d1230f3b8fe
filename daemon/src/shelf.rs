//! The model's shelf on disk: what the daemon knows of retired scans (retirement's
//! entries, the hub's listings and poses) in an embedded database (redb) in an
//! unlinked file beside the store, so that memory holds the served model and a
//! bounded cache whatever the session's length. The file lives as long as the
//! daemon: a resumed session rebuilds it from the recording.

use std::fs::{File, OpenOptions};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use redb::backends::FileBackend;
use redb::{Database, Durability, ReadableDatabase, TableDefinition};
use texel::Pose;
use texel::coverage::{Shelf, ShelfError};
use texel::model::{ScanId, ScanListing};

/// Retirement's entries of retired scans.
pub const RETIREMENT_TABLE: TableDefinition<'static, u64, &'static [u8]> =
    TableDefinition::new("retirement");
/// The hub's entries of retired scans.
pub const HUB_TABLE: TableDefinition<'static, u64, &'static [u8]> = TableDefinition::new("hub");

/// The database's page cache: the memory the shelf may hold, whatever it holds on
/// disk. Retired scans are read back one call at a time, a few hundred bytes each.
pub const CACHE_BYTES: usize = 8 << 20;

/// Commits between durable ones. Non-durable commits are cheap (no fsync) but redb
/// reuses the pages they free only after a durable commit; without one now and
/// then the file would grow with every revision.
const DURABLE_EVERY: u64 = 256;

/// Why the shelf could not be made.
#[derive(Debug, thiserror::Error)]
#[error("model shelf {path}: {message}")]
pub struct ShelfOpenError {
    pub path: String,
    pub message: String,
}

/// The database behind the daemon's shelves.
pub struct ShelfDb {
    db: Database,
    path: PathBuf,
}

impl ShelfDb {
    /// Creates an empty shelf in `dir`, its file unlinked at once: it lives as long
    /// as the daemon, even one that is killed.
    pub fn create_in(dir: &Path) -> Result<Arc<Self>, ShelfOpenError> {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let path = dir.join(format!("texel-shelf-{}-{nanos}.redb", std::process::id()));
        let fail = |message: String| ShelfOpenError {
            path: path.display().to_string(),
            message,
        };
        let file: File = OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(|e| fail(e.to_string()))?;
        std::fs::remove_file(&path).map_err(|e| fail(format!("cannot unlink: {e}")))?;
        let backend = FileBackend::new(file).map_err(|e| fail(e.to_string()))?;
        let db = Database::builder()
            .set_cache_size(CACHE_BYTES)
            .create_with_backend(backend)
            .map_err(|e| fail(e.to_string()))?;
        // Tables exist from the start, so reads never meet a missing one.
        let txn = db.begin_write().map_err(|e| fail(e.to_string()))?;
        for table in [RETIREMENT_TABLE, HUB_TABLE] {
            txn.open_table(table).map_err(|e| fail(e.to_string()))?;
        }
        txn.commit().map_err(|e| fail(e.to_string()))?;
        Ok(Arc::new(Self { db, path }))
    }

    /// Where the (unlinked) file was made: for messages.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// One table of the shelf database as a [`Shelf`].
pub struct DiskShelf {
    db: Arc<ShelfDb>,
    table: TableDefinition<'static, u64, &'static [u8]>,
    commits: u64,
}

impl DiskShelf {
    pub fn new(db: Arc<ShelfDb>, table: TableDefinition<'static, u64, &'static [u8]>) -> Self {
        Self {
            db,
            table,
            commits: 0,
        }
    }

    fn error(&self, e: impl std::fmt::Display) -> ShelfError {
        ShelfError(format!("{} ({}): {e}", self.db.path.display(), self.table))
    }
}

impl Shelf for DiskShelf {
    fn get(&self, ids: &[ScanId]) -> Result<Vec<Option<Vec<u8>>>, ShelfError> {
        let txn = self.db.db.begin_read().map_err(|e| self.error(e))?;
        let table = txn.open_table(self.table).map_err(|e| self.error(e))?;
        ids.iter()
            .map(|id| {
                table
                    .get(id)
                    .map(|found| found.map(|v| v.value().to_vec()))
                    .map_err(|e| self.error(e))
            })
            .collect()
    }

    fn commit(&mut self, puts: &[(ScanId, Vec<u8>)], removes: &[ScanId]) -> Result<(), ShelfError> {
        let mut txn = self.db.db.begin_write().map_err(|e| self.error(e))?;
        self.commits += 1;
        let durability = if self.commits.is_multiple_of(DURABLE_EVERY) {
            Durability::Immediate
        } else {
            Durability::None
        };
        txn.set_durability(durability).map_err(|e| self.error(e))?;
        {
            let mut table = txn.open_table(self.table).map_err(|e| self.error(e))?;
            for id in removes {
                table.remove(id).map_err(|e| self.error(e))?;
            }
            for (id, bytes) in puts {
                table
                    .insert(id, bytes.as_slice())
                    .map_err(|e| self.error(e))?;
            }
        }
        // Dropping an uncommitted transaction aborts it: an error leaves no part.
        txn.commit().map_err(|e| self.error(e))
    }

    fn heap_bytes(&self) -> usize {
        // The cache is shared by the tables and fills up to its size; each table
        // counts half so that the two together count it once.
        CACHE_BYTES / 2
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
    fn entries_round_trip_and_tables_are_apart() {
        let dir = std::env::temp_dir();
        let db = ShelfDb::create_in(&dir).unwrap();
        assert!(!db.path().exists(), "the file is unlinked");
        let mut retirement = DiskShelf::new(Arc::clone(&db), RETIREMENT_TABLE);
        let mut hub = DiskShelf::new(Arc::clone(&db), HUB_TABLE);
        let big: Vec<u8> = (0..5000u32).map(|i| (i * 7) as u8).collect();
        retirement
            .commit(&[(1, vec![1, 2, 3]), (u64::MAX, big.clone())], &[])
            .unwrap();
        hub.commit(&[(1, vec![9])], &[]).unwrap();
        assert_eq!(
            retirement.get(&[1, 2, u64::MAX]).unwrap(),
            vec![Some(vec![1, 2, 3]), None, Some(big)]
        );
        assert_eq!(hub.get(&[1]).unwrap(), vec![Some(vec![9])]);
        retirement.commit(&[(2, vec![4])], &[1]).unwrap();
        assert_eq!(retirement.get(&[1, 2]).unwrap(), vec![None, Some(vec![4])]);
        assert_eq!(hub.get(&[1]).unwrap(), vec![Some(vec![9])]);
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

    #[test]
    fn many_commits_reuse_the_file_s_pages() {
        let db = ShelfDb::create_in(&std::env::temp_dir()).unwrap();
        let mut shelf = DiskShelf::new(Arc::clone(&db), RETIREMENT_TABLE);
        // A thousand entries rewritten many times, as revisions rewrite retired
        // scans: the live data is 500 kB whatever the number of rewrites.
        for round in 0..20u64 {
            for chunk in 0..10u64 {
                let puts: Vec<(ScanId, Vec<u8>)> = (0..100)
                    .map(|i| (chunk * 100 + i, vec![round as u8; 500]))
                    .collect();
                shelf.commit(&puts, &[]).unwrap();
            }
        }
        let stats = {
            let txn = db.db.begin_write().unwrap();
            let stats = txn.stats().unwrap();
            txn.abort().unwrap();
            stats
        };
        let allocated = stats.allocated_pages() * stats.page_size() as u64;
        assert!(
            allocated < 8 << 20,
            "{allocated} bytes allocated for 500 kB of entries"
        );
        assert_eq!(shelf.get(&[999]).unwrap(), vec![Some(vec![19u8; 500])]);
    }
}
