//! Pending handshakes: connections accepted but not yet through their hello, bounded
//! in total and per source address. A connection holds no viewer slot until its hello
//! is accepted, only one of these places; over a bound the oldest pending handshake
//! of the crowded address is closed to make room for the newcomer.
//!
//! Evicting the oldest rather than refusing the newest means a flood of silent
//! connections cannot keep anyone out by holding its places: every newcomer, a
//! token holder on the flooder's own address included, gets a place at once and keeps
//! it until that address opens `per_address` more connections, while a client sends
//! its hello right after connecting. (Protecting young handshakes from eviction and
//! refusing the newcomer instead was tried: under a flood from the same address the
//! newcomer then needed a hundred attempts where eviction lets it in at the first.)

use std::collections::{HashMap, VecDeque};
use std::net::{IpAddr, Ipv6Addr};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

use tokio_util::sync::CancellationToken;

/// The bounds on pending handshakes.
#[derive(Debug, Clone, Copy)]
pub struct PendingLimits {
    pub total: usize,
    pub per_address: usize,
}

/// Where connections come from, for the per-address bound: an IPv4 address, or the
/// /64 prefix of an IPv6 address (one host commonly holds a whole /64).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SourceKey(IpAddr);

impl SourceKey {
    pub fn of(ip: IpAddr) -> Self {
        match ip.to_canonical() {
            IpAddr::V6(v6) => {
                let prefix = u128::from(v6) & !((1u128 << 64) - 1);
                Self(IpAddr::V6(Ipv6Addr::from(prefix)))
            }
            v4 => Self(v4),
        }
    }
}

struct Entry {
    id: u64,
    since: Instant,
    evict: CancellationToken,
}

#[derive(Default)]
struct Table {
    /// Oldest first within each source.
    by_source: HashMap<SourceKey, VecDeque<Entry>>,
    total: usize,
    next_id: u64,
}

impl Table {
    fn remove(&mut self, key: SourceKey, id: u64) -> Option<Entry> {
        let queue = self.by_source.get_mut(&key)?;
        let at = queue.iter().position(|e| e.id == id)?;
        let entry = queue.remove(at);
        if queue.is_empty() {
            self.by_source.remove(&key);
        }
        self.total = self.total.saturating_sub(1);
        entry
    }
}

/// Every pending handshake, shared by the accept loop and the handshake tasks.
pub struct PendingHandshakes {
    table: Mutex<Table>,
    limits: PendingLimits,
}

/// What making room for a newcomer did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Admission {
    /// There was room.
    Admitted,
    /// The oldest pending handshake of this source was closed to make room.
    EvictedOldest(SourceKey),
}

/// A connection's pending place; dropping it (hello read, failed or timed out) frees
/// the place. `evicted` is cancelled when the place is taken away to make room.
pub struct PendingTicket {
    pending: Arc<PendingHandshakes>,
    key: SourceKey,
    id: u64,
    pub evicted: CancellationToken,
}

impl Drop for PendingTicket {
    fn drop(&mut self) {
        self.pending.lock().remove(self.key, self.id);
    }
}

impl PendingHandshakes {
    pub fn new(limits: PendingLimits) -> Arc<Self> {
        Arc::new(Self {
            table: Mutex::new(Table::default()),
            limits: PendingLimits {
                total: limits.total.max(1),
                per_address: limits.per_address.max(1),
            },
        })
    }

    fn lock(&self) -> MutexGuard<'_, Table> {
        self.table
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Handshakes pending now.
    pub fn count(&self) -> usize {
        self.lock().total
    }

    /// Handshakes pending now from `ip`'s source.
    #[cfg(test)]
    fn count_from(&self, ip: IpAddr) -> usize {
        self.lock()
            .by_source
            .get(&SourceKey::of(ip))
            .map_or(0, VecDeque::len)
    }

