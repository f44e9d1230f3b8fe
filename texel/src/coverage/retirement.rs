//! The retirement index: world surface cells and the served scans that offer each,
//! updated one `add` or `revise` at a time with a bounded number of redundancy
//! tests. Invariant: every retired scan has, for each cell it covers, a served
//! witness whose offer dominates its own there (`docs/model.md`, "Retirement").
//! A retired scan keeps its offers packed (`offers.rs`), and with shedding on not
//! its signature: a pose revision loads the signature again from wherever its
//! caller keeps the scan. With a shelf (`shelf.rs`), a retired scan leaves memory
//! altogether between the calls that need it.

use std::collections::{HashMap, HashSet};

use super::links::Dependents;
use super::offers::{CellKey, Offer, Offers, moved_offers, offers_of};
use super::shelf::{Shelf, ShelvedEntry};
use super::{CoverageConfig, MIN_RANGE_M, ScanCoverage};
use crate::model::ScanId;
use crate::pose::Pose;

/// Which scans an `add` or `revise` call retired and which it served again.
/// A scan added and retired in the same call is in `retired`; a scan added and
/// served is in neither (serving is what an added scan does by default).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Changes {
    pub retired: Vec<ScanId>,
    pub restored: Vec<ScanId>,
}

/// What the index keeps of one scan: about 100 bytes and its packed offers while
/// retired, its open offers and signature while served.
#[derive(Debug, Clone)]
struct Entry {
    /// `None` once shed (a retired scan, with shedding on) until a revision loads it.
    coverage: Option<Box<ScanCoverage>>,
    /// The pose the offers were computed at.
    world_from_scan: Pose,
    /// The scan's offers at its current pose, sorted by cell: packed while retired.
    offers: Offers,
    score: f64,
    served: bool,
    /// Retired: the served scans whose offers dominate this one's.
    witnesses: Box<[ScanId]>,
    /// Served: the retired scans that name this one as a witness.
    dependents: Dependents,
}

/// What the index has decided since it was made, by cause: where a long session's
/// served set grows from.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RetirementCounts {
    /// New scans served: some cell had no dominating served offer among its candidates.
    pub added_served: u64,
    /// New scans retired on arrival.
    pub added_retired: u64,
    /// Served scans retired later, made redundant by newer ones.
    pub retired_later: u64,
    /// Retired scans served again after a test found no witness for some cell.
    pub restored_tested: u64,
    /// Retired scans served again untested: the call's tests were spent.
    pub restored_unexamined: u64,
    /// Retired scans served again because a revision's offers were approximate.
    pub restored_approximate: u64,
    /// Retired scans kept retired by their own witnesses after a revision.
    pub revalidated: u64,
    /// Retired scans served again because the shelf could not give them back.
    pub restored_unreadable: u64,
    /// Shelf operations that failed (what could not be shelved stays in memory).
    pub shelf_errors: u64,
}

/// The incremental retirement index. Holds only ids, poses' effects (offers) and
/// coverage signatures; never a scan.
#[derive(Debug, Default)]
pub struct Retirement {
    config: CoverageConfig,
    /// Served scans, and retired scans not on a shelf (all of them without one).
    scans: HashMap<ScanId, Entry>,
    /// Served scans offering each cell with their offer's strength, in arrival
    /// order or strongest first (`strongest_candidates_first`): a witness is looked
    /// for among the first `max_candidates_per_cell`.
    cells: HashMap<CellKey, Vec<(ScanId, f32)>>,
    served: usize,
    counts: RetirementCounts,
    /// Drop the signatures of retired scans (see [`Retirement::shed_retired_signatures`]).
    shed_retired: bool,
    /// Where retired scans wait between the calls that need them.
    shelf: Option<ShelfSlot>,
}

