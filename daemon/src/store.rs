//! The model's on-disk store: an append-only file of scans' `ScanAdded` frames,
//! exactly as served, so scans beyond the memory budget (and retired ones, which may
//! come back) are read back byte for byte when a viewer asks for them.
//!
//! An entry is a 32-byte header, then the frame:
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `TXSE` |
//! | 2 | format version (1), little-endian |
//! | 2 | reserved, 0 |
//! | 8 | scan id |
//! | 4 | frame length |
//! | 4 | CRC-32 (IEEE) of the frame |
//! | 8 | reserved, 0 |
//!
//! Writing appends; reading is positional (`pread`), so readers never wait for the
//! writer or for each other. A daemon killed mid-write leaves a short last entry:
//! [`Store::open_existing`] keeps every whole entry, reports the damaged tail (naming
//! its scan when its header survived) and cuts it off before appending again.

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use bytes::Bytes;
use texel::model::ScanId;
use texel::paged::{PAGE_RECORDS, PagedTable, Record};

use crate::pages::FilePages;

const MAGIC: [u8; 4] = *b"TXSE";
const VERSION: u16 = 1;
const HEADER_LEN: u64 = 32;
/// The longest frame an entry may hold (the wire format's own limit).
const MAX_FRAME_LEN: u64 = texel::wire::MAX_SERVER_FRAME_LEN as u64;

/// Why the store could not write or read.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("model store {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("model store {path}: no entry for scan {id}")]
    Missing { path: String, id: ScanId },
    #[error("model store {path}: scan {id}, entry at byte {offset}: {reason}")]
    Damaged {
        path: String,
        id: ScanId,
        offset: u64,
        reason: String,
    },
    #[error("model store {path}: a frame of {len} bytes is longer than {MAX_FRAME_LEN}")]
    TooLong { path: String, len: u64 },
}

/// Where one scan's entry lies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Slot {
    /// Offset of the entry's header.
    offset: u64,
    len: u32,
    crc: u32,
}

impl Slot {
    /// No entry (a gap in the ids): no frame is this long.
    const ABSENT: Self = Self {
        offset: 0,
        len: u32::MAX,
        crc: 0,
    };
}

impl Record for Slot {
    const LEN: usize = 16;
    fn encode(&self, out: &mut [u8]) {
        out[0..8].copy_from_slice(&self.offset.to_le_bytes());
        out[8..12].copy_from_slice(&self.len.to_le_bytes());
        out[12..16].copy_from_slice(&self.crc.to_le_bytes());
    }
    fn decode(bytes: &[u8]) -> Option<Self> {
        Some(Self {
            offset: u64::from_le_bytes(bytes.get(0..8)?.try_into().ok()?),
            len: u32::from_le_bytes(bytes.get(8..12)?.try_into().ok()?),
            crc: u32::from_le_bytes(bytes.get(12..16)?.try_into().ok()?),
        })
    }
}

/// Ids further than this beyond the highest so far go to the sparse map, so that a
/// stray id never fills the dense table with gaps.
const MAX_ID_GAP: u64 = 1 << 16;

/// Pages of slots (1,024 scans, 16 bytes each, a page) kept in memory.
const RESIDENT_SLOT_PAGES: usize = 4;

/// Where each scan's entry lies: a session's ids count from 0, so by id in a paged
/// table whose pages beyond a few wait in an unlinked file beside the store (its
/// memory does not grow with the session); ids far beyond the others in a map.
struct SlotIndex {
    dense: PagedTable<Slot>,
    sparse: HashMap<ScanId, Slot>,
}

impl SlotIndex {
    fn new(dir: &Path) -> std::io::Result<Self> {
        let pages = FilePages::create_in(dir, "store-slots", PAGE_RECORDS * Slot::LEN)?;
        Ok(Self {
            dense: PagedTable::paged(Box::new(pages), RESIDENT_SLOT_PAGES),
            sparse: HashMap::new(),
        })
    }

    fn insert(&mut self, id: ScanId, slot: Slot) {
        let len = self.dense.len() as u64;
        if id < len {
            self.dense.update(id as usize, |s| *s = slot);
        } else if id - len <= MAX_ID_GAP {
            while (self.dense.len() as u64) < id {
                self.dense.push(Slot::ABSENT);
            }
            self.dense.push(slot);
        } else {
            self.sparse.insert(id, slot);
        }
    }

    fn get(&self, id: ScanId) -> Option<Slot> {
        match usize::try_from(id).ok().and_then(|i| self.dense.get(i)) {
            Some(slot) => (slot != Slot::ABSENT).then_some(slot),
            None => self.sparse.get(&id).copied(),
        }
    }
}

