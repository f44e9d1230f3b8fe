//! The ingest stage: every source event is recorded first (nothing received is lost),
//! then range and EO frames are paired by timestamp (`texel::sync`), and each pair is
//! handed to the worker under the session's overload policy. Frames are shared: the
//! recorder and the pair hold the same frame, never a copy.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Instant;

use texel::capture::PoseTopic;
use texel::frames::SharedFramePair;
use texel::sync::SharedFrameSync;
use texel::{Pose, SensorModel};
use tokio::sync::mpsc;

use crate::config::OverloadPolicy;
use crate::record::RecordItem;
use crate::source::{SourceEvent, Tagged};
use crate::status::{Counter, Metrics, Stage};

/// One texel frame on its way to fusion and registration.
#[derive(Debug)]
pub struct PairJob {
    /// The frames, shared with the recorder until it has written them.
    pub pair: SharedFramePair,
    pub sensor: Arc<SensorModel>,
    /// When the pair's range frame reached ingest.
    pub received: Instant,
    /// The true pose at the pair's timestamp, when a source sent it first (the
    /// simulator does); registration anchors the world with it.
    pub truth: Option<Pose>,
}

/// Recent true poses by timestamp (bounded).
struct Truths(VecDeque<(u64, Pose)>);

impl Truths {
    const KEEP: usize = 64;

    fn note(&mut self, timestamp_ns: u64, pose: Pose) {
        if self.0.len() == Self::KEEP {
            self.0.pop_front();
        }
        self.0.push_back((timestamp_ns, pose));
    }

    fn of(&self, timestamp_ns: u64) -> Option<Pose> {
        self.0
            .iter()
            .rev()
            .find(|(t, _)| *t == timestamp_ns)
            .map(|(_, p)| *p)
    }
}

/// Arrival times of recent range frames, for latency (bounded).
struct Arrivals(VecDeque<(u64, Instant)>);

impl Arrivals {
    const KEEP: usize = 64;

    fn note(&mut self, timestamp_ns: u64) {
        if self.0.len() == Self::KEEP {
            self.0.pop_front();
        }
        self.0.push_back((timestamp_ns, Instant::now()));
    }

    fn of(&self, timestamp_ns: u64) -> Instant {
        self.0
            .iter()
            .rev()
            .find(|(t, _)| *t == timestamp_ns)
            .map_or_else(Instant::now, |(_, at)| *at)
    }
}

pub struct Ingest {
    pub events: mpsc::Receiver<Tagged>,
    pub record: Option<mpsc::Sender<RecordItem>>,
    pub pairs: mpsc::Sender<PairJob>,
    pub sync: SharedFrameSync,
    pub policy: OverloadPolicy,
    pub sensor: Option<Arc<SensorModel>>,
    pub metrics: Arc<Metrics>,
    /// Told each sensor model's response curve, which it serves (version 4).
    pub hub: Arc<crate::hub::Hub>,
    /// A live copy of every record, for the Foxglove server (never waits).
    pub tap: Option<super::tap::Tap>,
}

impl Ingest {
    /// Serves the sensor model's response curve from now on (or none).
    fn serve_response(&self, sensor: &SensorModel) {
        if let Err(e) = self.hub.set_eo_response(sensor.eo_response.as_ref()) {
            tracing::error!("the sensor's response curve cannot be served: {e}");
        }
    }

    /// Records an item; waits while the recorder is busy (the disk sets the pace
    /// rather than anything being dropped).
    async fn record(&mut self, item: RecordItem) {
        if let Some(tap) = &self.tap {
            tap.offer(&item);
        }
        if let Some(tx) = &self.record
            && tx.send(item).await.is_err()
        {
            self.metrics.add(Counter::RecordErrors, 1);
            tracing::error!("the recorder stopped; recording ends here");
            self.record = None;
        }
    }

    /// Counts a frame the sensor model does not describe; warns the first time.
    fn size_mismatch(&self, kind: &str, width: u32, height: u32) {
        if self.metrics.get(Counter::FrameSizeMismatch) == 0 {
            tracing::warn!(
                "a {kind} frame is {width}x{height}, which the sensor model does not describe; \
                 such frames are recorded but not fused"
            );
        }
        self.metrics.add(Counter::FrameSizeMismatch, 1);
    }