/// A shelf and what the index knows of it without asking it.
struct ShelfSlot {
    shelf: Box<dyn Shelf>,
    /// Served scans' lists of dependents.
    links: Box<dyn Shelf>,
    /// Served scans whose dependents' changes are due to be written to `links`.
    flush_due: Vec<ScanId>,
    /// Entries on it.
    len: usize,
    /// Scans in memory for the current call (loaded, added or retired in it): settled
    /// at its end. Those a failed commit left in memory stay here to try again.
    touched: Vec<ScanId>,
    /// Which of them are (still) on the shelf too.
    loaded: HashSet<ScanId>,
    /// Scans the shelf could not give back: forgotten at the end of the call.
    lost: Vec<ScanId>,
}

impl std::fmt::Debug for ShelfSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShelfSlot")
            .field("len", &self.len)
            .field("touched", &self.touched.len())
            .finish_non_exhaustive()
    }
}

/// The redundancy tests left in one call.
/// The work left in one call: redundancy tests (a search among a cell's candidates
/// for each cell) and revalidations (a scan's own witnesses only, at most a
/// `max_candidates_per_cell`-th of a test's comparisons).
struct Budget {
    tests: usize,
    revalidations: usize,
}

/// Revalidations a call may make per redundancy test it may make.
const REVALIDATIONS_PER_TEST: usize = 16;

impl Budget {
    fn new(config: &CoverageConfig) -> Self {
        let tests = config.max_checks_per_call.max(1);
        Self {
            tests,
            revalidations: tests.saturating_mul(REVALIDATIONS_PER_TEST),
        }
    }

    fn take(&mut self) -> bool {
        if self.tests == 0 {
            return false;
        }
        self.tests -= 1;
        true
    }

    fn take_revalidation(&mut self) -> bool {
        if self.revalidations == 0 {
            return false;
        }
        self.revalidations -= 1;
        true
    }
}

impl Retirement {
    pub fn new(config: CoverageConfig) -> Self {
        Self {
            config,
            ..Self::default()
        }
    }

    pub fn config(&self) -> &CoverageConfig {
        &self.config
    }

    /// With `on`, a scan keeps its signature only while served: retired scans (most
    /// of a long session's) hold their offers and links alone, and a revision of a
    /// scan without its signature asks [`Self::revise_with`]'s loader for it. Off by
    /// default: [`Self::revise`] has no loader.
    pub fn shed_retired_signatures(&mut self, on: bool) {
        self.shed_retired = on;
        if on {
            for id in self.retired_here() {
                self.shed(id);
            }
        }
    }

    /// Whether scan `id` holds its signature (false for an unknown id).
    pub fn holds_signature(&self, id: ScanId) -> bool {
        self.scans.get(&id).is_some_and(|e| e.coverage.is_some())
    }

    /// Adds scan `id` at `world_from_scan`: it is retired if the served scans make it
    /// redundant (a scan that covers nothing always is); otherwise it is served and
    /// the served scans sharing its cells that it makes redundant are retired,
    /// least reliable first. An id already present is treated as a pose revision.
    pub fn add(&mut self, id: ScanId, coverage: ScanCoverage, world_from_scan: &Pose) -> Changes {
        if self.scans.contains_key(&id) || self.shelved_entry(id).is_some() {
            return self.revise(id, world_from_scan);
        }
        let mut budget = Budget::new(&self.config);
        let offers = self.offers(&coverage, world_from_scan);
        let score = coverage.score();
        self.scans.insert(
            id,
            Entry {
                coverage: Some(Box::new(coverage)),
                world_from_scan: *world_from_scan,
                offers: Offers::Open(offers),
                score,
                served: false,
                witnesses: Box::default(),
                dependents: Dependents::default(),
            },
        );
        self.touch(id);
        let mut log = Log::default();
        log.note(id, true);
        let witnesses = if self.config.enabled {
            self.witnesses_of(id, &mut budget)
        } else {
            None
        };
        match witnesses {
            Some(witnesses) => {
                self.counts.added_retired += 1;
                self.link(id, witnesses);
                self.shed(id);
            }
            None => {
                self.counts.added_served += 1;
                self.serve(id);
                self.retire_neighbours(id, &mut budget, &mut log);
            }
        }
        self.finish(log)
    }

    /// The net changes of a call; then the retired scans it touched go (back) to the
    /// shelf.
    fn finish(&mut self, log: Log) -> Changes {
        let changes = log.finish(self);
        self.settle();
        changes
    }