    /// Gives a connection from `ip`, accepted at `now`, a pending place, evicting the
    /// oldest handshake of its source when that source is at its bound, or of the
    /// source with the most pending handshakes when all places are taken.
    pub fn admit(self: &Arc<Self>, ip: IpAddr, now: Instant) -> (PendingTicket, Admission) {
        let key = SourceKey::of(ip);
        let mut table = self.lock();
        let own = table.by_source.get(&key).map_or(0, VecDeque::len);
        let victim_source = if own >= self.limits.per_address {
            Some(key)
        } else if table.total >= self.limits.total {
            // The most crowded source pays (ties: the one with the oldest handshake).
            table
                .by_source
                .iter()
                .filter_map(|(k, q)| q.front().map(|e| (*k, q.len(), e.since)))
                .max_by(|a, b| a.1.cmp(&b.1).then(b.2.cmp(&a.2)))
                .map(|(k, _, _)| k)
        } else {
            None
        };
        let mut admission = Admission::Admitted;
        if let Some(source) = victim_source {
            let oldest = table
                .by_source
                .get(&source)
                .and_then(VecDeque::front)
                .map(|e| e.id);
            if let Some(entry) = oldest.and_then(|id| table.remove(source, id)) {
                entry.evict.cancel();
                admission = Admission::EvictedOldest(source);
            }
        }
        let id = table.next_id;
        table.next_id = table.next_id.wrapping_add(1);
        let evicted = CancellationToken::new();
        table.by_source.entry(key).or_default().push_back(Entry {
            id,
            since: now,
            evict: evicted.clone(),
        });
        table.total += 1;
        drop(table);
        (
            PendingTicket {
                pending: Arc::clone(self),
                key,
                id,
                evicted,
            },
            admission,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pending(total: usize, per_address: usize) -> Arc<PendingHandshakes> {
        PendingHandshakes::new(PendingLimits { total, per_address })
    }

    fn ip(s: &str) -> IpAddr {
        s.parse()
            .unwrap_or(IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED))
    }

    #[test]
    fn a_crowded_address_loses_its_oldest_handshake_and_no_other() {
        let p = pending(8, 2);
        let t0 = Instant::now();
        let other = p.admit(ip("10.0.0.2"), t0);
        let first = p.admit(ip("10.0.0.1"), t0);
        let second = p.admit(ip("10.0.0.1"), t0);
        assert_eq!(second.1, Admission::Admitted);
        let third = p.admit(ip("10.0.0.1"), t0);
        assert_eq!(
            third.1,
            Admission::EvictedOldest(SourceKey::of(ip("10.0.0.1")))
        );
        assert!(first.0.evicted.is_cancelled());
        assert!(!second.0.evicted.is_cancelled());
        assert!(!other.0.evicted.is_cancelled());
        assert_eq!(p.count_from(ip("10.0.0.1")), 2);
        assert_eq!(p.count(), 3);
        // An evicted ticket's drop frees nothing twice; the others free their places.
        drop(first);
        assert_eq!(p.count(), 3);
        drop((second, third));
        assert_eq!(p.count(), 1);
        drop(other);
        assert_eq!(p.count(), 0);
    }

    #[test]
    fn a_full_table_evicts_from_the_most_crowded_address() {
        let p = pending(4, 3);
        let t0 = Instant::now();
        let quiet = p.admit(ip("10.0.0.9"), t0);
        let later = t0 + std::time::Duration::from_millis(1);
        let flood: Vec<_> = (0..3).map(|_| p.admit(ip("10.0.0.1"), later)).collect();
        let newcomer = p.admit(ip("10.0.0.5"), later);
        // The quiet address's handshake is older, but the flooding address pays.
        assert!(!quiet.0.evicted.is_cancelled());
        assert!(flood[0].0.evicted.is_cancelled());
        assert!(!flood[1].0.evicted.is_cancelled());
        assert_eq!(
            newcomer.1,
            Admission::EvictedOldest(SourceKey::of(ip("10.0.0.1")))
        );
        assert_eq!(p.count(), 4);
    }

    #[test]
    fn ipv6_addresses_of_one_prefix_share_a_bound() {
        assert_eq!(
            SourceKey::of(ip("2001:db8::1")),
            SourceKey::of(ip("2001:db8::ffff:1"))
        );
        assert_ne!(
            SourceKey::of(ip("2001:db8::1")),
            SourceKey::of(ip("2001:db8:0:1::1"))
        );
        assert_eq!(
            SourceKey::of(ip("::ffff:10.0.0.1")),
            SourceKey::of(ip("10.0.0.1"))
        );
    }
}
