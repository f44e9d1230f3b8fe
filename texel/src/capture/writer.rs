//! Writes captures: channels created on first use, every message a Foxglove schema
//! (or the `/texel/sensor` JSON), and a chunk closed and flushed to the operating
//! system at least once per flush interval, so that a crash loses at most that much.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::Path;
use std::time::{Duration, Instant};

use foxglove::Encode;
use foxglove::messages::CompressedImage;

use super::convert::{calibration_from_camera, timestamp_from_nanos};
use super::images::{EoEncoding, RangeEncoding};
use super::{
    ANCHOR_JSON_SCHEMA, ANCHOR_SCHEMA_NAME, CameraRole, CaptureError, EXPOSURE_JSON_SCHEMA,
    EXPOSURE_SCHEMA_NAME, ExposureRecord, PoseAnchor, PoseTopic, SENSOR_JSON_SCHEMA,
    SENSOR_SCHEMA_NAME, frame_ids, messages, topics,
};
use crate::camera::PinholeCamera;
use crate::frames::{EoFrame, RangeFrame};
use crate::pose::Pose;
use crate::sensor::{SensorInfo, SensorModel};

/// A crash loses at most this much recording.
pub const DEFAULT_FLUSH_INTERVAL: Duration = Duration::from_secs(1);

/// How a capture is written.
#[derive(Debug, Clone)]
pub struct WriterOptions {
    /// `None` writes uncompressed chunks.
    pub compression: Option<mcap::Compression>,
    /// A chunk is closed when it reaches this many bytes (or at a flush).
    pub chunk_size_bytes: u64,
    pub flush_interval: Duration,
    /// Also ask the OS to put flushed bytes on the disk (`fdatasync`), so power loss
    /// loses no more than a crash does.
    pub sync_to_disk: bool,
}

impl Default for WriterOptions {
    fn default() -> Self {
        Self {
            compression: Some(mcap::Compression::Zstd),
            chunk_size_bytes: 4 << 20,
            flush_interval: DEFAULT_FLUSH_INTERVAL,
            sync_to_disk: true,
        }
    }
}

/// A buffered file whose `flush` also syncs the data to disk when asked to.
pub struct DurableFile {
    inner: BufWriter<File>,
    sync_to_disk: bool,
}

impl Write for DurableFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.inner.write(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()?;
        if self.sync_to_disk {
            self.inner.get_ref().sync_data()?;
        }
        Ok(())
    }
}

impl Seek for DurableFile {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.inner.seek(pos)
    }
}

/// Writes one capture.
pub struct CaptureWriter<W: Write + Seek> {
    writer: mcap::Writer<W>,
    /// Topic to channel id.
    channels: HashMap<String, u16>,
    /// Per-channel message sequence numbers.
    sequences: HashMap<u16, u32>,
    last_flush: Instant,
    flush_interval: Duration,
    path: String,
    messages_written: u64,
}

impl CaptureWriter<DurableFile> {
    /// Creates (or truncates) a capture file.
    pub fn create(path: &Path, options: WriterOptions) -> Result<Self, CaptureError> {
        let display = path.display().to_string();
        let file = File::create(path).map_err(|source| CaptureError::Io {
            path: display.clone(),
            source,
        })?;
        let sync_to_disk = options.sync_to_disk;
        Self::new(
            DurableFile {
                inner: BufWriter::with_capacity(1 << 20, file),
                sync_to_disk,
            },
            options,
            display,
        )
    }
}

impl<W: Write + Seek> CaptureWriter<W> {
    /// Writes a capture into any seekable sink (a file, or memory in tests); `name`
    /// identifies it in errors.
    pub fn new(sink: W, options: WriterOptions, name: String) -> Result<Self, CaptureError> {
        let writer = mcap::WriteOptions::new()
            .profile("")
            .library(concat!("texel ", env!("CARGO_PKG_VERSION")))
            .compression(options.compression)
            .chunk_size(Some(options.chunk_size_bytes))
            .create(sink)
            .map_err(|e| CaptureError::Write {
                path: name.clone(),
                message: e.to_string(),
            })?;
        Ok(Self {
            writer,
            channels: HashMap::new(),
            sequences: HashMap::new(),
            last_flush: Instant::now(),
            flush_interval: options.flush_interval,
            path: name,
            messages_written: 0,
        })
    }

    fn write_error(&self, e: impl std::fmt::Display) -> CaptureError {
        CaptureError::Write {
            path: self.path.clone(),
            message: e.to_string(),
        }
    }