    /// Moves scan `id` to `world_from_scan`: the scans that named it as a witness
    /// keep their witnesses where those still dominate them at their current offers,
    /// and are tested again otherwise (served again when no longer redundant, or
    /// when the budget runs out); then the scan itself (a retired one first against
    /// its own witnesses; retired when redundant at its new place, served again when
    /// it no longer is), then the served scans around it. An unknown id changes
    /// nothing.
    pub fn revise(&mut self, id: ScanId, world_from_scan: &Pose) -> Changes {
        self.revise_with(id, world_from_scan, || None)
    }

    /// [`Self::revise`] for an index that sheds signatures: `load` gives scan `id`'s
    /// signature when the index no longer holds it (it is called at most once, and
    /// only then). Without one (the scan could not be read back), the offers are
    /// moved rigidly with the scan and the scan is served again: serving a scan
    /// that might be redundant costs memory, retiring one that might not costs
    /// surfaces.
    pub fn revise_with(
        &mut self,
        id: ScanId,
        world_from_scan: &Pose,
        load: impl FnOnce() -> Option<ScanCoverage>,
    ) -> Changes {
        let mut log = Log::default();
        self.load(&[id], &mut log);
        self.revise_logged(id, world_from_scan, load, &mut log);
        self.finish(log)
    }

    fn revise_logged(
        &mut self,
        id: ScanId,
        world_from_scan: &Pose,
        load: impl FnOnce() -> Option<ScanCoverage>,
        log: &mut Log,
    ) {
        let mut budget = Budget::new(&self.config);
        let Some(entry) = self.scans.get(&id) else {
            return;
        };
        let served = entry.served;
        let (offers, loaded, exact) = match &entry.coverage {
            Some(c) => (self.offers(c, world_from_scan), None, true),
            None => match load() {
                Some(c) => (self.offers(&c, world_from_scan), Some(Box::new(c)), true),
                None => (
                    moved_offers(
                        &entry.offers.view(),
                        &entry.world_from_scan,
                        world_from_scan,
                        self.config.cell_size_m(),
                    ),
                    None,
                    false,
                ),
            },
        };
        log.note(id, served);
        if served {
            self.unindex(id);
        }
        if let Some(e) = self.scans.get_mut(&id) {
            e.offers = Offers::Open(offers);
            e.world_from_scan = *world_from_scan;
            if loaded.is_some() {
                e.coverage = loaded;
            }
        }
        if !exact {
            // Approximate offers retire nothing, this scan least of all.
            if served {
                self.index(id);
                let dependents = self.take_dependents(id, log);
                self.recheck_all(&dependents, &mut budget, log);
            } else {
                self.counts.restored_approximate += 1;
                self.unlink(id);
                self.serve(id);
            }
            return;
        }
        if served {
            self.index(id);
            let dependents = self.take_dependents(id, log);
            self.revalidate_all(&dependents, &mut budget, log);
            if let Some(witnesses) = self.redundant_served(id, &mut budget) {
                self.retire(id, witnesses, &mut budget, log);
            } else {
                self.retire_neighbours(id, &mut budget, log);
            }
        } else if let Some(witnesses) = self.still_witnessed(id, &mut budget) {
            // Its witnesses still stand in for it where it moved to.
            self.counts.revalidated += 1;
            self.unlink(id);
            self.link(id, witnesses);
        } else {
            self.unlink(id);
            if self.recheck(id, &mut budget, log) {
                self.retire_neighbours(id, &mut budget, log);
            }
        }
        if self.is_retired_here(id) {
            self.shed(id);
        }
    }

    /// Whether scan `id` is retired (false for an unknown id).
    pub fn is_retired(&self, id: ScanId) -> bool {
        match self.scans.get(&id) {
            Some(e) => !e.served,
            None => self.shelved_entry(id).is_some(),
        }
    }

    /// The retired scans held in memory.
    fn retired_here(&self) -> Vec<ScanId> {
        self.scans
            .iter()
            .filter(|(_, e)| !e.served)
            .map(|(id, _)| *id)
            .collect()
    }

