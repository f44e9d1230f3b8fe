//! The recorder: a dedicated thread that writes everything received, before any lossy
//! stage, to a capture (docs/capture-format.md): sensor model, raw range and EO
//! frames, source poses, and the poses the pipeline estimated (`/texel/pose`). A pose
//! revision is a further `/texel/pose` message with the frame's timestamp in its
//! `timestamp` field and, as log time, the latest frame time recorded when the
//! revision was made: it comes later in the file and in log-time order, and readers
//! take the last `/texel/pose` of a timestamp. Chunks are flushed at
//! least every `flush_interval`, so `kill -9` loses at most that much; a clean stop
//! finalises the file.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use texel::capture::{
    CaptureError, CaptureWriter, EoEncoding, PoseAnchor, PoseTopic, RangeEncoding, WriterOptions,
};
use texel::{EoFrame, Pose, RangeFrame, SensorModel};
use tokio::sync::mpsc;

use crate::config::{Compression, RecordSection};

/// One thing to record (cheap to clone: frames and models are shared).
#[derive(Debug, Clone)]
pub enum RecordItem {
    Sensor(Arc<SensorModel>),
    /// The frame the pipeline pairs and fuses, shared rather than copied; the
    /// recorder lets go of it as soon as it is written.
    Range(Arc<RangeFrame>),
    Eo(Arc<EoFrame>),
    Pose {
        topic: PoseTopic,
        timestamp_ns: u64,
        world_from_eo: Pose,
        /// A revision of a pose recorded before (logged at the latest frame time).
        revision: bool,
    },
    /// `/texel/anchor`: how a registered scan hangs from its keyframe (logged at
    /// the latest frame time, like a revision).
    Anchor(PoseAnchor),
    /// Nothing to write; lets an idle recorder flush on time.
    Tick,
}

/// What the recorder did.
#[derive(Debug, Default, Clone)]
pub struct RecordSummary {
    pub path: PathBuf,
    pub messages: u64,
    pub errors: u64,
    pub first_error: Option<String>,
}

/// A running recorder.
pub struct Recorder {
    pub tx: mpsc::Sender<RecordItem>,
    pub messages: Arc<AtomicU64>,
    pub errors: Arc<AtomicU64>,
    pub path: PathBuf,
    thread: JoinHandle<RecordSummary>,
}

impl Recorder {
    /// Creates the capture and starts the writing thread.
    pub fn start(path: &Path, config: &RecordSection) -> Result<Self, CaptureError> {
        let options = WriterOptions {
            compression: match config.compression {
                Compression::Zstd => Some(mcap::Compression::Zstd),
                Compression::Lz4 => Some(mcap::Compression::Lz4),
                Compression::None => None,
            },
            flush_interval: Duration::from_millis(config.flush_interval_ms),
            sync_to_disk: config.sync_to_disk,
            ..WriterOptions::default()
        };
        let writer = CaptureWriter::create(path, options)?;
        let (tx, rx) = mpsc::channel(config.queue);
        let messages = Arc::new(AtomicU64::new(0));
        let errors = Arc::new(AtomicU64::new(0));
        let counters = (Arc::clone(&messages), Arc::clone(&errors));
        let owned = path.to_path_buf();
        let thread = std::thread::Builder::new()
            .name("texel-record".into())
            .spawn(move || write_loop(writer, rx, counters, owned))
            .map_err(|e| CaptureError::Write {
                path: path.display().to_string(),
                message: format!("cannot start the recorder thread: {e}"),
            })?;
        Ok(Self {
            tx,
            messages,
            errors,
            path: path.to_path_buf(),
            thread,
        })
    }

    /// Waits for the thread to write what is queued and finalise the file. Every
    /// sender must have been dropped first.
    pub fn finish(self) -> RecordSummary {
        drop(self.tx);
        self.thread.join().unwrap_or_else(|_| RecordSummary {
            path: self.path.clone(),
            errors: 1,
            first_error: Some("the recorder thread panicked".into()),
            ..Default::default()
        })
    }
}