impl std::fmt::Debug for SlotIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SlotIndex")
            .field("dense", &self.dense.len())
            .field("sparse", &self.sparse.len())
            .finish()
    }
}

/// The damaged tail an existing store was cut back from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DamagedTail {
    /// Where the damaged entry began (the file now ends there).
    pub offset: u64,
    /// Its scan, when the header was whole.
    pub id: Option<ScanId>,
    pub reason: String,
}

/// What opening an existing store found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StoreScan {
    /// Scans with a whole entry, in file order.
    pub ids: Vec<ScanId>,
    pub damaged_tail: Option<DamagedTail>,
}

/// The on-disk store of one session's model.
#[derive(Debug)]
pub struct Store {
    path: PathBuf,
    file: File,
    /// Appends are serialised; reads go straight to the file.
    end: Mutex<u64>,
    slots: Mutex<SlotIndex>,
}

fn header(id: ScanId, frame: &[u8], crc: u32) -> [u8; HEADER_LEN as usize] {
    let mut h = [0u8; HEADER_LEN as usize];
    h[0..4].copy_from_slice(&MAGIC);
    h[4..6].copy_from_slice(&VERSION.to_le_bytes());
    h[8..16].copy_from_slice(&id.to_le_bytes());
    h[16..20].copy_from_slice(&(frame.len() as u32).to_le_bytes());
    h[20..24].copy_from_slice(&crc.to_le_bytes());
    h
}

/// A header's scan id, frame length and CRC, or why it is not a header.
fn parse_header(h: &[u8; HEADER_LEN as usize]) -> Result<(ScanId, u32, u32), String> {
    let le32 = |r: std::ops::Range<usize>| {
        let mut b = [0u8; 4];
        b.copy_from_slice(&h[r]);
        u32::from_le_bytes(b)
    };
    if h[0..4] != MAGIC {
        return Err(format!("bad magic {:02x?}", &h[0..4]));
    }
    let version = u16::from_le_bytes([h[4], h[5]]);
    if version != VERSION {
        return Err(format!("format version {version}, expected {VERSION}"));
    }
    let mut id = [0u8; 8];
    id.copy_from_slice(&h[8..16]);
    let len = le32(16..20);
    if u64::from(len) > MAX_FRAME_LEN {
        return Err(format!("frame length {len} exceeds {MAX_FRAME_LEN}"));
    }
    Ok((u64::from_le_bytes(id), len, le32(20..24)))
}

impl Store {
    /// Creates an empty store at `path` (replacing any file there).
    pub fn create(path: &Path) -> Result<Self, StoreError> {
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(path)
            .map_err(|source| io_error(path, source))?;
        Self::with(path, file, 0, Vec::new())
    }

    /// Creates a store in the system's temporary folder whose file is unlinked at
    /// once: it lives as long as the store, even if the process is killed.
    pub fn create_anonymous() -> Result<Self, StoreError> {
        Self::create_unlinked_in(&std::env::temp_dir(), "model")
    }

    /// Creates a store in `dir` whose file is unlinked at once (`name` only marks it
    /// while it is being made).
    pub fn create_unlinked_in(dir: &Path, name: &str) -> Result<Self, StoreError> {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let path = dir.join(format!("texel-{name}-{}-{nanos}.scans", std::process::id()));
        let store = Self::create(&path)?;
        std::fs::remove_file(&path).map_err(|source| io_error(&path, source))?;
        Ok(store)
    }

    /// Opens a store a previous run wrote, keeping every whole entry; a damaged tail
    /// (a run killed mid-write) is reported and cut off so appends continue cleanly.
    pub fn open_existing(path: &Path) -> Result<(Self, StoreScan), StoreError> {
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .map_err(|source| io_error(path, source))?;
        let file_len = file
            .metadata()
            .map_err(|source| io_error(path, source))?
            .len();
        let mut slots = Vec::new();
        let mut scan = StoreScan::default();
        let mut offset = 0u64;
        let mut reader = std::io::BufReader::new(&mut file);
        while offset < file_len {
            match read_entry_at(&mut reader, offset, file_len) {
                Ok((id, slot)) => {
                    slots.push((id, slot));
                    scan.ids.push(id);
                    offset = slot.offset + HEADER_LEN + u64::from(slot.len);
                }
                Err((id, reason)) => {
                    scan.damaged_tail = Some(DamagedTail { offset, id, reason });
                    break;
                }
            }
        }
        drop(reader);
        if offset < file_len {
            file.set_len(offset)
                .map_err(|source| io_error(path, source))?;
        }
        Ok((Self::with(path, file, offset, slots)?, scan))
    }

