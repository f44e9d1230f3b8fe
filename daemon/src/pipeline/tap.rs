//! The live tap: a bounded, non-blocking copy of what the recorder is given (the
//! sensor model, raw range and EO frames, true and estimated poses), for a live
//! publisher that must never slow the camera down (the Foxglove server,
//! `foxglove_live`). Ingest and the worker offer each record to the tap beside the
//! recorder; the tap never waits: an offer that finds no room is dropped and counted.
//!
//! Frames are shared (`Arc`), so an offer costs a reference, but a held frame keeps
//! its pixels alive: at most [`FRAME_SLOTS`] frames wait in the tap at once, and a
//! frame offered beyond them is dropped (a live view wants the newest frames, not
//! every frame). The small records (sensor models, poses, anchors) have the rest of
//! the queue, so a burst of frames never pushes out a pose.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

use tokio::sync::mpsc;

use crate::record::RecordItem;
use crate::status::QueueProbe;

/// Frames (range or EO) waiting in the tap at most.
pub const FRAME_SLOTS: usize = 4;

/// Records of every kind waiting in the tap at most.
pub const TAP_QUEUE: usize = 1024;

/// What the tap dropped, for the consumer's status.
#[derive(Debug, Default)]
pub struct TapCounters {
    /// Frames dropped because [`FRAME_SLOTS`] frames were waiting.
    pub frames_dropped: AtomicU64,
    /// Small records dropped because the whole queue was full.
    pub records_dropped: AtomicU64,
}

/// The producers' end (cheap to clone).
#[derive(Debug, Clone)]
pub struct Tap {
    tx: mpsc::Sender<RecordItem>,
    frames_waiting: Arc<AtomicUsize>,
    counters: Arc<TapCounters>,
}

/// The consumer's end.
#[derive(Debug)]
pub struct TapReceiver {
    rx: mpsc::Receiver<RecordItem>,
    frames_waiting: Arc<AtomicUsize>,
    pub counters: Arc<TapCounters>,
}

/// A new tap and its receiver.
pub fn tap() -> (Tap, TapReceiver) {
    let (tx, rx) = mpsc::channel(TAP_QUEUE);
    let frames_waiting = Arc::new(AtomicUsize::new(0));
    let counters = Arc::new(TapCounters::default());
    (
        Tap {
            tx,
            frames_waiting: Arc::clone(&frames_waiting),
            counters: Arc::clone(&counters),
        },
        TapReceiver {
            rx,
            frames_waiting,
            counters,
        },
    )
}

fn is_frame(item: &RecordItem) -> bool {
    matches!(item, RecordItem::Range(_) | RecordItem::Eo(_))
}

impl Tap {
    /// Offers a copy of `item` (a reference for a frame); never waits.
    pub fn offer(&self, item: &RecordItem) {
        if matches!(item, RecordItem::Tick) {
            return;
        }
        let frame = is_frame(item);
        if frame {
            // Reserve a frame slot first; give it back if the queue refuses.
            let taken =
                self.frames_waiting
                    .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                        (n < FRAME_SLOTS).then_some(n + 1)
                    });
            if taken.is_err() {
                self.counters.frames_dropped.fetch_add(1, Ordering::Relaxed);
                return;
            }
        }
        if self.tx.try_send(item.clone()).is_err() {
            if frame {
                self.frames_waiting.fetch_sub(1, Ordering::AcqRel);
                self.counters.frames_dropped.fetch_add(1, Ordering::Relaxed);
            } else {
                self.counters
                    .records_dropped
                    .fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Records waiting in the tap.
    pub fn depth(&self) -> usize {
        self.tx.max_capacity() - self.tx.capacity()
    }

    /// A probe of the tap's depth for the status's queue depths; it does not keep
    /// the tap open.
    pub fn probe(&self, name: &'static str) -> QueueProbe {
        let weak = self.tx.downgrade();
        QueueProbe {
            name,
            capacity: TAP_QUEUE,
            depth: Box::new(move || weak.upgrade().map(|tx| tx.max_capacity() - tx.capacity())),
        }
    }
}

impl TapReceiver {
    /// The next record, waiting for one (call from a blocking thread); `None` once
    /// every producer has gone.
    pub fn blocking_recv(&mut self) -> Option<RecordItem> {
        let item = self.rx.blocking_recv()?;
        if is_frame(&item) {
            self.frames_waiting.fetch_sub(1, Ordering::AcqRel);
        }
        Some(item)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use texel::{EoFrame, Pose};

    fn eo() -> RecordItem {
        RecordItem::Eo(Arc::new(EoFrame {
            width: 1,
            height: 1,
            rgb: vec![0; 3],
            timestamp_ns: 0,
            exposure: None,
        }))
    }

    #[test]
    fn frames_beyond_their_slots_are_dropped_and_poses_are_not() {
        let (tap, mut rx) = tap();
        for _ in 0..FRAME_SLOTS + 3 {
            tap.offer(&eo());
        }
        let pose = RecordItem::Pose {
            topic: texel::capture::PoseTopic::Texel,
            timestamp_ns: 1,
            world_from_eo: Pose::identity(),
            revision: false,
        };
        tap.offer(&pose);
        assert_eq!(rx.counters.frames_dropped.load(Ordering::Relaxed), 3);
        assert_eq!(tap.depth(), FRAME_SLOTS + 1);
        // Taking a frame frees its slot.
        assert!(matches!(rx.blocking_recv(), Some(RecordItem::Eo(_))));
        tap.offer(&eo());
        assert_eq!(rx.counters.frames_dropped.load(Ordering::Relaxed), 3);
        drop(tap);
        let rest: Vec<_> = std::iter::from_fn(|| rx.blocking_recv()).collect();
        assert_eq!(rest.len(), FRAME_SLOTS + 1);
        assert_eq!(rx.counters.records_dropped.load(Ordering::Relaxed), 0);
    }
}