    fn publish_sync_counters(&self) {
        let c = self.sync.counters();
        let m = &self.metrics;
        m.set(Counter::Paired, c.paired);
        m.set(Counter::UnpairedRange, c.unpaired_range);
        m.set(Counter::UnpairedEo, c.unpaired_eo);
        m.set(Counter::LateRange, c.late_range);
        m.set(Counter::LateEo, c.late_eo);
    }

    /// Runs until every source has stopped, then passes on what is still waiting.
    pub async fn run(mut self) {
        if let Some(sensor) = self.sensor.clone() {
            self.serve_response(&sensor);
            self.record(RecordItem::Sensor(sensor)).await;
        }
        let mut arrivals = Arrivals(VecDeque::new());
        let mut truths = Truths(VecDeque::new());
        // keep-newest: the one pair waiting for room in the worker's queue.
        let mut waiting: Option<PairJob> = None;
        let pairs = self.pairs.clone();
        loop {
            let tagged = tokio::select! {
                t = self.events.recv() => match t {
                    Some(t) => t,
                    None => break,
                },
                permit = pairs.reserve(), if waiting.is_some() => {
                    match (permit, waiting.take()) {
                        (Ok(permit), Some(job)) => permit.send(job),
                        _ => return,
                    }
                    continue;
                }
            };
            let pair = match tagged.event {
                SourceEvent::Sensor(model) => {
                    if self.sensor.as_deref() != Some(&*model) {
                        self.serve_response(&model);
                        self.sensor = Some(Arc::clone(&model));
                        self.record(RecordItem::Sensor(model)).await;
                    }
                    None
                }
                SourceEvent::Range(frame) => {
                    arrivals.note(frame.timestamp_ns);
                    self.record(RecordItem::Range(Arc::clone(&frame))).await;
                    let fits = self.sensor.as_ref().is_none_or(|m| {
                        (frame.width, frame.height) == (m.lidar.width, m.lidar.height)
                    });
                    if fits {
                        self.sync.push_range(frame)
                    } else {
                        self.size_mismatch("range", frame.width, frame.height);
                        None
                    }
                }
                SourceEvent::Eo(frame) => {
                    self.record(RecordItem::Eo(Arc::clone(&frame))).await;
                    let fits = self
                        .sensor
                        .as_ref()
                        .is_none_or(|m| (frame.width, frame.height) == (m.eo.width, m.eo.height));
                    if fits {
                        self.sync.push_eo(frame)
                    } else {
                        self.size_mismatch("EO", frame.width, frame.height);
                        None
                    }
                }
                SourceEvent::Pose {
                    topic,
                    timestamp_ns,
                    world_from_eo,
                } => {
                    // The session records its own /texel/pose; a source's texel poses
                    // would duplicate them, its truth is worth keeping.
                    if topic == PoseTopic::Truth {
                        truths.note(timestamp_ns, world_from_eo);
                        self.record(RecordItem::Pose {
                            topic,
                            timestamp_ns,
                            world_from_eo,
                            revision: false,
                        })
                        .await;
                    }
                    None
                }
            };
            self.publish_sync_counters();
            let Some(pair) = pair else {
                continue;
            };
            let received = arrivals.of(pair.range.timestamp_ns);
            self.metrics.record_latency(Stage::Sync, received.elapsed());
            let Some(sensor) = self.sensor.clone() else {
                self.metrics.add(Counter::NoSensor, 1);
                continue;
            };
            let truth = truths.of(pair.timestamp_ns());
            let job = PairJob {
                pair,
                sensor,
                received,
                truth,
            };
            match self.policy {
                OverloadPolicy::Backpressure => {
                    if self.pairs.send(job).await.is_err() {
                        return;
                    }
                }
                OverloadPolicy::KeepNewest => match self.pairs.try_send(job) {
                    Ok(()) => {}
                    Err(mpsc::error::TrySendError::Full(job)) => {
                        if waiting.replace(job).is_some() {
                            self.metrics.add(Counter::SkippedByOverload, 1);
                        }
                    }
                    Err(mpsc::error::TrySendError::Closed(_)) => return,
                },
            }
        }
        // Every source stopped: what waits still gets registered.
        if let Some(job) = waiting.take() {
            let _ = self.pairs.send(job).await;
        }
        self.sync.finish();
        self.publish_sync_counters();
    }
}