fn write_loop<W: std::io::Write + std::io::Seek>(
    mut writer: CaptureWriter<W>,
    mut rx: mpsc::Receiver<RecordItem>,
    (messages, errors): (Arc<AtomicU64>, Arc<AtomicU64>),
    path: PathBuf,
) -> RecordSummary {
    let mut summary = RecordSummary {
        path,
        ..Default::default()
    };
    let mut sensor_written: Option<Arc<SensorModel>> = None;
    // A calibration is logged at the time of the latest frame, so a reader meets it
    // before the frames it applies to.
    let mut latest_ns = 0u64;
    let note = |summary: &mut RecordSummary, r: Result<(), CaptureError>| {
        if let Err(e) = r {
            if summary.first_error.is_none() {
                tracing::error!("recording: {e}");
                summary.first_error = Some(e.to_string());
            }
            summary.errors += 1;
            errors.store(summary.errors, Ordering::Relaxed);
        }
    };
    while let Some(item) = rx.blocking_recv() {
        let result = match item {
            RecordItem::Sensor(model) => {
                if sensor_written.as_deref() == Some(&*model) {
                    Ok(())
                } else {
                    let r = writer.write_sensor(&model, latest_ns);
                    sensor_written = Some(model);
                    r
                }
            }
            RecordItem::Range(frame) => {
                latest_ns = latest_ns.max(frame.timestamp_ns);
                writer.write_range(&frame, RangeEncoding::F32Metres)
            }
            RecordItem::Eo(frame) => {
                latest_ns = latest_ns.max(frame.timestamp_ns);
                writer.write_eo(&frame, EoEncoding::Rgb8)
            }
            RecordItem::Pose {
                topic,
                timestamp_ns,
                world_from_eo,
                revision,
            } => {
                if revision && latest_ns > timestamp_ns {
                    write_pose_at(&mut writer, topic, timestamp_ns, latest_ns, &world_from_eo)
                } else {
                    writer.write_pose(topic, timestamp_ns, &world_from_eo)
                }
            }
            RecordItem::Anchor(anchor) => {
                writer.write_anchor(&anchor, latest_ns.max(anchor.timestamp_ns))
            }
            RecordItem::Tick => writer.flush_if_due(),
        };
        note(&mut summary, result);
        messages.store(writer.messages_written(), Ordering::Relaxed);
    }
    summary.messages = writer.messages_written();
    note(&mut summary, writer.finish().map(|_| ()));
    summary
}

/// A pose message whose log time is later than its timestamp (a revision): the same
/// `foxglove.FrameTransform` on the same channel as `CaptureWriter::write_pose` writes.
fn write_pose_at<W: std::io::Write + std::io::Seek>(
    writer: &mut CaptureWriter<W>,
    topic: PoseTopic,
    timestamp_ns: u64,
    log_time_ns: u64,
    world_from_eo: &Pose,
) -> Result<(), CaptureError> {
    use foxglove::Encode;
    let message = texel::capture::transform_from_pose(
        texel::capture::frame_ids::WORLD,
        texel::capture::frame_ids::EO,
        world_from_eo,
        timestamp_ns,
    );
    let error = |m: String| CaptureError::Write {
        path: topic.topic().to_string(),
        message: m,
    };
    let mut data = Vec::with_capacity(message.encoded_len().unwrap_or(256));
    message
        .encode(&mut data)
        .map_err(|e| error(e.to_string()))?;
    let schema = foxglove::messages::FrameTransform::get_schema()
        .ok_or_else(|| error("FrameTransform has no schema".into()))?;
    let channel = mcap::Channel {
        id: 0,
        topic: topic.topic().to_string(),
        schema: Some(Arc::new(mcap::Schema {
            id: 0,
            name: schema.name,
            encoding: schema.encoding,
            data: std::borrow::Cow::Owned(schema.data.into_owned()),
        })),
        message_encoding: foxglove::messages::FrameTransform::get_message_encoding(),
        metadata: std::collections::BTreeMap::new(),
    };
    writer.copy_message(&mcap::Message {
        channel: Arc::new(channel),
        sequence: 0,
        log_time: log_time_ns,
        publish_time: log_time_ns,
        data: std::borrow::Cow::Owned(data),
    })
}