    /// Whether scan `id` is in memory and retired.
    fn is_retired_here(&self, id: ScanId) -> bool {
        self.scans.get(&id).is_some_and(|e| !e.served)
    }

    /// Keeps retired scans on `shelf` between the calls that need them, and the
    /// served scans' lists of dependents on `links` (`links.rs`), and sheds
    /// retired scans' signatures: memory then holds the served scans and the recent
    /// changes of their links. The retired scans held now go to the shelf at once.
    pub fn set_shelf(&mut self, shelf: Box<dyn Shelf>, links: Box<dyn Shelf>) {
        self.shed_retired_signatures(true);
        let retired = self.retired_here();
        self.shelf = Some(ShelfSlot {
            shelf,
            links,
            flush_due: Vec::new(),
            len: 0,
            touched: retired,
            loaded: HashSet::new(),
            lost: Vec::new(),
        });
        self.settle();
    }

    /// The number of retired scans on the shelf.
    pub fn shelved(&self) -> usize {
        self.shelf.as_ref().map_or(0, |s| s.len)
    }

    /// Notes that scan `id` is in memory for this call, to be settled at its end.
    fn touch(&mut self, id: ScanId) {
        if let Some(slot) = self.shelf.as_mut() {
            slot.touched.push(id);
        }
    }

    /// Scan `id`'s entry on the shelf, read without loading it (`None` when it is
    /// not there, or not readable).
    fn shelved_entry(&self, id: ScanId) -> Option<ShelvedEntry> {
        let slot = self.shelf.as_ref()?;
        let bytes = slot.shelf.get(&[id]).into_iter().next()?.ok()??;
        ShelvedEntry::from_bytes(&bytes).ok()
    }

    /// Brings the shelved scans among `ids` into memory for this call. A scan the
    /// shelf cannot give back is forgotten and reported served again: the index
    /// cannot judge it, and serving a scan costs memory where retiring one on a
    /// guess could cost surfaces.
    fn load(&mut self, ids: &[ScanId], log: &mut Log) {
        let Some(slot) = self.shelf.as_mut() else {
            return;
        };
        let wanted: Vec<ScanId> = ids
            .iter()
            .copied()
            .filter(|id| !self.scans.contains_key(id))
            .collect();
        if wanted.is_empty() {
            return;
        }
        let found = slot.shelf.get(&wanted);
        for (id, bytes) in wanted.into_iter().zip(found) {
            let entry = match bytes {
                Ok(Some(bytes)) => ShelvedEntry::from_bytes(&bytes),
                Ok(None) => continue,
                Err(e) => Err(e),
            };
            match entry {
                Ok(e) => {
                    self.scans.insert(
                        id,
                        Entry {
                            coverage: None,
                            world_from_scan: e.world_from_scan,
                            offers: Offers::Packed(e.packed_offers),
                            score: e.score,
                            served: false,
                            witnesses: e.witnesses,
                            dependents: Dependents::default(),
                        },
                    );
                    slot.touched.push(id);
                    slot.loaded.insert(id);
                }
                Err(_) => {
                    self.counts.shelf_errors += 1;
                    self.counts.restored_unreadable += 1;
                    slot.lost.push(id);
                    log.note(id, false);
                }
            }
        }
    }

