//! A served scan's dependents: the retired scans that name it as a witness, needed
//! whole only when it moves or retires. Without a links shelf they are a sorted list
//! in memory. With one, the list waits on the shelf (ids packed as varint
//! differences, about 2 bytes each) and memory holds only the changes since it was
//! written, merged back every `FLUSH_CHANGES` changes: a looped walk's few served
//! scans gather every retired scan of the session as dependents, so the list would
//! otherwise grow with the session.

use super::shelf::{Shelf, ShelfError};
use crate::model::ScanId;

/// Changes held in memory before the list on the shelf is rewritten with them.
pub const FLUSH_CHANGES: usize = 256;

/// One served scan's dependents (or any set of ids an owner gathers over a session,
/// such as a keyframe's member scans).
#[derive(Debug, Clone, Default)]
pub struct Dependents {
    count: usize,
    /// Without a shelf: all of them. With one: those added since the shelved list
    /// was written. Sorted.
    added: Vec<ScanId>,
    /// With a shelf: those removed since. Sorted.
    removed: Vec<ScanId>,
    /// A list for this scan is on the shelf.
    on_shelf: bool,
}

impl Dependents {
    /// A set of one.
    pub fn with(id: ScanId) -> Self {
        let mut d = Self::default();
        d.insert(id);
        d
    }

