//! The tree's fields, one per level, finest first, and the paging that keeps them
//! within a memory budget: beyond it, the blocks used longest ago go to a page store
//! the owner provides (the daemon: an unlinked file) and come back before anything
//! reads or changes them. The fields grow with the ground covered (about a mebibyte
//! a metre of street at the default voxel); paged, a walk of any length holds only
//! the budget, and the tree built is the same bit for bit.
//!
//! Every read and write of a block goes through here, so each operation first names
//! the blocks it needs: fusion the blocks its samples' bands cross
//! (`Tsdf::keys_touched`), resampling the eight finer children, a tile the columns
//! it is cut or coloured from.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Mutex;

use texel::paged::PageStore;
use texel_surface::{BLOCK_BYTES, BlockKey, Sample, Tsdf};

/// Bytes of each page the fields write: one block.
pub const PAGE_BYTES: usize = BLOCK_BYTES;

/// Paging stops spilling at this share of the budget, so a model at its budget
/// spills in batches rather than a block with every scan.
const LOW_WATER_NUM: usize = 3;
const LOW_WATER_DEN: usize = 4;

/// What paging has done so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PagingCounts {
    /// Blocks out of memory now, and their bytes in the page store.
    pub blocks_out: u64,
    pub bytes_out: u64,
    /// Blocks written to the page store and read back.
    pub writes: u64,
    pub reads: u64,
    /// Writes that failed (the block stayed in memory) and reads that failed (the
    /// block's observations are lost; later scans observe it anew).
    pub errors: u64,
}

/// A block by level and key.
type LevelKey = (usize, BlockKey);

struct Pager {
    /// Behind a mutex only so a model can be shared between threads (a page store
    /// need only be `Send`); paging has `&mut` access and never waits on it.
    store: Mutex<Box<dyn PageStore>>,
    max_resident_bytes: usize,
    /// Per level, the blocks out of memory and the page each was written to.
    out: Vec<BTreeMap<BlockKey, u64>>,
    /// Blocks read back and not changed since: their page still holds them, so they
    /// leave again without a write.
    clean: HashMap<LevelKey, u64>,
    free_pages: Vec<u64>,
    next_page: u64,
    /// When each block in memory was last used (a tick per operation).
    last_used: HashMap<LevelKey, u64>,
    tick: u64,
    counts: PagingCounts,
}

/// The fields of every level, paged or not.
pub struct Fields {
    levels: Vec<Tsdf>,
    pager: Option<Pager>,
}

impl std::fmt::Debug for Fields {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Fields")
            .field("levels", &self.levels.len())
            .field("paged", &self.pager.is_some())
            .finish_non_exhaustive()
    }
}

impl Fields {
    /// Fields held wholly in memory.
    pub fn new(levels: Vec<Tsdf>) -> Self {
        Self {
            levels,
            pager: None,
        }
    }

    /// From now on, keeps the fields' blocks in memory within `max_resident_bytes`
    /// (outside a single operation's own needs), the rest in `store`.
    pub fn page_to(&mut self, store: Box<dyn PageStore>, max_resident_bytes: usize) {
        self.pager = Some(Pager {
            store: Mutex::new(store),
            max_resident_bytes,
            out: vec![BTreeMap::new(); self.levels.len()],
            clean: HashMap::new(),
            free_pages: Vec::new(),
            next_page: 0,
            last_used: HashMap::new(),
            tick: 0,
            counts: PagingCounts::default(),
        });
        self.keep_within_budget();
    }

    /// The levels as held in memory now (paged-out blocks are missing: call the
    /// paging methods first).
    pub fn levels(&self) -> &[Tsdf] {
        &self.levels
    }

    pub fn level(&self, lod: usize) -> Option<&Tsdf> {
        self.levels.get(lod)
    }

    pub fn len(&self) -> usize {
        self.levels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.levels.is_empty()
    }

    /// Replaces the finest field (before any paging).
    pub(crate) fn set_finest(&mut self, field: Tsdf) {
        if let Some(finest) = self.levels.first_mut() {
            *finest = field;
        }
    }

    /// Bytes of the blocks in memory.
    pub fn resident_bytes(&self) -> usize {
        self.levels.iter().map(Tsdf::heap_bytes).sum()
    }

    pub fn paging(&self) -> PagingCounts {
        self.pager.as_ref().map_or_else(PagingCounts::default, |p| {
            let blocks_out: usize = p.out.iter().map(BTreeMap::len).sum();
            PagingCounts {
                blocks_out: blocks_out as u64,
                bytes_out: (blocks_out * BLOCK_BYTES) as u64,
                ..p.counts
            }
        })
    }