    /// The end of a call: the retired scans it touched go (back) to the shelf and
    /// leave memory, the ones it served again leave the shelf, in one commit. After
    /// a failed commit they stay in memory (nothing is lost) and are tried again at
    /// the end of the next call.
    fn settle(&mut self) {
        let Some(slot) = self.shelf.as_mut() else {
            return;
        };
        for owner in std::mem::take(&mut slot.flush_due) {
            if let Some(e) = self.scans.get_mut(&owner).filter(|e| e.served)
                && e.dependents.flush_due()
                && e.dependents.flush(owner, &mut slot.links).is_err()
            {
                self.counts.shelf_errors += 1;
            }
        }
        slot.touched.sort_unstable();
        slot.touched.dedup();
        let mut puts = Vec::new();
        let mut removes: Vec<ScanId> = slot.lost.clone();
        for &id in &slot.touched {
            match self.scans.get_mut(&id) {
                Some(e) if !e.served => {
                    e.offers.pack();
                    if let Offers::Packed(packed) = &e.offers {
                        let shelved = ShelvedEntry {
                            world_from_scan: e.world_from_scan,
                            score: e.score,
                            witnesses: e.witnesses.clone(),
                            packed_offers: packed.clone(),
                        };
                        puts.push((id, shelved.to_bytes()));
                    }
                }
                _ => {
                    if slot.loaded.contains(&id) {
                        removes.push(id);
                    }
                }
            }
        }
        if puts.is_empty() && removes.is_empty() {
            slot.touched.clear();
            return;
        }
        if slot.shelf.commit(&puts, &removes).is_err() {
            self.counts.shelf_errors += 1;
            return;
        }
        let added = puts
            .iter()
            .filter(|(id, _)| !slot.loaded.contains(id))
            .count();
        slot.len = (slot.len + added).saturating_sub(removes.len());
        for (id, _) in &puts {
            self.scans.remove(id);
        }
        slot.touched.clear();
        slot.loaded.clear();
        slot.lost.clear();
    }

    /// What the index decided so far, by cause.
    pub fn counts(&self) -> RetirementCounts {
        self.counts
    }

    /// The number of served scans.
    pub fn served(&self) -> usize {
        self.served
    }

    /// The number of retired scans.
    pub fn retired(&self) -> usize {
        let in_memory = self.scans.len() - self.served;
        match &self.shelf {
            // Scans a failed commit left in memory that are also on the shelf count once.
            Some(slot) => in_memory + slot.len - slot.loaded.len(),
            None => in_memory,
        }
    }

    /// The cells scan `id` covers at its current pose (empty for an unknown id).
    pub fn cells_of(&self, id: ScanId) -> Vec<[i64; 3]> {
        match self.scans.get(&id) {
            Some(_) => self.cells_here(id),
            None => self
                .shelved_entry(id)
                .map(|e| {
                    Offers::Packed(e.packed_offers)
                        .view()
                        .iter()
                        .map(|(k, _)| *k)
                        .collect()
                })
                .unwrap_or_default(),
        }
    }

    /// The cells of scan `id` held in memory.
    fn cells_here(&self, id: ScanId) -> Vec<[i64; 3]> {
        self.scans
            .get(&id)
            .map(|e| e.offers.view().iter().map(|(k, _)| *k).collect())
            .unwrap_or_default()
    }

    /// The served witnesses of retired scan `id` (empty when served or unknown).
    pub fn witnesses_of_retired(&self, id: ScanId) -> Vec<ScanId> {
        match self.scans.get(&id) {
            Some(e) => e.witnesses.to_vec(),
            None => self
                .shelved_entry(id)
                .map(|e| e.witnesses.to_vec())
                .unwrap_or_default(),
        }
    }

    /// Bytes the index holds on the heap (approximate: tables at their capacity).
    pub fn heap_bytes(&self) -> usize {
        let entries: usize = self
            .scans
            .values()
            .map(|e| {
                e.coverage
                    .as_ref()
                    .map_or(0, |c| std::mem::size_of::<ScanCoverage>() + c.heap_bytes())
                    + e.offers.heap_bytes()
                    + e.witnesses.len() * std::mem::size_of::<ScanId>()
                    + e.dependents.heap_bytes()
            })
            .sum();
        let cells: usize = self
            .cells
            .values()
            .map(|v| v.capacity() * std::mem::size_of::<(ScanId, f32)>())
            .sum();
        entries
            + self.shelf.as_ref().map_or(0, |s| {
                s.shelf.heap_bytes()
                    + (s.touched.capacity() + s.lost.capacity() + s.loaded.capacity())
                        * std::mem::size_of::<ScanId>()
            })
            + self.scans.capacity() * (std::mem::size_of::<(ScanId, Entry)>() + 8)
            + cells
            + self.cells.capacity() * (std::mem::size_of::<(CellKey, Vec<(ScanId, f32)>)>() + 8)
    }