    pub fn len(&self) -> usize {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Adds `id` (not already a dependent).
    pub fn insert(&mut self, id: ScanId) {
        if let Ok(at) = self.removed.binary_search(&id) {
            self.removed.remove(at);
        } else if let Err(at) = self.added.binary_search(&id) {
            self.added.insert(at, id);
        } else {
            return;
        }
        self.count += 1;
    }

    /// Removes `id` (a dependent).
    pub fn remove(&mut self, id: ScanId) {
        if let Ok(at) = self.added.binary_search(&id) {
            self.added.remove(at);
        } else if self.on_shelf {
            match self.removed.binary_search(&id) {
                Ok(_) => return,
                Err(at) => self.removed.insert(at, id),
            }
        } else {
            return;
        }
        self.count = self.count.saturating_sub(1);
    }

    /// Whether enough changes are held that the shelved list should take them.
    pub fn flush_due(&self) -> bool {
        self.changes() >= FLUSH_CHANGES
    }

    /// Changes held since the list was last written (all of them without a shelf).
    pub fn changes(&self) -> usize {
        self.added.len() + self.removed.len()
    }

    /// All of them, sorted, and none left: the shelved list (if any) merged with the
    /// changes since, and removed from `links`. When the shelved list cannot be
    /// read, the changes alone and the error.
    pub fn take(
        &mut self,
        owner: ScanId,
        links: Option<&mut Box<dyn Shelf>>,
    ) -> (Vec<ScanId>, Option<ShelfError>) {
        let taken = std::mem::take(self);
        let Some(links) = links.filter(|_| taken.on_shelf) else {
            return (taken.added, None);
        };
        let (merged, error) = match read_list(links.as_ref(), owner) {
            Ok(shelved) => (merge(&shelved, &taken.added, &taken.removed), None),
            Err(e) => (taken.added, Some(e)),
        };
        let error = error.or(links.commit(&[], &[owner]).err());
        (merged, error)
    }

    /// All of them, sorted, left in place: the shelved list (if any) merged with the
    /// changes since. When the shelved list cannot be read, the changes alone and
    /// the error.
    pub fn list(
        &self,
        owner: ScanId,
        links: Option<&dyn Shelf>,
    ) -> (Vec<ScanId>, Option<ShelfError>) {
        let Some(links) = links.filter(|_| self.on_shelf) else {
            return (self.added.clone(), None);
        };
        match read_list(links, owner) {
            Ok(shelved) => (merge(&shelved, &self.added, &self.removed), None),
            Err(e) => (self.added.clone(), Some(e)),
        }
    }

    /// Writes the list with the changes merged to `links`; the changes leave
    /// memory. On an error nothing changes (the changes stay, to be tried later).
    pub fn flush(&mut self, owner: ScanId, links: &mut Box<dyn Shelf>) -> Result<(), ShelfError> {
        let shelved = if self.on_shelf {
            read_list(links.as_ref(), owner)?
        } else {
            Vec::new()
        };
        let merged = merge(&shelved, &self.added, &self.removed);
        links.commit(&[(owner, pack_ids(&merged))], &[])?;
        self.count = merged.len();
        self.added = Vec::new();
        self.removed = Vec::new();
        self.on_shelf = true;
        Ok(())
    }

    pub fn heap_bytes(&self) -> usize {
        (self.added.capacity() + self.removed.capacity()) * std::mem::size_of::<ScanId>()
    }
}

/// The list of `owner` on `links` (empty when it holds none).
fn read_list(links: &dyn Shelf, owner: ScanId) -> Result<Vec<ScanId>, ShelfError> {
    match links.get(&[owner]).into_iter().next() {
        Some(Ok(Some(bytes))) => unpack_ids(&bytes)
            .ok_or_else(|| ShelfError(format!("the dependents of scan {owner} do not decode"))),
        Some(Ok(None)) | None => Ok(Vec::new()),
        Some(Err(e)) => Err(e),
    }
}

/// `base` with `added` and without `removed` (all sorted), sorted and unique.
fn merge(base: &[ScanId], added: &[ScanId], removed: &[ScanId]) -> Vec<ScanId> {
    let mut out: Vec<ScanId> = base
        .iter()
        .copied()
        .filter(|id| removed.binary_search(id).is_err())
        .chain(added.iter().copied())
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

/// Sorted ids as LEB128 varints of their differences (the first from 0), then a
/// CRC-32 of those bytes.
fn pack_ids(sorted: &[ScanId]) -> Vec<u8> {
    let mut out = Vec::with_capacity(sorted.len() * 2 + 4);
    let mut previous = 0u64;
    for &id in sorted {
        let mut v = id.wrapping_sub(previous);
        previous = id;
        loop {
            let byte = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                out.push(byte);
                break;
            }
            out.push(byte | 0x80);
        }
    }
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

/// The ids of a packed list; `None` when it is damaged.
fn unpack_ids(bytes: &[u8]) -> Option<Vec<ScanId>> {
    let (body, crc) = bytes.split_at(bytes.len().checked_sub(4)?);
    if crc32fast::hash(body) != u32::from_le_bytes(crc.try_into().ok()?) {
        return None;
    }
    let mut ids = Vec::with_capacity(body.len() / 2);
    let (mut previous, mut v, mut shift) = (0u64, 0u64, 0u32);
    for &byte in body {
        if shift >= 64 {
            return None;
        }
        v |= u64::from(byte & 0x7f) << shift;
        shift += 7;
        if byte & 0x80 == 0 {
            previous = previous.wrapping_add(v);
            ids.push(previous);
            (v, shift) = (0, 0);
        }
    }
    (shift == 0).then_some(ids)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

    use std::collections::BTreeSet;

    use proptest::prelude::*;

    use super::*;
    use crate::coverage::MemoryShelf;

    proptest! {
        /// With or without a links shelf, the dependents taken are exactly the set
        /// built by the same inserts and removes, whenever the flushes come.
        #[test]
        fn dependents_are_the_set_they_were_given(
            ops in prop::collection::vec((any::<bool>(), 0u64..400), 1..1500),
            flush_every in 1usize..300,
        ) {
            let mut links: Box<dyn Shelf> = Box::new(MemoryShelf::default());
            let (mut kept, mut shelved) = (Dependents::default(), Dependents::default());
            let mut truth = BTreeSet::new();
            for (k, (add, id)) in ops.into_iter().enumerate() {
                if add && !truth.contains(&id) {
                    truth.insert(id);
                    kept.insert(id);
                    shelved.insert(id);
                } else if !add && truth.contains(&id) {
                    truth.remove(&id);
                    kept.remove(id);
                    shelved.remove(id);
                }
                if k % flush_every == 0 {
                    shelved.flush(7, &mut links).unwrap();
                }
                prop_assert_eq!(kept.len(), truth.len());
                prop_assert_eq!(shelved.len(), truth.len());
            }
            let want: Vec<ScanId> = truth.into_iter().collect();
            prop_assert_eq!(shelved.list(7, Some(links.as_ref())).0, want.clone());
            prop_assert_eq!(kept.list(7, None).0, want.clone());
            prop_assert_eq!(kept.take(7, None).0, want.clone());
            let (got, error) = shelved.take(7, Some(&mut links));
            prop_assert!(error.is_none());
            prop_assert_eq!(got, want);
            prop_assert_eq!(shelved.len(), 0);
            prop_assert!(links.get(&[7])[0].as_ref().unwrap().is_none(), "the list left the shelf");
        }
    }

    #[test]
    fn packed_lists_round_trip_and_refuse_damage() {
        let ids = vec![0, 1, 2, 300, 70_000, u64::MAX - 1, u64::MAX];
        let packed = pack_ids(&ids);
        assert_eq!(unpack_ids(&packed), Some(ids));
        assert_eq!(unpack_ids(&pack_ids(&[])), Some(vec![]));
        let mut damaged = packed.clone();
        damaged[2] ^= 1;
        assert_eq!(unpack_ids(&damaged), None);
        assert_eq!(unpack_ids(&packed[..3]), None);
        // Ten thousand neighbouring ids take about a byte each.
        let dense: Vec<ScanId> = (5_000..15_000).collect();
        assert!(pack_ids(&dense).len() < 10_010);
    }
}