    /// The channel for `topic`, creating it (and its schema) on first use.
    fn channel(
        &mut self,
        topic: &str,
        schema: Option<(&str, &str, &[u8])>,
        message_encoding: &str,
    ) -> Result<u16, CaptureError> {
        if let Some(&id) = self.channels.get(topic) {
            return Ok(id);
        }
        let schema_id = match schema {
            Some((name, encoding, data)) => self
                .writer
                .add_schema(name, encoding, data)
                .map_err(|e| self.write_error(e))?,
            None => 0,
        };
        let id = self
            .writer
            .add_channel(schema_id, topic, message_encoding, &BTreeMap::new())
            .map_err(|e| self.write_error(e))?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    fn write_on(
        &mut self,
        channel_id: u16,
        log_time_ns: u64,
        data: &[u8],
    ) -> Result<(), CaptureError> {
        let sequence = self.sequences.entry(channel_id).or_insert(0);
        *sequence = sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: *sequence,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        self.writer
            .write_to_known_channel(&header, data)
            .map_err(|e| self.write_error(e))?;
        self.messages_written += 1;
        self.flush_if_due()
    }

    /// Writes a Foxglove protobuf message on `topic`.
    fn write_foxglove<M: Encode>(
        &mut self,
        topic: &str,
        log_time_ns: u64,
        message: &M,
    ) -> Result<(), CaptureError> {
        let schema =
            M::get_schema().ok_or_else(|| self.write_error("message type has no schema"))?;
        let id = self.channel(
            topic,
            Some((&schema.name, &schema.encoding, &schema.data)),
            &M::get_message_encoding(),
        )?;
        let mut buf = Vec::with_capacity(message.encoded_len().unwrap_or(256));
        message.encode(&mut buf).map_err(|e| self.write_error(e))?;
        self.write_on(id, log_time_ns, &buf)
    }

    /// Writes the whole sensor model as the capture format wants it before the first
    /// frame: both calibrations, the co-boresight extrinsic and `/texel/sensor`.
    pub fn write_sensor(
        &mut self,
        sensor: &SensorModel,
        timestamp_ns: u64,
    ) -> Result<(), CaptureError> {
        self.write_calibration(CameraRole::Lidar, &sensor.lidar, timestamp_ns)?;
        self.write_calibration(CameraRole::Eo, &sensor.eo, timestamp_ns)?;
        self.write_eo_from_lidar(&sensor.eo_from_lidar, timestamp_ns)?;
        self.write_sensor_info(&sensor.info(), timestamp_ns)
    }

    pub fn write_calibration(
        &mut self,
        role: CameraRole,
        camera: &PinholeCamera,
        timestamp_ns: u64,
    ) -> Result<(), CaptureError> {
        let msg = calibration_from_camera(camera, role.frame_id(), timestamp_ns);
        self.write_foxglove(role.calibration_topic(), timestamp_ns, &msg)
    }

    /// `/tf_static`: the lidar frame's pose in the EO frame.
    pub fn write_eo_from_lidar(
        &mut self,
        eo_from_lidar: &Pose,
        timestamp_ns: u64,
    ) -> Result<(), CaptureError> {
        let msg = messages::eo_from_lidar(eo_from_lidar, timestamp_ns);
        self.write_foxglove(topics::TF_STATIC, timestamp_ns, &msg)
    }

    pub fn write_sensor_info(
        &mut self,
        info: &SensorInfo,
        timestamp_ns: u64,
    ) -> Result<(), CaptureError> {
        let id = self.channel(
            topics::TEXEL_SENSOR,
            Some((
                SENSOR_SCHEMA_NAME,
                "jsonschema",
                SENSOR_JSON_SCHEMA.as_bytes(),
            )),
            "json",
        )?;
        let json = serde_json::to_vec(info).map_err(|e| self.write_error(e))?;
        self.write_on(id, timestamp_ns, &json)
    }

    /// `/lidar/range`, and `/lidar/intensity` when the frame has intensity.
    pub fn write_range(
        &mut self,
        frame: &RangeFrame,
        encoding: RangeEncoding,
    ) -> Result<(), CaptureError> {
        let (range, intensity) =
            messages::range_images(frame, encoding).map_err(|e| self.write_error(e))?;
        self.write_foxglove(topics::LIDAR_RANGE, frame.timestamp_ns, &range)?;
        if let Some(intensity) = intensity {
            self.write_foxglove(topics::LIDAR_INTENSITY, frame.timestamp_ns, &intensity)?;
        }
        Ok(())
    }

    /// `/eo/image` in one of the raw encodings.
    pub fn write_eo(&mut self, frame: &EoFrame, encoding: EoEncoding) -> Result<(), CaptureError> {
        let msg = messages::eo_image(frame, encoding).map_err(|e| self.write_error(e))?;
        if let Some(exposure) = frame.exposure {
            self.write_exposure(&ExposureRecord {
                timestamp_ns: frame.timestamp_ns,
                exposure,
            })?;
        }
        self.write_foxglove(topics::EO_IMAGE, frame.timestamp_ns, &msg)
    }

    /// `/eo/exposure`: how the EO frame at `record.timestamp_ns` was exposed. Written
    /// before the frame (as [`Self::write_eo`] does), logged at the frame's time.
    pub fn write_exposure(&mut self, record: &ExposureRecord) -> Result<(), CaptureError> {
        let json = record.to_json().map_err(|e| {
            self.write_error(format!("EO frame at {} ns: {e}", record.timestamp_ns))
        })?;
        let id = self.channel(
            topics::EO_EXPOSURE,
            Some((
                EXPOSURE_SCHEMA_NAME,
                "jsonschema",
                EXPOSURE_JSON_SCHEMA.as_bytes(),
            )),
            "json",
        )?;
        self.write_on(id, record.timestamp_ns, &json)
    }

    /// `/eo/image/compressed`, already compressed as `format` (`jpeg` or `png`).
    pub fn write_eo_compressed(
        &mut self,
        timestamp_ns: u64,
        format: &str,
        data: Vec<u8>,
    ) -> Result<(), CaptureError> {
        let msg = CompressedImage {
            timestamp: Some(timestamp_from_nanos(timestamp_ns)),
            frame_id: frame_ids::EO.to_string(),
            data: data.into(),
            format: format.to_string(),
        };
        self.write_foxglove(topics::EO_IMAGE_COMPRESSED, timestamp_ns, &msg)
    }

    /// `/truth/pose` or `/texel/pose`: `world_from_eo` at a frame's timestamp.
    pub fn write_pose(
        &mut self,
        topic: PoseTopic,
        timestamp_ns: u64,
        world_from_eo: &Pose,
    ) -> Result<(), CaptureError> {
        let msg = messages::world_from_eo(world_from_eo, timestamp_ns);
        self.write_foxglove(topic.topic(), timestamp_ns, &msg)
    }

    /// `/texel/anchor`: the frame at `anchor.timestamp_ns` hangs from a keyframe,
    /// logged at `log_time_ns` (the frame's time, or later when it is re-hung).
    pub fn write_anchor(
        &mut self,
        anchor: &PoseAnchor,
        log_time_ns: u64,
    ) -> Result<(), CaptureError> {
        let id = self.channel(
            topics::TEXEL_ANCHOR,
            Some((
                ANCHOR_SCHEMA_NAME,
                "jsonschema",
                ANCHOR_JSON_SCHEMA.as_bytes(),
            )),
            "json",
        )?;
        let json = anchor.to_json().map_err(|e| self.write_error(e))?;
        self.write_on(id, log_time_ns, &json)
    }

    /// Copies a message read from another capture as it is (same topic, schema,
    /// encoding, log time and bytes).
    pub fn copy_message(&mut self, message: &mcap::Message<'_>) -> Result<(), CaptureError> {
        let channel = &message.channel;
        let id = match self.channels.get(&channel.topic) {
            Some(&id) => id,
            None => {
                let schema = channel
                    .schema
                    .as_ref()
                    .map(|s| (s.name.clone(), s.encoding.clone(), s.data.to_vec()));
                self.channel(
                    &channel.topic,
                    schema
                        .as_ref()
                        .map(|(n, e, d)| (n.as_str(), e.as_str(), d.as_slice())),
                    &channel.message_encoding,
                )?
            }
        };
        self.write_on(id, message.log_time, &message.data)
    }

    /// Closes the open chunk and flushes it to the OS if the flush interval has
    /// passed since the last flush. Writes call this; an idle recorder should call it
    /// on a timer.
    pub fn flush_if_due(&mut self) -> Result<(), CaptureError> {
        if self.last_flush.elapsed() >= self.flush_interval {
            self.flush()?;
        }
        Ok(())
    }

    /// Closes the open chunk and flushes everything written so far.
    pub fn flush(&mut self) -> Result<(), CaptureError> {
        self.writer.flush().map_err(|e| self.write_error(e))?;
        self.last_flush = Instant::now();
        Ok(())
    }

    pub fn messages_written(&self) -> u64 {
        self.messages_written
    }

    /// Writes the summary and footer; the file is complete.
    pub fn finish(mut self) -> Result<W, CaptureError> {
        self.writer.finish().map_err(|e| self.write_error(e))?;
        let mut sink = self.writer.into_inner();
        sink.flush().map_err(|e| CaptureError::Write {
            path: self.path.clone(),
            message: e.to_string(),
        })?;
        Ok(sink)
    }
}