    fn with(
        path: &Path,
        file: File,
        end: u64,
        slots: Vec<(ScanId, Slot)>,
    ) -> Result<Self, StoreError> {
        let dir = path
            .parent()
            .filter(|d| !d.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let mut index = SlotIndex::new(dir).map_err(|source| io_error(path, source))?;
        for (id, slot) in slots {
            index.insert(id, slot);
        }
        Ok(Self {
            path: path.to_path_buf(),
            file,
            end: Mutex::new(end),
            slots: Mutex::new(index),
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes the store holds in memory: its index's resident pages, and the map of
    /// ids far beyond the others.
    pub fn heap_bytes(&self) -> usize {
        let slots = self
            .slots
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        slots.dense.heap_bytes()
            + slots.sparse.capacity() * (std::mem::size_of::<(ScanId, Slot)>() + 1)
    }

    /// Bytes written so far.
    pub fn len_bytes(&self) -> u64 {
        *self
            .end
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Whether scan `id` has an entry.
    pub fn contains(&self, id: ScanId) -> bool {
        self.slots
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(id)
            .is_some()
    }

    /// Appends scan `id`'s frame; a later entry for the same id supersedes it.
    pub fn append(&self, id: ScanId, frame: &[u8]) -> Result<(), StoreError> {
        if frame.len() as u64 > MAX_FRAME_LEN {
            return Err(StoreError::TooLong {
                path: self.path.display().to_string(),
                len: frame.len() as u64,
            });
        }
        let crc = crc32fast::hash(frame);
        let mut entry = Vec::with_capacity(HEADER_LEN as usize + frame.len());
        entry.extend_from_slice(&header(id, frame, crc));
        entry.extend_from_slice(frame);
        let mut end = self
            .end
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let offset = *end;
        self.file
            .write_all_at(&entry, offset)
            .map_err(|source| io_error(&self.path, source))?;
        *end = offset + entry.len() as u64;
        self.slots
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .insert(
                id,
                Slot {
                    offset,
                    len: frame.len() as u32,
                    crc,
                },
            );
        Ok(())
    }

    /// Reads scan `id`'s frame back, checking its header and CRC.
    pub fn read(&self, id: ScanId) -> Result<Bytes, StoreError> {
        let slot = self
            .slots
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(id)
            .ok_or_else(|| StoreError::Missing {
                path: self.path.display().to_string(),
                id,
            })?;
        let damaged = |reason: String| StoreError::Damaged {
            path: self.path.display().to_string(),
            id,
            offset: slot.offset,
            reason,
        };
        let mut h = [0u8; HEADER_LEN as usize];
        self.file
            .read_exact_at(&mut h, slot.offset)
            .map_err(|e| damaged(format!("header unreadable: {e}")))?;
        let (got_id, len, crc) = parse_header(&h).map_err(damaged)?;
        if (got_id, len, crc) != (id, slot.len, slot.crc) {
            return Err(damaged(format!(
                "header names scan {got_id} ({len} bytes), expected scan {id} ({} bytes)",
                slot.len
            )));
        }
        let mut frame = vec![0u8; len as usize];
        self.file
            .read_exact_at(&mut frame, slot.offset + HEADER_LEN)
            .map_err(|e| damaged(format!("frame unreadable: {e}")))?;
        let got = crc32fast::hash(&frame);
        if got != crc {
            return Err(damaged(format!(
                "CRC 0x{got:08x} does not match 0x{crc:08x}"
            )));
        }
        Ok(Bytes::from(frame))
    }
}

/// Reads the entry at `offset` of a file `file_len` long: its id and slot, or the
/// id (when the header was whole) and why it is not a whole entry.
fn read_entry_at<R: Read + Seek>(
    reader: &mut R,
    offset: u64,
    file_len: u64,
) -> Result<(ScanId, Slot), (Option<ScanId>, String)> {
    if file_len - offset < HEADER_LEN {
        return Err((
            None,
            format!("{} bytes of a {HEADER_LEN}-byte header", file_len - offset),
        ));
    }
    let mut h = [0u8; HEADER_LEN as usize];
    reader
        .seek(SeekFrom::Start(offset))
        .and_then(|_| reader.read_exact(&mut h))
        .map_err(|e| (None, format!("header unreadable: {e}")))?;
    let (id, len, crc) = parse_header(&h).map_err(|reason| (None, reason))?;
    let available = file_len - offset - HEADER_LEN;
    if available < u64::from(len) {
        return Err((
            Some(id),
            format!("truncated: {available} of {len} frame bytes"),
        ));
    }
    let mut frame = vec![0u8; len as usize];
    reader
        .read_exact(&mut frame)
        .map_err(|e| (Some(id), format!("frame unreadable: {e}")))?;
    let got = crc32fast::hash(&frame);
    if got != crc {
        return Err((
            Some(id),
            format!("CRC 0x{got:08x} does not match 0x{crc:08x}"),
        ));
    }
    Ok((id, Slot { offset, len, crc }))
}

fn io_error(path: &Path, source: std::io::Error) -> StoreError {
    StoreError::Io {
        path: path.display().to_string(),
        source,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    fn frame(id: u64, len: usize) -> Vec<u8> {
        (0..len).map(|k| (k as u64 * 31 + id * 7) as u8).collect()
    }

    #[test]
    fn frames_round_trip_byte_for_byte_and_survive_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.store");
        let store = Store::create(&path).unwrap();
        for id in [3u64, 0, 7] {
            store.append(id, &frame(id, 1000 + id as usize)).unwrap();
        }
        store.append(0, &frame(9, 10)).unwrap(); // supersedes the first entry of 0
        for id in [3u64, 7] {
            assert_eq!(
                &store.read(id).unwrap()[..],
                &frame(id, 1000 + id as usize)[..]
            );
        }
        assert_eq!(&store.read(0).unwrap()[..], &frame(9, 10)[..]);
        assert!(matches!(
            store.read(5),
            Err(StoreError::Missing { id: 5, .. })
        ));
        drop(store);
        let (store, scan) = Store::open_existing(&path).unwrap();
        assert_eq!(scan.ids, vec![3, 0, 7, 0]);
        assert_eq!(scan.damaged_tail, None);
        assert_eq!(&store.read(7).unwrap()[..], &frame(7, 1007)[..]);
        assert_eq!(&store.read(0).unwrap()[..], &frame(9, 10)[..]);
    }

    #[test]
    fn a_truncated_last_entry_costs_that_scan_alone() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.store");
        let store = Store::create(&path).unwrap();
        for id in 0..4u64 {
            store.append(id, &frame(id, 500)).unwrap();
        }
        let full = store.len_bytes();
        drop(store);
        // Every cut inside the last entry: header or frame.
        for cut in [1u64, 20, HEADER_LEN, HEADER_LEN + 1, HEADER_LEN + 499] {
            let f = OpenOptions::new().write(true).open(&path).unwrap();
            let last = full - HEADER_LEN - 500;
            f.set_len(last + cut).unwrap();
            drop(f);
            let (store, scan) = Store::open_existing(&path).unwrap();
            assert_eq!(scan.ids, vec![0, 1, 2], "cut {cut}");
            let tail = scan.damaged_tail.expect("the damaged tail is reported");
            assert_eq!(tail.offset, last);
            assert_eq!(tail.id, (cut >= HEADER_LEN).then_some(3), "cut {cut}");
            assert!(tail.reason.contains("truncated") || tail.reason.contains("header"));
            for id in 0..3 {
                assert_eq!(&store.read(id).unwrap()[..], &frame(id, 500)[..]);
            }
            assert!(matches!(
                store.read(3),
                Err(StoreError::Missing { id: 3, .. })
            ));
            // Appending continues where the whole entries end.
            store.append(3, &frame(3, 500)).unwrap();
            assert_eq!(store.len_bytes(), full);
        }
    }

    #[test]
    fn a_corrupted_entry_is_named_when_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.store");
        let store = Store::create(&path).unwrap();
        store.append(1, &frame(1, 64)).unwrap();
        store.append(2, &frame(2, 64)).unwrap();
        // Flip one byte of scan 1's frame behind the store's back.
        let f = OpenOptions::new().write(true).open(&path).unwrap();
        f.write_all_at(&[0xff], HEADER_LEN + 5).unwrap();
        let err = store.read(1).unwrap_err().to_string();
        assert!(err.contains("scan 1") && err.contains("CRC"), "{err}");
        assert_eq!(&store.read(2).unwrap()[..], &frame(2, 64)[..]);
        // Reopening stops at the damage and keeps nothing after it.
        drop(store);
        let (_, scan) = Store::open_existing(&path).unwrap();
        assert_eq!(scan.ids, Vec::<u64>::new());
        assert_eq!(scan.damaged_tail.unwrap().id, Some(1));
    }
}