    /// Every block of level `lod`, in memory or out of it.
    pub fn block_keys(&self, lod: usize) -> impl Iterator<Item = BlockKey> + '_ {
        let held = self.levels.get(lod).into_iter().flat_map(Tsdf::block_keys);
        let out = self
            .pager
            .as_ref()
            .and_then(|p| p.out.get(lod))
            .into_iter()
            .flat_map(|o| o.keys().copied());
        held.chain(out)
    }

    /// Fuses samples into the finest field, adding the blocks changed to `changed`.
    pub fn integrate(&mut self, samples: &[Sample], changed: &mut BTreeSet<BlockKey>) -> usize {
        self.fuse(samples, changed, Tsdf::integrate_marking)
    }

    /// Takes samples out of the finest field, adding the blocks changed to `changed`.
    pub fn remove(&mut self, samples: &[Sample], changed: &mut BTreeSet<BlockKey>) -> usize {
        self.fuse(samples, changed, Tsdf::remove_marking)
    }

    /// Runs `op` (fusion or removal) on the finest field with the blocks it reaches
    /// in memory, then marks the blocks it changed.
    fn fuse(
        &mut self,
        samples: &[Sample],
        changed: &mut BTreeSet<BlockKey>,
        op: fn(&mut Tsdf, &[Sample], &mut BTreeSet<BlockKey>) -> usize,
    ) -> usize {
        let Some(p) = self.pager.as_ref() else {
            return self
                .levels
                .first_mut()
                .map_or(0, |f| op(f, samples, changed));
        };
        // Walking the samples' bands twice costs a fusion's time again: only when
        // some block is out of memory can the walk find one to bring back.
        if p.out.first().is_some_and(|o| !o.is_empty()) {
            let mut keys = BTreeSet::new();
            if let Some(finest) = self.levels.first() {
                finest.keys_touched(samples, &mut keys);
            }
            let keys: Vec<BlockKey> = keys.into_iter().collect();
            self.page_in(0, &keys);
        }
        let mut here = BTreeSet::new();
        let updates = self
            .levels
            .first_mut()
            .map_or(0, |f| op(f, samples, &mut here));
        if let Some(p) = self.pager.as_mut() {
            for key in &here {
                p.changing(0, *key);
            }
        }
        self.used(0, here.iter().copied());
        changed.extend(here);
        updates
    }

    /// Recomputes block `key` of level `lod` (≥ 1) from the level below.
    pub fn resample(&mut self, lod: usize, key: BlockKey) {
        if lod == 0 || lod >= self.levels.len() {
            return;
        }
        let children: Vec<BlockKey> = (0..8usize)
            .map(|c| [0, 1, 2].map(|a| key[a] * 2 + ((c >> a) & 1) as i64))
            .collect();
        self.page_in(lod - 1, &children);
        // The block is recomputed whole: a copy out of memory is stale, not needed.
        if let Some(p) = self.pager.as_mut() {
            p.forget(lod, key);
        }
        let (fine, coarse) = self.levels.split_at_mut(lod);
        coarse[0].resample_block(&fine[lod - 1], key);
        self.used(lod - 1, children);
        self.used(lod, [key]);
    }

    /// Brings back every block of level `lod` over voxel columns `[lo, hi)`.
    pub fn page_in_columns(&mut self, lod: usize, lo: [i64; 2], hi: [i64; 2]) {
        let Some(p) = self.pager.as_ref() else {
            return;
        };
        let block_lo = lo.map(|i| i.div_euclid(8));
        let block_hi = hi.map(|i| i.saturating_sub(1).div_euclid(8));
        let Some(out) = p.out.get(lod) else {
            return;
        };
        let keys: Vec<BlockKey> = out
            .range([block_lo[0], i64::MIN, i64::MIN]..=[block_hi[0], i64::MAX, i64::MAX])
            .map(|(k, _)| *k)
            .filter(|k| k[1] >= block_lo[1] && k[1] <= block_hi[1])
            .collect();
        self.page_in(lod, &keys);
        // Blocks in memory over the columns count as used too, so a tile's blocks
        // are not the next to leave.
        let held: Vec<BlockKey> = self.levels[lod]
            .block_keys()
            .filter(|k| (0..2).all(|a| k[a] >= block_lo[a] && k[a] <= block_hi[a]))
            .collect();
        self.used(lod, held);
    }

    /// Pages the blocks used longest ago out while memory is over the budget, down to
    /// three quarters of it.
    pub fn keep_within_budget(&mut self) {
        let Some(p) = self.pager.as_mut() else {
            return;
        };
        let mut resident: usize = self.levels.iter().map(Tsdf::heap_bytes).sum();
        if resident <= p.max_resident_bytes {
            return;
        }
        let target = p.max_resident_bytes / LOW_WATER_DEN * LOW_WATER_NUM;
        let mut candidates: Vec<(u64, usize, BlockKey)> = self
            .levels
            .iter()
            .enumerate()
            .flat_map(|(lod, f)| f.block_keys().map(move |k| (lod, k)))
            .map(|(lod, k)| (p.last_used.get(&(lod, k)).copied().unwrap_or(0), lod, k))
            .collect();
        candidates.sort_unstable();
        for (_, lod, key) in candidates {
            if resident <= target {
                break;
            }
            let field = &mut self.levels[lod];
            let before = field.heap_bytes();
            if !p.page_out(field, lod, key) {
                // The store refuses writes: keep the rest in memory, try next time.
                break;
            }
            resident = resident.saturating_sub(before.saturating_sub(field.heap_bytes()));
        }
        let levels = &self.levels;
        p.last_used
            .retain(|(lod, k), _| levels.get(*lod).is_some_and(|f| f.has_block(*k)));
    }

    /// Brings back the listed blocks of level `lod` that are out of memory.
    fn page_in(&mut self, lod: usize, keys: &[BlockKey]) {
        let (Some(p), Some(field)) = (self.pager.as_mut(), self.levels.get_mut(lod)) else {
            return;
        };
        for key in keys {
            p.page_in(field, lod, *key);
        }
    }

    /// Marks blocks used now (paging only).
    fn used(&mut self, lod: usize, keys: impl IntoIterator<Item = BlockKey>) {
        let Some(p) = self.pager.as_mut() else {
            return;
        };
        p.tick += 1;
        for key in keys {
            p.last_used.insert((lod, key), p.tick);
        }
    }
}

