//! The worker thread: fuses each texel frame into a scan (`texel::fuse`), places it
//! through the registration stage, records the pose, encodes the scan for the wire
//! and adds it to the hub. Synchronous, on its own thread, so the async runtime
//! never waits on computation.

use std::sync::Arc;
use std::time::Instant;

use bytes::Bytes;
use texel::capture::PoseTopic;
use texel::model::ScanId;
use texel::wire::{Message, TextureFormat, WireScan};
use texel::{FuseConfig, Pose, Sensor, SensorModel, TexelScan, fuse};
use tokio::sync::mpsc;

use super::ingest::PairJob;
use super::placement::{PoseRevision, Registration};
use crate::hub::Hub;
use crate::record::RecordItem;
use crate::status::{Counter, Metrics, Stage};

pub struct Worker {
    pub jobs: mpsc::Receiver<PairJob>,
    pub registration: Box<dyn Registration>,
    pub record: Option<mpsc::Sender<RecordItem>>,
    pub hub: Arc<Hub>,
    pub metrics: Arc<Metrics>,
    pub fuse: FuseConfig,
    pub texture: TextureFormat,
    pub jpeg_quality: u8,
}

impl Worker {
    /// Processes jobs until the ingest stage closes the queue.
    pub fn run(mut self) {
        // The ray table is built once per sensor model, not per frame.
        let mut sensor: Option<(Arc<SensorModel>, Sensor)> = None;
        // Timestamps of the placed scans by id, to record pose revisions.
        let mut timestamps: Vec<u64> = Vec::new();
        while let Some(job) = self.jobs.blocking_recv() {
            if sensor.as_ref().is_none_or(|(m, _)| **m != *job.sensor) {
                sensor = Some((Arc::clone(&job.sensor), Sensor::new((*job.sensor).clone())));
            }
            let Some((_, s)) = &sensor else {
                continue;
            };
            let id = timestamps.len() as ScanId;
            if let Some((timestamp_ns, revisions)) = self.process(job, s, id) {
                timestamps.push(timestamp_ns);
                // Revisions that came with this placement refer to earlier scans.
                self.apply_revisions(&revisions, &timestamps);
            }
            let revisions = self.registration.take_revisions();
            self.apply_revisions(&revisions, &timestamps);
        }
    }

    fn record(&self, item: RecordItem) {
        if let Some(tx) = &self.record
            && tx.blocking_send(item).is_err()
        {
            self.metrics.add(Counter::RecordErrors, 1);
        }
    }

    /// Fuses, places and publishes one texel frame as scan `id`; if placed, its
    /// timestamp and the revisions of earlier scans that came with it.
    fn process(
        &mut self,
        job: PairJob,
        sensor: &Sensor,
        id: ScanId,
    ) -> Option<(u64, Vec<PoseRevision>)> {
        let timestamp_ns = job.pair.timestamp_ns();
        let started = Instant::now();
        let scan = match fuse(&job.pair.range, job.pair.eo, sensor, &self.fuse) {
            Ok(scan) => Arc::new(scan),
            Err(e) => {
                self.metrics.add(Counter::FuseFailures, 1);
                tracing::warn!("frame at {timestamp_ns} ns not fused: {e}");
                return None;
            }
        };
        let fused = Instant::now();
        self.metrics
            .record_latency(Stage::Fuse, fused.duration_since(started));
        let placement = match self.registration.register(id, &scan, timestamp_ns) {
            Ok(p) => p,
            Err(failure) => {
                self.metrics.add(Counter::RegistrationFailures, 1);
                tracing::warn!(
                    kind = failure.kind,
                    "frame at {timestamp_ns} ns not placed: {}",
                    failure.reason
                );
                return None;
            }
        };
        let placed = Instant::now();
        self.metrics
            .record_latency(Stage::Register, placed.duration_since(fused));
        if placement.degenerate {
            self.metrics.add(Counter::RegistrationDegenerate, 1);
        }
        let frame = match self.encode(id, &scan, placement.world_from_scan) {
            Ok(f) => f,
            Err(e) => {
                self.metrics.add(Counter::RegistrationFailures, 1);
                tracing::error!("scan at {timestamp_ns} ns cannot be sent: {e}");
                return None;
            }
        };
        self.metrics.record_latency(Stage::Encode, placed.elapsed());
        self.record(RecordItem::Pose {
            topic: PoseTopic::Texel,
            timestamp_ns,
            world_from_eo: placement.world_from_scan,
        });
        if let Err(e) = self
            .hub
            .add_scan(id, Arc::clone(&scan), placement.world_from_scan, frame)
        {
            tracing::debug!("scan {id} not added: {e}");
            return None;
        }
        self.metrics.add(Counter::Scans, 1);
        self.metrics
            .record_latency(Stage::EndToEnd, job.received.elapsed());
        Some((timestamp_ns, placement.revisions))
    }

    fn encode(&self, id: ScanId, scan: &TexelScan, pose: Pose) -> Result<Bytes, String> {
        let texture = crate::texture::encode(&scan.texture, self.texture, self.jpeg_quality)
            .map_err(|e| e.to_string())?;
        let wire = WireScan::with_texture(id, scan, pose, texture).map_err(|e| e.to_string())?;
        let bytes = Message::ScanAdded(Box::new(wire))
            .encode()
            .map_err(|e| e.to_string())?;
        Ok(Bytes::from(bytes))
    }

    fn revise(&self, r: &PoseRevision, timestamp_ns: Option<u64>) {
        if let Err(e) = self.hub.revise_pose(r.id, r.world_from_scan) {
            tracing::warn!("pose revision of scan {} refused: {e}", r.id);
            return;
        }
        self.metrics.add(Counter::PoseRevisions, 1);
        if let Some(timestamp_ns) = timestamp_ns {
            // A later /texel/pose at the same timestamp supersedes the earlier one.
            self.record(RecordItem::Pose {
                topic: PoseTopic::Texel,
                timestamp_ns,
                world_from_eo: r.world_from_scan,
            });
        }
    }

    fn apply_revisions(&self, revisions: &[PoseRevision], timestamps: &[u64]) {
        for r in revisions {
            let t = usize::try_from(r.id)
                .ok()
                .and_then(|i| timestamps.get(i))
                .copied();
            self.revise(r, t);
        }
    }
}
