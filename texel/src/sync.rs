//! Pairs lidar range frames with the EO frames taken with them, by timestamp within
//! a tolerance, with bounded buffers and counters for what could not be paired.
//!
//! Used by live sources (where the two sensors' frames arrive with slightly
//! different timestamps) and by capture replay alike. Frames are paired as they come:
//! owned (the default) or shared behind `Arc`s ([`SharedFrameSync`]), which the
//! daemon uses so its recorder and fusion hold the same frame, not two copies.

use std::borrow::Borrow;
use std::collections::VecDeque;
use std::sync::Arc;

use crate::frames::{EoFrame, FramePair, RangeFrame};

/// Counts of what the synchroniser did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SyncCounters {
    pub paired: u64,
    /// Range frames dropped without an EO partner (superseded or buffer full).
    pub unpaired_range: u64,
    pub unpaired_eo: u64,
    /// Frames that arrived older than an already-emitted pair.
    pub late_range: u64,
    pub late_eo: u64,
}

/// The synchroniser's state, holding range frames as `R` and EO frames as `E`
/// (owned frames, or `Arc`s of them).
#[derive(Debug)]
pub struct FrameSync<R = RangeFrame, E = EoFrame> {
    tolerance_ns: u64,
    max_pending: usize,
    ranges: VecDeque<R>,
    eos: VecDeque<E>,
    last_paired_ns: Option<u64>,
    counters: SyncCounters,
}

/// A synchroniser of shared frames: pairs hold the same allocations as were pushed.
pub type SharedFrameSync = FrameSync<Arc<RangeFrame>, Arc<EoFrame>>;

impl<R: Borrow<RangeFrame>, E: Borrow<EoFrame>> FrameSync<R, E> {
    /// `tolerance_ns`: the largest timestamp difference of a pair. `max_pending`:
    /// how many unpaired frames of each kind wait for a partner (at least 1).
    pub fn new(tolerance_ns: u64, max_pending: usize) -> Self {
        Self {
            tolerance_ns,
            max_pending: max_pending.max(1),
            ranges: VecDeque::new(),
            eos: VecDeque::new(),
            last_paired_ns: None,
            counters: SyncCounters::default(),
        }
    }

    pub fn counters(&self) -> SyncCounters {
        self.counters
    }

    pub fn pending(&self) -> (usize, usize) {
        (self.ranges.len(), self.eos.len())
    }

    fn is_late(&self, t: u64) -> bool {
        self.last_paired_ns
            .is_some_and(|last| t.saturating_add(self.tolerance_ns) < last)
    }

    /// Index of the queued timestamp nearest to `t` within the tolerance.
    fn nearest(&self, times: impl Iterator<Item = u64>, t: u64) -> Option<usize> {
        times
            .enumerate()
            .map(|(i, ti)| (i, ti.abs_diff(t)))
            .filter(|&(_, dt)| dt <= self.tolerance_ns)
            // Ties go to the earlier frame, deterministically.
            .min_by_key(|&(i, dt)| (dt, i))
            .map(|(i, _)| i)
    }

    /// Drops queued frames older than a pair just made at `t` (they can no longer
    /// pair with anything newer without crossing it).
    fn drop_older_than(&mut self, t: u64) {
        while self
            .ranges
            .front()
            .is_some_and(|f| f.borrow().timestamp_ns < t)
        {
            self.ranges.pop_front();
            self.counters.unpaired_range += 1;
        }
        while self
            .eos
            .front()
            .is_some_and(|f| f.borrow().timestamp_ns < t)
        {
            self.eos.pop_front();
            self.counters.unpaired_eo += 1;
        }
    }

    fn emit(&mut self, range: R, eo: E) -> FramePair<R, E> {
        let (tr, te) = (range.borrow().timestamp_ns, eo.borrow().timestamp_ns);
        let t = tr.min(te);
        self.last_paired_ns = Some(tr.max(te));
        self.counters.paired += 1;
        self.drop_older_than(t);
        FramePair { range, eo }
    }

    /// Offers a range frame; returns a pair if it completes one.
    pub fn push_range(&mut self, frame: R) -> Option<FramePair<R, E>> {
        let t = frame.borrow().timestamp_ns;
        if self.is_late(t) {
            self.counters.late_range += 1;
            return None;
        }
        match self.nearest(self.eos.iter().map(|f| f.borrow().timestamp_ns), t) {
            Some(i) => {
                let eo = self.eos.remove(i)?;
                Some(self.emit(frame, eo))
            }
            None => {
                insert_sorted(&mut self.ranges, frame, |f| f.borrow().timestamp_ns);
                if self.ranges.len() > self.max_pending {
                    self.ranges.pop_front();
                    self.counters.unpaired_range += 1;
                }
                None
            }
        }
    }

