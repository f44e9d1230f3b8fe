//! The worker thread: fuses each texel frame into a scan (`texel::fuse`), hands it to
//! the registration stage, records the poses the stage decides (`/texel/pose` when a
//! scan is placed, `/texel/anchor` for the keyframe it hangs from, and a revision, as
//! a later `/texel/pose` at the same frame timestamp, only for a scan that hangs from
//! no other: the others follow their keyframe) and passes the model changes, in
//! order, to the encode stage. Synchronous, on its own thread, so the
//! async runtime never waits on computation; wire encoding happens on the encode
//! thread, so registration latency is not serialised behind JPEG compression.
//!
//! A fused scan is checked against the wire's limits here, once (`check_sendable`):
//! the encode stage writes its frame from the scan without checking its arrays again.

use std::sync::Arc;
use std::time::Instant;

use texel::capture::{PoseAnchor, PoseTopic};
use texel::model::{ModelEvent, ScanId};
use texel::paged::{PageStore, PagedTable};
use texel::{FuseConfig, Pose, Sensor, SensorModel, TexelScan, fuse};
use texel_register::ScanAnchor;
use tokio::sync::mpsc;

use super::encode::Publish;
use super::ingest::PairJob;
use super::placement::{Placement, Registration, ScanInput};
use crate::record::RecordItem;
use crate::status::{Counter, Metrics, Stage};

pub struct Worker {
    pub jobs: mpsc::Receiver<PairJob>,
    pub registration: Box<dyn Registration>,
    pub record: Option<mpsc::Sender<RecordItem>>,
    /// To the encode stage (bounded: the worker waits when it is full).
    pub publish: mpsc::Sender<Publish>,
    pub metrics: Arc<Metrics>,
    pub fuse: FuseConfig,
    /// Timestamps of the scans already in the model by id (a resumed session's).
    pub timestamps: Vec<u64>,
    /// Where the timestamps' pages beyond a few go (`None`: all in memory).
    pub timestamp_pages: Option<Box<dyn PageStore>>,
    /// Where the pages of the set of hanging scans beyond a few go.
    pub hanging_pages: Option<Box<dyn PageStore>>,
    /// A live copy of every pose recorded, for the Foxglove server (never waits).
    pub tap: Option<super::tap::Tap>,
}

/// Pages of timestamps (1,024 scans, 8 bytes each, a page) kept in memory.
const RESIDENT_TIMESTAMP_PAGES: usize = 4;

impl Worker {
    /// Processes jobs until the ingest stage closes the queue.
    pub fn run(mut self) {
        // The ray table is built once per sensor model, not per frame.
        let mut sensor: Option<(Arc<SensorModel>, Sensor)> = None;
        // Timestamps of the scans in the model by id, to record pose revisions.
        let mut timestamps = PagedTable::default();
        for t in std::mem::take(&mut self.timestamps) {
            timestamps.push(t);
        }
        if let Some(store) = self.timestamp_pages.take() {
            timestamps.page_to(store, RESIDENT_TIMESTAMP_PAGES);
        }
        let mut hanging = PagedTable::default();
        if let Some(store) = self.hanging_pages.take() {
            hanging.page_to(store, RESIDENT_TIMESTAMP_PAGES);
        }
        let mut recorded = Recorded {
            timestamps,
            hanging,
        };
        while let Some(job) = self.jobs.blocking_recv() {
            if sensor.as_ref().is_none_or(|(m, _)| **m != *job.sensor) {
                sensor = Some((Arc::clone(&job.sensor), Sensor::new((*job.sensor).clone())));
            }
            let Some((_, s)) = &sensor else {
                continue;
            };
            if !self.process(job, s, &mut recorded) {
                // The encode stage has stopped: nothing more can be published.
                break;
            }
        }
    }

    fn record(&self, item: RecordItem) {
        if let Some(tap) = &self.tap {
            tap.offer(&item);
        }
        if let Some(tx) = &self.record
            && tx.blocking_send(item).is_err()
        {
            self.metrics.add(Counter::RecordErrors, 1);
        }
    }

    /// Fuses and registers one texel frame and publishes what changed; false when the
    /// encode stage is gone.
    fn process(&mut self, job: PairJob, sensor: &Sensor, recorded: &mut Recorded) -> bool {
        let timestamp_ns = job.pair.timestamp_ns();
        let started = Instant::now();
        // The scan shares the EO frame as its texture (the recorder may still hold it).
        let scan = match fuse(&job.pair.range, job.pair.eo, sensor, &self.fuse) {
            Ok(scan) => Arc::new(scan),
            Err(e) => {
                self.metrics.add(Counter::FuseFailures, 1);
                tracing::warn!("frame at {timestamp_ns} ns not fused: {e}");
                return true;
            }
        };
        if let Err(e) = texel::wire::check_sendable(&scan) {
            // Never enters registration: a scan in the model must reach every viewer.
            self.metrics.add(Counter::FuseFailures, 1);
            tracing::warn!("frame at {timestamp_ns} ns cannot be streamed: {e}");
            return true;
        }
        let fused = Instant::now();
        self.metrics
            .record_latency(Stage::Fuse, fused.duration_since(started));
        let input = ScanInput {
            timestamp_ns,
            sensor: &sensor.model,
            truth: job.truth,
        };
        let output = self.registration.register(&scan, input);
        self.metrics
            .record_latency(Stage::Register, fused.elapsed());
        match &output.placement {
            Placement::Placed { degenerate, .. } => {
                if *degenerate {
                    self.metrics.add(Counter::RegistrationDegenerate, 1);
                }
            }
            Placement::Failed(failure) => {
                self.metrics.add(Counter::RegistrationFailures, 1);
                tracing::warn!(
                    kind = failure.kind,
                    "frame at {timestamp_ns} ns not placed (kept for a retry where the stage \
                     retries): {}",
                    failure.reason
                );
            }
        }
        if output.recovered > 0 {
            self.metrics
                .add(Counter::RegistrationRecovered, u64::from(output.recovered));
        }
        let this_id = match output.placement {
            Placement::Placed { id, .. } => Some(id),
            Placement::Failed(_) => None,
        };
        // How scans hang decides which revisions are recorded; the anchors are
        // recorded after the poses of the scans they concern.
        for anchor in &output.anchors {
            recorded.set_hanging(anchor.id, anchor.keyframe != anchor.id);
        }
        let added: Vec<ScanId> = output
            .events
            .iter()
            .filter_map(|e| match e {
                ModelEvent::ScanAdded { id, .. } => Some(*id),
                _ => None,
            })
            .collect();
        let anchors = output.anchors;
        for event in output.events {
            let item = match event {
                ModelEvent::ScanAdded {
                    id,
                    scan,
                    world_from_scan,
                } => self.added(id, scan, world_from_scan, recorded, |id| {
                    (Some(id) == this_id).then_some(job.received)
                }),
                ModelEvent::PoseRevised {
                    id,
                    world_from_scan,
                } => self.revised(id, world_from_scan, recorded),
                // Registration only adds and moves scans.
                _ => None,
            };
            let Some(item) = item else {
                continue;
            };
            if self.publish.blocking_send(item).is_err() {
                return false;
            }
        }
        for anchor in anchors {
            self.record_anchor(&anchor, &added, recorded);
        }
        true
    }