    /// The offers of a signature placed at `world_from_scan`, one per cell it
    /// reaches, sorted by cell.
    fn offers(&self, coverage: &ScanCoverage, world_from_scan: &Pose) -> Vec<(CellKey, Offer)> {
        offers_of(coverage, world_from_scan, self.config.cell_size_m())
    }

    /// Whether offer `t` stands in for offer `s`: acquisition directions within the
    /// angular tolerance, and `t`'s normal accuracy times its worst range factor
    /// against `s` (`min(1, r_s / r_t)^gamma`) within the margin of `s`'s accuracy.
    fn dominates(&self, t: &Offer, s: &Offer) -> bool {
        if t.direction().dot(&s.direction()) < self.config.cos_tolerance() {
            return false;
        }
        let ratio = s.range_m() / t.range_m().max(MIN_RANGE_M);
        let range_factor = ratio.clamp(0.0, 1.0).powf(self.config.gamma());
        t.normal_accuracy() * range_factor >= s.normal_accuracy() - self.config.margin()
    }

    /// The served scans (other than `id`) whose offers dominate every offer of
    /// `id`, one per cell, or `None` when some cell has none (or the budget is
    /// spent). Witnesses already chosen are tried first, so few are named.
    fn witnesses_of(&self, id: ScanId, budget: &mut Budget) -> Option<Vec<ScanId>> {
        let entry = self.scans.get(&id)?;
        if !budget.take() {
            return None;
        }
        let mut witnesses: Vec<ScanId> = Vec::new();
        for (key, offer) in entry.offers.view().iter() {
            let known = witnesses.iter().copied();
            let others = self
                .cells
                .get(key)
                .into_iter()
                .flatten()
                .map(|&(t, _)| t)
                .filter(|&t| t != id)
                .take(self.config.max_candidates_per_cell.max(1));
            let found = known.chain(others).find(|&t| {
                self.offer_of(t, key)
                    .is_some_and(|o| self.dominates(&o, offer))
            });
            match found {
                Some(t) if !witnesses.contains(&t) => witnesses.push(t),
                Some(_) => {}
                None => return None,
            }
        }
        Some(witnesses)
    }

    /// Witnesses of served scan `id` if it is redundant and retiring it would not
    /// send back more unexamined dependents than the budget can test.
    fn redundant_served(&self, id: ScanId, budget: &mut Budget) -> Option<Vec<ScanId>> {
        if !self.config.enabled {
            return None;
        }
        let dependents = self.scans.get(&id).map_or(0, |e| e.dependents.len());
        if dependents >= budget.tests {
            return None;
        }
        self.witnesses_of(id, budget)
    }

    /// The offer of served scan `t` at `key`.
    fn offer_of(&self, t: ScanId, key: &CellKey) -> Option<Offer> {
        self.scans.get(&t).filter(|e| e.served)?.offers.get(key)
    }

    /// Retires the served scans sharing `id`'s cells that are now redundant, least
    /// reliable first, within the budget.
    fn retire_neighbours(&mut self, id: ScanId, budget: &mut Budget, log: &mut Log) {
        if !self.config.enabled {
            return;
        }
        let mut neighbours: Vec<ScanId> = self
            .cells_here(id)
            .iter()
            .filter_map(|k| self.cells.get(k))
            .flatten()
            .map(|&(n, _)| n)
            .filter(|&n| n != id)
            .collect::<HashSet<_>>()
            .into_iter()
            .collect();
        let score = |n: &ScanId| self.scans.get(n).map_or(0.0, |e| e.score);
        neighbours.sort_by(|a, b| score(a).total_cmp(&score(b)).then(a.cmp(b)));
        for n in neighbours {
            if budget.tests == 0 {
                break;
            }
            if !self.scans.get(&n).is_some_and(|e| e.served) {
                continue;
            }
            if let Some(witnesses) = self.redundant_served(n, budget) {
                log.note(n, true);
                self.retire(n, witnesses, budget, log);
            }
        }
    }