impl Pager {
    /// Reads block `key` of level `lod` back if it is out. A page that cannot be read
    /// or is not a block loses the block's observations (counted).
    fn page_in(&mut self, field: &mut Tsdf, lod: usize, key: BlockKey) {
        let Some(page) = self.out.get_mut(lod).and_then(|o| o.remove(&key)) else {
            return;
        };
        let mut bytes = vec![0u8; BLOCK_BYTES];
        let store = self
            .store
            .get_mut()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let read = store
            .read_page(page, &mut bytes)
            .map_err(|e| e.to_string())
            .and_then(|()| field.insert_block(key, &bytes).map_err(|e| e.to_string()));
        match read {
            Ok(()) => {
                self.counts.reads += 1;
                self.clean.insert((lod, key), page);
            }
            Err(_) => {
                self.counts.errors += 1;
                self.free_pages.push(page);
            }
        }
    }

    /// Writes block `key` of level `lod` out (or leaves it without a write when its
    /// page still holds it) and drops it from memory; false when the store refused.
    fn page_out(&mut self, field: &mut Tsdf, lod: usize, key: BlockKey) -> bool {
        if let Some(page) = self.clean.remove(&(lod, key)) {
            field.drop_block(key);
            self.out[lod].insert(key, page);
            return true;
        }
        let Some(bytes) = field.encode_block(key) else {
            return true;
        };
        let page = self.free_pages.pop().unwrap_or_else(|| {
            self.next_page += 1;
            self.next_page - 1
        });
        let store = self
            .store
            .get_mut()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if store.write_page(page, &bytes).is_err() {
            self.counts.errors += 1;
            self.free_pages.push(page);
            return false;
        }
        self.counts.writes += 1;
        field.drop_block(key);
        self.out[lod].insert(key, page);
        true
    }

    /// Block `key` of level `lod` is about to change: a page holding its old state
    /// no longer does.
    fn changing(&mut self, lod: usize, key: BlockKey) {
        if let Some(page) = self.clean.remove(&(lod, key)) {
            self.free_pages.push(page);
        }
    }

    /// Block `key` of level `lod` is about to be recomputed whole: any copy of it,
    /// in a page or read back from one, is stale.
    fn forget(&mut self, lod: usize, key: BlockKey) {
        if let Some(page) = self.out.get_mut(lod).and_then(|o| o.remove(&key)) {
            self.free_pages.push(page);
        }
        self.changing(lod, key);
    }
}