    /// Offers an EO frame; returns a pair if it completes one.
    pub fn push_eo(&mut self, frame: E) -> Option<FramePair<R, E>> {
        let t = frame.borrow().timestamp_ns;
        if self.is_late(t) {
            self.counters.late_eo += 1;
            return None;
        }
        match self.nearest(self.ranges.iter().map(|f| f.borrow().timestamp_ns), t) {
            Some(i) => {
                let range = self.ranges.remove(i)?;
                Some(self.emit(range, frame))
            }
            None => {
                insert_sorted(&mut self.eos, frame, |f| f.borrow().timestamp_ns);
                if self.eos.len() > self.max_pending {
                    self.eos.pop_front();
                    self.counters.unpaired_eo += 1;
                }
                None
            }
        }
    }

    /// Ends the stream: whatever still waits is counted unpaired.
    pub fn finish(&mut self) {
        self.counters.unpaired_range += self.ranges.len() as u64;
        self.counters.unpaired_eo += self.eos.len() as u64;
        self.ranges.clear();
        self.eos.clear();
    }
}

/// Keeps a queue ordered by timestamp (frames usually arrive in order, so this
/// scans from the back).
fn insert_sorted<T>(queue: &mut VecDeque<T>, item: T, key: impl Fn(&T) -> u64) {
    let k = key(&item);
    let at = queue.iter().rposition(|q| key(q) <= k).map_or(0, |i| i + 1);
    queue.insert(at, item);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn range(t: u64) -> RangeFrame {
        RangeFrame::empty(1, 1, t, 0)
    }

    fn eo(t: u64) -> EoFrame {
        EoFrame {
            width: 1,
            height: 1,
            rgb: vec![0; 3],
            timestamp_ns: t,
            exposure: None,
        }
    }

    #[test]
    fn equal_timestamps_pair_in_either_order() {
        let mut s = FrameSync::new(0, 4);
        assert!(s.push_range(range(10)).is_none());
        assert_eq!(s.push_eo(eo(10)).unwrap().timestamp_ns(), 10);
        assert!(s.push_eo(eo(20)).is_none());
        assert_eq!(s.push_range(range(20)).unwrap().eo.timestamp_ns, 20);
        assert_eq!(s.counters().paired, 2);
    }

    #[test]
    fn nearest_within_tolerance_wins_and_older_ones_are_dropped() {
        let mut s = FrameSync::new(5, 8);
        s.push_eo(eo(100));
        s.push_eo(eo(108));
        let p = s.push_range(range(107)).unwrap();
        assert_eq!(p.eo.timestamp_ns, 108);
        let c = s.counters();
        assert_eq!(c.unpaired_eo, 1, "the EO frame at 100 can no longer pair");
        // A range frame from before the pair is late.
        assert!(s.push_range(range(90)).is_none());
        assert_eq!(s.counters().late_range, 1);
    }

    #[test]
    fn shared_frames_are_paired_without_copies() {
        let mut s = SharedFrameSync::new(5, 4);
        let (r, e) = (Arc::new(range(10)), Arc::new(eo(12)));
        // What a recorder would hold while the pair goes on to fusion.
        let (recorded_r, recorded_e) = (Arc::clone(&r), Arc::clone(&e));
        assert!(s.push_range(r).is_none());
        let pair = s.push_eo(e).unwrap();
        assert_eq!(pair.timestamp_ns(), 10);
        assert!(Arc::ptr_eq(&pair.range, &recorded_r));
        assert!(Arc::ptr_eq(&pair.eo, &recorded_e));
        // Once the other holder lets go, the frame can be taken back by value.
        drop(recorded_e);
        assert_eq!(Arc::try_unwrap(pair.eo).unwrap(), eo(12));
    }

    #[test]
    fn beyond_tolerance_does_not_pair_and_buffers_are_bounded() {
        let mut s = FrameSync::new(5, 2);
        for t in [0, 100, 200, 300] {
            assert!(s.push_range(range(t)).is_none());
        }
        assert_eq!(s.pending(), (2, 0));
        assert_eq!(s.counters().unpaired_range, 2);
        assert!(s.push_eo(eo(250)).is_none());
        s.finish();
        assert_eq!(s.counters().unpaired_range, 4);
        assert_eq!(s.counters().unpaired_eo, 1);
    }
}