    /// Retires served scan `id` with its witnesses; the scans that named it as a
    /// witness are tested again.
    fn retire(&mut self, id: ScanId, witnesses: Vec<ScanId>, budget: &mut Budget, log: &mut Log) {
        self.touch(id);
        self.unindex(id);
        if let Some(e) = self.scans.get_mut(&id)
            && e.served
        {
            e.served = false;
            self.served = self.served.saturating_sub(1);
            self.counts.retired_later += 1;
        }
        let dependents = self.take_dependents(id, log);
        self.link(id, witnesses);
        self.shed(id);
        self.recheck_all(&dependents, budget, log);
    }

    /// Packs retired scan `id`'s offers, and drops its signature when shedding is on.
    fn shed(&mut self, id: ScanId) {
        let shed_signature = self.shed_retired;
        if let Some(e) = self.scans.get_mut(&id)
            && !e.served
        {
            e.offers.pack();
            if shed_signature {
                e.coverage = None;
            }
        }
    }

    /// Tests each retired scan of `ids` again (see [`Self::recheck`]).
    fn recheck_all(&mut self, ids: &[ScanId], budget: &mut Budget, log: &mut Log) {
        for &r in ids {
            log.note(r, false);
            self.unlink(r);
            self.recheck(r, budget, log);
        }
    }

    /// The dependents of a served scan whose offers changed (`ids`, taken from it):
    /// each keeps its witnesses when they, at their current offers, still dominate
    /// every cell of it (a revalidation: a pose revision mostly moves a witness by
    /// millimetres); the others are tested again (see [`Self::recheck_all`]).
    /// Without this, a revision of a scan with more dependents than one call's
    /// tests would serve the rest again unexamined, and a looped walk, revised at
    /// every loop closure, would keep growing its served set.
    fn revalidate_all(&mut self, ids: &[ScanId], budget: &mut Budget, log: &mut Log) {
        let mut retest = Vec::new();
        for &r in ids {
            match self.still_witnessed(r, budget) {
                Some(witnesses) => {
                    self.counts.revalidated += 1;
                    self.unlink(r);
                    self.link(r, witnesses);
                }
                None => retest.push(r),
            }
        }
        self.recheck_all(&retest, budget, log);
    }

    /// The served witnesses of retired scan `id` that still dominate each of its
    /// cells, or `None` when some cell has none among them (or the revalidation
    /// budget is spent).
    fn still_witnessed(&self, id: ScanId, budget: &mut Budget) -> Option<Vec<ScanId>> {
        let entry = self.scans.get(&id).filter(|e| !e.served)?;
        if entry.witnesses.is_empty() || !budget.take_revalidation() {
            return None;
        }
        let mut used: Vec<ScanId> = Vec::new();
        for (key, offer) in entry.offers.view().iter() {
            let t = entry.witnesses.iter().copied().find(|&t| {
                self.offer_of(t, key)
                    .is_some_and(|o| self.dominates(&o, offer))
            })?;
            if !used.contains(&t) {
                used.push(t);
            }
        }
        Some(used)
    }

    /// Tests retired, unlinked scan `id`: linked to new witnesses when still
    /// redundant, else (or when the budget is spent) served again. True when it was
    /// served again.
    fn recheck(&mut self, id: ScanId, budget: &mut Budget, log: &mut Log) -> bool {
        let unexamined = budget.tests == 0;
        let witnesses = if self.config.enabled {
            self.witnesses_of(id, budget)
        } else {
            None
        };
        match witnesses {
            Some(w) => {
                self.link(id, w);
                false
            }
            None => {
                if unexamined {
                    self.counts.restored_unexamined += 1;
                } else {
                    self.counts.restored_tested += 1;
                }
                log.note(id, false);
                self.serve(id);
                true
            }
        }
    }

    /// Marks `id` served and puts it in its cells.
    fn serve(&mut self, id: ScanId) {
        if let Some(e) = self.scans.get_mut(&id) {
            if !e.served {
                e.served = true;
                self.served += 1;
            }
            e.offers.open();
            e.witnesses = Box::default();
        }
        self.index(id);
    }

