//! The worker thread: fuses each texel frame into a scan (`texel::fuse`), hands it to
//! the registration stage, records every pose the stage decides (`/texel/pose`, a
//! revision as a later message at the same frame timestamp) and passes the model
//! changes, in order, to the encode stage. Synchronous, on its own thread, so the
//! async runtime never waits on computation; wire encoding happens on the encode
//! thread, so registration latency is not serialised behind JPEG compression.
//!
//! A fused scan is checked against the wire's limits here, once (`check_sendable`):
//! the encode stage writes its frame from the scan without checking its arrays again.

use std::sync::Arc;
use std::time::Instant;

use texel::capture::PoseTopic;
use texel::model::{ModelEvent, ScanId};
use texel::{FuseConfig, Pose, Sensor, SensorModel, TexelScan, fuse};
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
}

impl Worker {
    /// Processes jobs until the ingest stage closes the queue.
    pub fn run(mut self) {
        // The ray table is built once per sensor model, not per frame.
        let mut sensor: Option<(Arc<SensorModel>, Sensor)> = None;
        // Timestamps of the scans in the model by id, to record pose revisions.
        let mut timestamps: Vec<u64> = std::mem::take(&mut self.timestamps);
        while let Some(job) = self.jobs.blocking_recv() {
            if sensor.as_ref().is_none_or(|(m, _)| **m != *job.sensor) {
                sensor = Some((Arc::clone(&job.sensor), Sensor::new((*job.sensor).clone())));
            }
            let Some((_, s)) = &sensor else {
                continue;
            };
            if !self.process(job, s, &mut timestamps) {
                // The encode stage has stopped: nothing more can be published.
                break;
            }
        }
    }

    fn record(&self, item: RecordItem) {
        if let Some(tx) = &self.record
            && tx.blocking_send(item).is_err()
        {
            self.metrics.add(Counter::RecordErrors, 1);
        }
    }

    /// Fuses and registers one texel frame and publishes what changed; false when the
    /// encode stage is gone.
    fn process(&mut self, job: PairJob, sensor: &Sensor, timestamps: &mut Vec<u64>) -> bool {
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
            lidar: &sensor.model.lidar,
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
        for event in output.events {
            let item = match event {
                ModelEvent::ScanAdded {
                    id,
                    scan,
                    world_from_scan,
                } => self.added(id, scan, world_from_scan, timestamps, |id| {
                    (Some(id) == this_id).then_some(job.received)
                }),
                ModelEvent::PoseRevised {
                    id,
                    world_from_scan,
                } => self.revised(id, world_from_scan, timestamps),
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
        true
    }

    /// A scan joined the model: record its pose, publish it.
    fn added(
        &self,
        id: ScanId,
        scan: Arc<TexelScan>,
        world_from_scan: Pose,
        timestamps: &mut Vec<u64>,
        received: impl Fn(ScanId) -> Option<Instant>,
    ) -> Option<Publish> {
        if id != timestamps.len() as ScanId {
            // The stage broke its contract; the model would refuse the scan.
            tracing::error!(
                "registration gave id {id}, expected {}; scan dropped",
                timestamps.len()
            );
            return None;
        }
        timestamps.push(scan.timestamp_ns);
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

    /// A pose moved: record the revision, publish it.
    fn revised(&self, id: ScanId, world_from_scan: Pose, timestamps: &[u64]) -> Option<Publish> {
        let Some(&timestamp_ns) = usize::try_from(id).ok().and_then(|i| timestamps.get(i)) else {
            tracing::warn!("pose revision of unknown scan {id} ignored");
            return None;
        };
        // A later /texel/pose at the same frame timestamp supersedes the earlier one.
        self.record(RecordItem::Pose {
            topic: PoseTopic::Texel,
            timestamp_ns,
            world_from_eo: world_from_scan,
            revision: true,
        });
        Some(Publish::Revision {
            id,
            world_from_scan,
        })
    }
}
