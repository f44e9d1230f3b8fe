//! Tables that grow with a session's frames, kept in memory a few pages at a time:
//! fixed-size records by dense index (0, 1, 2, ...), in pages of `PAGE_RECORDS`, the
//! newest page and the most recently used others in memory, the rest in a page
//! store its owner provides (the daemon: an unlinked file). Without a store every
//! page stays in memory, as a `Vec` would, less its doubling slack.
//!
//! A session's per-frame records (the registrar's scan records, the store's slots,
//! the recorded timestamps) are written once and read back rarely (a pose revision
//! of an old scan, a fetch), so paging them costs a read now and then and makes
//! their memory independent of the session's length.

use std::collections::HashMap;
use std::sync::Mutex;

/// Records a page holds.
pub const PAGE_RECORDS: usize = 1024;

/// A record of fixed byte length.
pub trait Record: Copy + Send + 'static {
    /// Bytes of the encoded form.
    const LEN: usize;
    fn encode(&self, out: &mut [u8]);
    /// The record of `bytes` (exactly `LEN` long); `None` when they are not one.
    fn decode(bytes: &[u8]) -> Option<Self>;
}

/// Why a page could not be written or read back.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("page store: {0}")]
pub struct PageError(pub String);

/// Where pages beyond memory go, by page number; each page is written whole.
pub trait PageStore: Send {
    fn write_page(&mut self, page: u64, bytes: &[u8]) -> Result<(), PageError>;
    /// The bytes last written for `page` (exactly `out.len()` of them).
    fn read_page(&self, page: u64, out: &mut [u8]) -> Result<(), PageError>;
}

struct Page<T> {
    records: Vec<T>,
    /// Changed since it was last written to the store.
    dirty: bool,
    used: u64,
}

struct State<T> {
    pages: HashMap<usize, Page<T>>,
    tick: u64,
    /// Page writes and reads that failed (a page that could not be written stays in
    /// memory; one that cannot be read back leaves its records unknown).
    errors: u64,
    store: Option<Box<dyn PageStore>>,
    max_resident_pages: usize,
    per_page: usize,
}

/// A table of `T` by dense index, paged to a [`PageStore`] beyond a number of
/// resident pages. Reads take `&self` (the pages sit behind a mutex).
pub struct PagedTable<T: Record> {
    len: usize,
    per_page: usize,
    state: Mutex<State<T>>,
}

impl<T: Record> std::fmt::Debug for PagedTable<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PagedTable")
            .field("len", &self.len)
            .finish_non_exhaustive()
    }
}

impl<T: Record> Default for PagedTable<T> {
    fn default() -> Self {
        Self::with_page_records(PAGE_RECORDS)
    }
}

impl<T: Record> PagedTable<T> {
    /// An empty table in pages of `per_page` records (at least 1): small pages for
    /// tests that page a few dozen records.
    pub fn with_page_records(per_page: usize) -> Self {
        let per_page = per_page.max(1);
        Self {
            len: 0,
            per_page,
            state: Mutex::new(State {
                pages: HashMap::new(),
                tick: 0,
                errors: 0,
                store: None,
                max_resident_pages: usize::MAX,
                per_page,
            }),
        }
    }
}

impl<T: Record> PagedTable<T> {
    /// An empty table that keeps at most `max_resident_pages` pages (at least 2) in
    /// memory and the rest in `store`.
    pub fn paged(store: Box<dyn PageStore>, max_resident_pages: usize) -> Self {
        let mut table = Self::default();
        table.page_to(store, max_resident_pages);
        table
    }