    /// Records `witnesses` as those of retired scan `id`, both ways.
    fn link(&mut self, id: ScanId, witnesses: Vec<ScanId>) {
        for w in &witnesses {
            if let Some(e) = self.scans.get_mut(w) {
                e.dependents.insert(id);
                if e.dependents.flush_due()
                    && let Some(slot) = self.shelf.as_mut()
                {
                    slot.flush_due.push(*w);
                }
            }
        }
        if let Some(e) = self.scans.get_mut(&id) {
            e.witnesses = witnesses.into_boxed_slice();
        }
    }

    /// Forgets the witnesses of `id`, both ways.
    fn unlink(&mut self, id: ScanId) {
        let witnesses = self
            .scans
            .get_mut(&id)
            .map(|e| std::mem::take(&mut e.witnesses))
            .unwrap_or_default();
        for w in witnesses {
            if let Some(e) = self.scans.get_mut(&w) {
                e.dependents.remove(id);
            }
        }
    }

    /// The retired scans naming `id` as a witness, unlinked from it, in id order,
    /// loaded from the shelf (those it cannot give back are left out, to be served
    /// again).
    fn take_dependents(&mut self, id: ScanId, log: &mut Log) -> Vec<ScanId> {
        let links = self.shelf.as_mut().map(|s| &mut s.links);
        let (mut d, error) = match self.scans.get_mut(&id) {
            Some(e) => e.dependents.take(id, links),
            None => (Vec::new(), None),
        };
        if error.is_some() {
            self.counts.shelf_errors += 1;
        }
        self.load(&d, log);
        d.retain(|r| self.scans.contains_key(r));
        d
    }

    /// Puts `id` in the cells of its offers, each at its strength's place.
    fn index(&mut self, id: ScanId) {
        let Some(e) = self.scans.get(&id) else {
            return;
        };
        let placed: Vec<(CellKey, f32)> = e
            .offers
            .view()
            .iter()
            .map(|(k, o)| (*k, self.strength(o)))
            .collect();
        for (k, strength) in placed {
            let list = self.cells.entry(k).or_default();
            if list.iter().any(|&(s, _)| s == id) {
                continue;
            }
            // Ties keep arrival order: the earlier scan stays the first candidate.
            let at = if self.config.strongest_candidates_first {
                list.partition_point(|&(_, st)| st >= strength)
            } else {
                list.len()
            };
            list.insert(at, (id, strength));
        }
    }

    /// How strongly an offer can stand in for others: its normal accuracy times its
    /// range confidence at its own range (`r^-gamma`), the two factors of
    /// [`Self::dominates`] that belong to the witness alone.
    fn strength(&self, o: &Offer) -> f32 {
        let range = o.range_m().max(MIN_RANGE_M);
        let s = o.normal_accuracy() * range.powf(-self.config.gamma());
        if s.is_finite() { s as f32 } else { 0.0 }
    }

    /// Takes `id` out of the cells of its offers.
    fn unindex(&mut self, id: ScanId) {
        for k in self.cells_here(id) {
            if let Some(list) = self.cells.get_mut(&k) {
                list.retain(|&(s, _)| s != id);
                if list.is_empty() {
                    self.cells.remove(&k);
                }
            }
        }
    }
}

/// The served state of every scan a call touched, before the call (`true`: served;
/// a scan added in the call counts as served before it).
#[derive(Default)]
struct Log(HashMap<ScanId, bool>);

impl Log {
    fn note(&mut self, id: ScanId, served_before: bool) {
        self.0.entry(id).or_insert(served_before);
    }

    /// The net changes of the call, in id order.
    fn finish(self, index: &Retirement) -> Changes {
        let mut changes = Changes::default();
        let mut touched: Vec<(ScanId, bool)> = self.0.into_iter().collect();
        touched.sort_unstable();
        for (id, before) in touched {
            // Every scan a call touched is in memory until the call settles: a scan
            // the shelf could not give back is not, and counts as served again.
            match (before, index.is_retired_here(id)) {
                (true, true) => changes.retired.push(id),
                (false, false) => changes.restored.push(id),
                _ => {}
            }
        }
        changes
    }
}