    /// Records how a scan hangs. A scan that became a keyframe outside a placement
    /// (a resumed session's, hung anew) gets its current pose recorded too: the
    /// scans hanging from it follow that pose.
    fn record_anchor(&self, anchor: &ScanAnchor, added: &[ScanId], recorded: &Recorded) {
        let (Some(timestamp_ns), Some(keyframe_timestamp_ns)) =
            (recorded.of(anchor.id), recorded.of(anchor.keyframe))
        else {
            tracing::warn!(
                "anchor of scan {} on scan {}: unknown scan; not recorded",
                anchor.id,
                anchor.keyframe
            );
            return;
        };
        if anchor.keyframe == anchor.id && !added.contains(&anchor.id) {
            self.record(RecordItem::Pose {
                topic: PoseTopic::Texel,
                timestamp_ns,
                world_from_eo: anchor.world_from_scan,
                revision: true,
            });
        }
        self.record(RecordItem::Anchor(PoseAnchor {
            timestamp_ns,
            keyframe_timestamp_ns,
            keyframe_from_eo: anchor.keyframe_from_scan,
        }));
    }

    /// A scan joined the model: record its pose, publish it.
    fn added(
        &self,
        id: ScanId,
        scan: Arc<TexelScan>,
        world_from_scan: Pose,
        recorded: &mut Recorded,
        received: impl Fn(ScanId) -> Option<Instant>,
    ) -> Option<Publish> {
        if id != recorded.timestamps.len() as ScanId {
            // The stage broke its contract; the model would refuse the scan.
            tracing::error!(
                "registration gave id {id}, expected {}; scan dropped",
                recorded.timestamps.len()
            );
            return None;
        }
        recorded.timestamps.push(scan.timestamp_ns);
        self.record(RecordItem::Pose {
            topic: PoseTopic::Texel,
            timestamp_ns: scan.timestamp_ns,
            world_from_eo: world_from_scan,
            revision: false,
        });
        Some(Publish::Scan {
            id,
            scan,
            world_from_scan,
            received: received(id),
        })
    }

    /// A pose moved: record the revision (unless the scan's recorded pose follows
    /// its keyframe's), publish it.
    fn revised(&self, id: ScanId, world_from_scan: Pose, recorded: &Recorded) -> Option<Publish> {
        let Some(timestamp_ns) = recorded.of(id) else {
            tracing::warn!("pose revision of unknown scan {id} ignored");
            return None;
        };
        // A later /texel/pose at the same frame timestamp supersedes the earlier one.
        if !recorded.is_hanging(id) {
            self.record(RecordItem::Pose {
                topic: PoseTopic::Texel,
                timestamp_ns,
                world_from_eo: world_from_scan,
                revision: true,
            });
        }
        Some(Publish::Revision {
            id,
            world_from_scan,
        })
    }
}

/// What the worker knows of the recorded scans: their frame timestamps by id, and
/// which hang from another scan (one bit each: the recording derives their pose
/// from their keyframe's).
struct Recorded {
    timestamps: PagedTable<u64>,
    /// A bit per scan, 64 to a word.
    hanging: PagedTable<u64>,
}

impl Recorded {
    fn of(&self, id: ScanId) -> Option<u64> {
        usize::try_from(id)
            .ok()
            .and_then(|i| self.timestamps.get(i))
    }

    fn is_hanging(&self, id: ScanId) -> bool {
        let Ok(i) = usize::try_from(id) else {
            return false;
        };
        self.hanging
            .get(i / 64)
            .is_some_and(|word| word & (1 << (i % 64)) != 0)
    }

    fn set_hanging(&mut self, id: ScanId, hanging: bool) {
        // Only scans the model has (or is about to have): bounded by the ids given.
        let Ok(i) = usize::try_from(id) else {
            return;
        };
        if i > self.timestamps.len() + (1 << 20) {
            return;
        }
        while self.hanging.len() <= i / 64 {
            self.hanging.push(0);
        }
        self.hanging.update(i / 64, |word| {
            if hanging {
                *word |= 1 << (i % 64);
            } else {
                *word &= !(1 << (i % 64));
            }
        });
    }
}