    /// Moves this table's pages beyond `max_resident_pages` to `store`, now and
    /// from now on.
    pub fn page_to(&mut self, store: Box<dyn PageStore>, max_resident_pages: usize) {
        let newest = self.newest_page();
        let state = self.state_mut();
        state.store = Some(store);
        state.max_resident_pages = max_resident_pages.max(2);
        for page in state.pages.values_mut() {
            page.dirty = true;
        }
        state.evict(newest);
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State<T>> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn state_mut(&mut self) -> &mut State<T> {
        self.state
            .get_mut()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn newest_page(&self) -> usize {
        self.len.saturating_sub(1) / self.per_page
    }

    /// The record at `index` (`None` beyond the end, or when its page cannot be read
    /// back).
    pub fn get(&self, index: usize) -> Option<T> {
        if index >= self.len {
            return None;
        }
        let (page, at) = (index / self.per_page, index % self.per_page);
        let (len, newest) = (self.len, self.newest_page());
        let mut state = self.lock();
        let record = state.resident(page, len)?.records.get(at).copied();
        state.evict(newest);
        record
    }

    /// Changes the record at `index` with `change`; false when there is none (or
    /// its page cannot be read back).
    pub fn update(&mut self, index: usize, change: impl FnOnce(&mut T)) -> bool {
        if index >= self.len {
            return false;
        }
        let (page, at) = (index / self.per_page, index % self.per_page);
        let (len, newest) = (self.len, self.newest_page());
        let state = self.state_mut();
        let Some(p) = state.resident(page, len) else {
            return false;
        };
        let Some(r) = p.records.get_mut(at) else {
            return false;
        };
        change(r);
        p.dirty = true;
        state.evict(newest);
        true
    }

    /// Appends a record; returns its index.
    pub fn push(&mut self, record: T) -> usize {
        let index = self.len;
        self.len += 1;
        let page = index / self.per_page;
        let per_page = self.per_page;
        let state = self.state_mut();
        state.tick += 1;
        let used = state.tick;
        let p = state.pages.entry(page).or_insert_with(|| Page {
            // Grown by doubling up to a page: a small table costs little.
            records: Vec::with_capacity(per_page.min(32)),
            dirty: true,
            used,
        });
        p.records.push(record);
        p.dirty = true;
        p.used = used;
        state.evict(page);
        index
    }

    /// The newest record that `matches`, searching back from the newest: for
    /// searches that usually end among the newest.
    pub fn find_from_newest(&self, mut matches: impl FnMut(&T) -> bool) -> Option<T> {
        (0..self.len)
            .rev()
            .map_while(|i| self.get(i))
            .find(|r| matches(r))
    }

    /// Every record in index order (pages read back one at a time).
    pub fn to_vec(&self) -> Vec<T> {
        (0..self.len).map_while(|i| self.get(i)).collect()
    }

    /// Heap bytes held: the resident pages.
    pub fn heap_bytes(&self) -> usize {
        let state = self.lock();
        state
            .pages
            .values()
            .map(|p| p.records.capacity() * std::mem::size_of::<T>())
            .sum::<usize>()
            + state.pages.capacity() * (std::mem::size_of::<(usize, Page<T>)>() + 1)
    }

    /// Page writes and reads that failed so far.
    pub fn errors(&self) -> u64 {
        self.lock().errors
    }

    /// Pages in memory.
    pub fn resident_pages(&self) -> usize {
        self.lock().pages.len()
    }
}

impl<T: Record> State<T> {
    /// Page `page` in memory, read back from the store if need be, marked used.
    fn resident(&mut self, page: usize, len: usize) -> Option<&mut Page<T>> {
        self.tick += 1;
        let tick = self.tick;
        if !self.pages.contains_key(&page) {
            let records = self.read(page, len)?;
            self.pages.insert(
                page,
                Page {
                    records,
                    dirty: false,
                    used: tick,
                },
            );
        }
        let p = self.pages.get_mut(&page)?;
        p.used = tick;
        Some(p)
    }

    /// Page `page` read back from the store (the last page may be partly filled).
    fn read(&mut self, page: usize, len: usize) -> Option<Vec<T>> {
        let store = self.store.as_ref()?;
        let count = len.saturating_sub(page * self.per_page).min(self.per_page);
        let mut bytes = vec![0u8; self.per_page * T::LEN];
        let decoded = store
            .read_page(page as u64, &mut bytes)
            .ok()
            .and_then(|()| {
                bytes
                    .chunks_exact(T::LEN)
                    .take(count)
                    .map(T::decode)
                    .collect::<Option<Vec<T>>>()
            });
        if decoded.is_none() {
            self.errors += 1;
        }
        let mut records = decoded?;
        records.reserve_exact(self.per_page - records.len());
        Some(records)
    }

    /// Writes the least recently used pages (never `newest`, where pushes go) to the
    /// store and drops them, while more than `max_resident_pages` are held. A page
    /// that cannot be written stays in memory: nothing is lost.
    fn evict(&mut self, newest: usize) {
        let Some(store) = self.store.as_mut() else {
            return;
        };
        if self.pages.len() <= self.max_resident_pages {
            return;
        }
        let mut order: Vec<(u64, usize)> = self
            .pages
            .iter()
            .filter(|(n, _)| **n != newest)
            .map(|(n, p)| (p.used, *n))
            .collect();
        order.sort_unstable();
        let excess = self.pages.len() - self.max_resident_pages;
        let mut dropped = 0;
        for (_, victim) in order {
            if dropped == excess {
                break;
            }
            let Some(page) = self.pages.get(&victim) else {
                continue;
            };
            if page.dirty {
                let mut bytes = vec![0u8; self.per_page * T::LEN];
                for (r, out) in page.records.iter().zip(bytes.chunks_exact_mut(T::LEN)) {
                    r.encode(out);
                }
                if store.write_page(victim as u64, &bytes).is_err() {
                    self.errors += 1;
                    continue;
                }
            }
            self.pages.remove(&victim);
            dropped += 1;
        }
    }
}

/// Pages in memory, for tests: a store that counts what it is asked.
#[derive(Debug, Default)]
pub struct MemoryPages {
    pages: HashMap<u64, Vec<u8>>,
}

impl MemoryPages {
    pub fn len(&self) -> usize {
        self.pages.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pages.is_empty()
    }
}

impl PageStore for MemoryPages {
    fn write_page(&mut self, page: u64, bytes: &[u8]) -> Result<(), PageError> {
        self.pages.insert(page, bytes.to_vec());
        Ok(())
    }

    fn read_page(&self, page: u64, out: &mut [u8]) -> Result<(), PageError> {
        let bytes = self
            .pages
            .get(&page)
            .ok_or_else(|| PageError(format!("page {page} was never written")))?;
        if bytes.len() != out.len() {
            return Err(PageError(format!("page {page}: {} bytes", bytes.len())));
        }
        out.copy_from_slice(bytes);
        Ok(())
    }
}

impl Record for u64 {
    const LEN: usize = 8;
    fn encode(&self, out: &mut [u8]) {
        out.copy_from_slice(&self.to_le_bytes());
    }
    fn decode(bytes: &[u8]) -> Option<Self> {
        Some(u64::from_le_bytes(bytes.try_into().ok()?))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// A paged table reads back exactly what a `Vec` holds, under any mix of
        /// pushes, changes and reads, with at most its page budget in memory.
        #[test]
        fn a_paged_table_behaves_as_a_vec(
            ops in prop::collection::vec((0u8..3, 0usize..6000, any::<u64>()), 1..3000),
            max_pages in 2usize..5,
            per_page in prop_oneof![Just(PAGE_RECORDS), 1usize..40],
        ) {
            let mut table: PagedTable<u64> = PagedTable::with_page_records(per_page);
            table.page_to(Box::new(MemoryPages::default()), max_pages);
            let mut vec: Vec<u64> = Vec::new();
            for (op, at, value) in ops {
                match op {
                    0 => {
                        // Pushes come in runs, so the table spans several pages.
                        for k in 0..8 {
                            prop_assert_eq!(table.push(value.wrapping_add(k)), vec.len());
                            vec.push(value.wrapping_add(k));
                        }
                    }
                    1 => {
                        let changed = table.update(at, |r| *r = value);
                        prop_assert_eq!(changed, at < vec.len());
                        if let Some(r) = vec.get_mut(at) {
                            *r = value;
                        }
                    }
                    _ => prop_assert_eq!(table.get(at), vec.get(at).copied()),
                }
                prop_assert!(table.resident_pages() <= max_pages);
            }
            prop_assert_eq!(table.to_vec(), vec.clone());
            prop_assert_eq!(table.errors(), 0);
        }
    }

    #[test]
    fn a_store_that_fails_keeps_pages_in_memory_and_loses_nothing() {
        struct Failing;
        impl PageStore for Failing {
            fn write_page(&mut self, page: u64, _: &[u8]) -> Result<(), PageError> {
                Err(PageError(format!("page {page}: disk full")))
            }
            fn read_page(&self, page: u64, _: &mut [u8]) -> Result<(), PageError> {
                Err(PageError(format!("page {page}: unreadable")))
            }
        }
        let mut table: PagedTable<u64> = PagedTable::paged(Box::new(Failing), 2);
        for i in 0..(5 * PAGE_RECORDS as u64) {
            table.push(i);
        }
        assert_eq!(table.resident_pages(), 5);
        assert!(table.errors() > 0);
        assert_eq!(
            table.to_vec(),
            (0..5 * PAGE_RECORDS as u64).collect::<Vec<_>>()
        );
    }

    #[test]
    fn unpaged_tables_hold_everything_and_paged_ones_a_bounded_share() {
        let mut kept: PagedTable<u64> = PagedTable::default();
        let mut paged: PagedTable<u64> = PagedTable::paged(Box::new(MemoryPages::default()), 3);
        for i in 0..(40 * PAGE_RECORDS as u64) {
            kept.push(i);
            paged.push(i);
        }
        assert_eq!(kept.resident_pages(), 40);
        assert_eq!(paged.resident_pages(), 3);
        assert!(paged.heap_bytes() * 10 < kept.heap_bytes());
        assert_eq!(paged.get(5), Some(5));
        // Moving a grown table to a store writes out all but its budget.
        kept.page_to(Box::new(MemoryPages::default()), 4);
        assert_eq!(kept.resident_pages(), 4);
        assert_eq!(kept.to_vec(), paged.to_vec());
    }
}
