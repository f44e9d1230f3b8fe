//! Which listed scans a client still lacks and which of them it has asked for: the
//! bookkeeping behind `RequestScan` (`docs/wire-protocol.md`, "Fetching scans"). It
//! follows the server's messages by id alone (no scan is decoded), so a transport can
//! keep one beside a [`Replica`](super::client::Replica) or a viewer's own model.

use std::collections::BTreeMap;

use super::Message;
use crate::model::ScanId;

/// Requests a client keeps outstanding unless told otherwise: enough to keep a
/// connection busy, far below the daemon's default limit (64).
pub const DEFAULT_MAX_IN_FLIGHT: usize = 16;

/// Where a listed scan stands for this client.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// Listed, its data not here and not asked for.
    Missing,
    Requested,
    Resident,
    /// The server said it cannot send it (until the scan is listed again).
    Unavailable,
}

#[derive(Debug, Clone, Copy)]
struct Entry {
    priority: f32,
    state: State,
}

/// The fetch bookkeeping of one connection.
#[derive(Debug, Clone, Default)]
pub struct FetchPlan {
    scans: BTreeMap<ScanId, Entry>,
    in_flight: usize,
    live: bool,
}

impl FetchPlan {
    pub fn new() -> Self {
        Self::default()
    }

    /// Follows one server message (messages that concern no scan are ignored).
    pub fn observe(&mut self, message: &Message) {
        match message {
            Message::ModelReset { .. } => {
                // The server forgets unanswered requests too.
                *self = Self::default();
            }
            Message::SnapshotComplete { .. } => self.live = true,
            Message::ScanListed { id, listing, .. } => self.listed(*id, listing.priority),
            Message::ScanAdded(scan) => self.added(scan.id),
            Message::ScanWithdrawn { id } => self.withdrawn(*id),
            Message::ScanUnavailable { id, .. } => self.unavailable(*id),
            _ => {}
        }
    }

    fn settle(&mut self, state: State) {
        if state == State::Requested {
            self.in_flight = self.in_flight.saturating_sub(1);
        }
    }

    /// A scan is listed: data held stays, a request stays outstanding, and one that
    /// was unavailable may be asked for again.
    pub fn listed(&mut self, id: ScanId, priority: f32) {
        let entry = self.scans.entry(id).or_insert(Entry {
            priority,
            state: State::Missing,
        });
        entry.priority = priority;
        if entry.state == State::Unavailable {
            entry.state = State::Missing;
        }
    }

    /// A scan's data arrived (the answer to a request, or a new scan).
    pub fn added(&mut self, id: ScanId) {
        let entry = self.scans.entry(id).or_insert(Entry {
            priority: 0.0,
            state: State::Resident,
        });
        let before = std::mem::replace(&mut entry.state, State::Resident);
        self.settle(before);
    }

    /// The scan left the served model: nothing to fetch, and no answer will come.
    pub fn withdrawn(&mut self, id: ScanId) {
        if let Some(entry) = self.scans.remove(&id) {
            self.settle(entry.state);
        }
    }

    /// The server cannot send the scan.
    pub fn unavailable(&mut self, id: ScanId) {
        if let Some(entry) = self.scans.get_mut(&id) {
            let before = entry.state;
            if before != State::Resident {
                entry.state = State::Unavailable;
            }
            self.settle(before);
        }
    }

    /// The client dropped a scan's data to stay within a budget: it can be fetched
    /// again.
    pub fn evicted(&mut self, id: ScanId) {
        if let Some(entry) = self.scans.get_mut(&id)
            && entry.state == State::Resident
        {
            entry.state = State::Missing;
        }
    }

    /// The scans to request now, counted as requested: listed, not here, not asked
    /// for, highest priority first (then lowest id), so that at most `max_in_flight`
    /// requests are outstanding.
    pub fn wanted(&mut self, max_in_flight: usize) -> Vec<ScanId> {
        let room = max_in_flight.saturating_sub(self.in_flight);
        if room == 0 {
            return Vec::new();
        }
        let mut missing: Vec<(f32, ScanId)> = self
            .scans
            .iter()
            .filter(|(_, e)| e.state == State::Missing)
            .map(|(id, e)| (e.priority, *id))
            .collect();
        let order = |a: &(f32, ScanId), b: &(f32, ScanId)| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1));
        if missing.len() > room {
            missing.select_nth_unstable_by(room, order);
            missing.truncate(room);
        }
        missing.sort_unstable_by(order);
        for (_, id) in &missing {
            if let Some(entry) = self.scans.get_mut(id) {
                entry.state = State::Requested;
            }
        }
        self.in_flight += missing.len();
        missing.into_iter().map(|(_, id)| id).collect()
    }

    /// Requests sent and not yet answered.
    pub fn in_flight(&self) -> usize {
        self.in_flight
    }

    /// Whether a request for `id` is outstanding.
    pub fn is_requested(&self, id: ScanId) -> bool {
        self.scans
            .get(&id)
            .is_some_and(|e| e.state == State::Requested)
    }

    /// Listed scans whose data is neither here nor declared unavailable.
    pub fn missing(&self) -> usize {
        self.scans
            .values()
            .filter(|e| matches!(e.state, State::Missing | State::Requested))
            .count()
    }

    /// The snapshot is complete and every listed scan is here (or unavailable).
    pub fn complete(&self) -> bool {
        self.live && self.missing() == 0
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    #[test]
    fn requests_go_by_priority_within_the_limit_and_answers_free_them() {
        let mut p = FetchPlan::new();
        for (id, priority) in [(0, 1.0), (1, 5.0), (2, 3.0), (3, 5.0), (4, -1.0)] {
            p.listed(id, priority);
        }
        p.observe(&Message::SnapshotComplete { scan_count: 5 });
        assert_eq!(p.wanted(3), vec![1, 3, 2]);
        assert_eq!((p.in_flight(), p.wanted(3)), (3, vec![]));
        p.added(3);
        p.withdrawn(1);
        assert_eq!(p.wanted(3), vec![0, 4]);
        p.unavailable(2);
        p.added(0);
        assert!(!p.complete());
        p.added(4);
        assert!(p.complete(), "the unavailable scan does not count");
        assert_eq!(p.in_flight(), 0);
        // Listed again, an unavailable scan is wanted again; a reset forgets all.
        p.listed(2, 0.0);
        assert_eq!(p.wanted(8), vec![2]);
        p.observe(&Message::ModelReset { scan_count: 0 });
        assert_eq!((p.in_flight(), p.missing(), p.complete()), (0, 0, false));
    }
}
