//! Streams a capture message by message (constant memory whatever the file size),
//! decodes each known topic into the project's types and enforces the reading rules:
//! a frame before its calibration or of another size is an error naming the topic and
//! log time, and a truncated file yields every complete message before the cut, then
//! an error saying where the file ends. Damage inside the file is read around
//! (`records`): each stretch skipped is reported, with the log times it cost, and
//! reading goes on.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use foxglove::messages::{CameraCalibration, CompressedImage, FrameTransform, RawImage};

use super::convert::{camera_from_calibration, nanos_from_timestamp, pose_from_transform};
use super::images::{decode_compressed, decode_eo, decode_intensity, decode_range};
use super::records::{RecordReader, Step};
use super::summary::SummaryIndex;
use super::{CaptureError, ExposureRecord, PoseAnchor, PoseTopic, frame_ids, topics};
use crate::camera::PinholeCamera;
use crate::frames::{EoFrame, RangeFrame};
use crate::pose::Pose;
use crate::sensor::SensorInfo;

/// No record may be longer than this, nor longer than the rest of the file; larger
/// claims are refused before any allocation (a 16384² RGBA image is 1 GiB, far beyond
/// any texel camera).
const RECORD_LENGTH_LIMIT: u64 = 512 << 20;

pub(super) const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// One decoded message of a capture.
#[derive(Debug, Clone)]
pub enum CaptureEvent {
    LidarCalibration {
        log_time_ns: u64,
        camera: PinholeCamera,
    },
    EoCalibration {
        log_time_ns: u64,
        camera: PinholeCamera,
    },
    /// `/tf_static`: the lidar frame's pose in the EO frame.
    EoFromLidar {
        log_time_ns: u64,
        pose: Pose,
    },
    Sensor {
        log_time_ns: u64,
        info: SensorInfo,
    },
    Range(RangeFrame),
    Intensity {
        timestamp_ns: u64,
        width: u32,
        height: u32,
        values: Vec<f32>,
    },
    /// From `/eo/image` or `/eo/image/compressed`, converted to RGB8.
    Eo(EoFrame),
    Pose {
        topic: PoseTopic,
        timestamp_ns: u64,
        world_from_eo: Pose,
    },
    /// `/texel/anchor`: a registered frame hangs from a keyframe.
    Anchor(PoseAnchor),
    /// `/eo/exposure`: how the EO frame at its timestamp was exposed (the reader also
    /// attaches it to that frame's [`EoFrame::exposure`]).
    Exposure(ExposureRecord),
    /// A topic the format does not define; readers skip it.
    Other {
        topic: String,
        log_time_ns: u64,
    },
}

/// Where the reader is in the file.
#[derive(Debug, Clone, Copy, Default)]
pub struct ReadPosition {
    pub bytes_read: u64,
    pub messages: u64,
    pub last_log_time_ns: Option<u64>,
}

/// Streams a capture.
pub struct CaptureReader<R: Read> {
    records: RecordReader<R>,
    path: String,
    file_len: Option<u64>,
    position: ReadPosition,
    magic_checked: bool,
    done: bool,
    lidar_calibration: Option<PinholeCamera>,
    eo_calibration: Option<PinholeCamera>,
    /// The last `/eo/exposure` read, until the EO frame it names arrives.
    pending_exposure: Option<ExposureRecord>,
}

impl CaptureReader<File> {
    /// Opens a capture file; its summary, when it has a sound one, is read first so
    /// that damage can be read around and its cost told in log times.
    pub fn open(path: &Path) -> Result<Self, CaptureError> {
        let display = path.display().to_string();
        let io = |source| CaptureError::Io {
            path: display.clone(),
            source,
        };
        let mut file = File::open(path).map_err(io)?;
        let len = file.metadata().map_err(io)?.len();
        let summary = SummaryIndex::read(&mut file, len);
        file.seek(SeekFrom::Start(0)).map_err(io)?;
        Ok(Self::with_summary(file, Some(len), display, summary))
    }
}

impl<R: Read> CaptureReader<R> {
    /// Reads from any byte source; `file_len` (when known) sharpens truncation
    /// reports; `name` identifies the capture in errors.
    pub fn new(source: R, file_len: Option<u64>, name: String) -> Self {
        Self::with_summary(source, file_len, name, None)
    }

    fn with_summary(
        source: R,
        file_len: Option<u64>,
        name: String,
        summary: Option<SummaryIndex>,
    ) -> Self {
        Self {
            records: RecordReader::new(source, 0, file_len, RECORD_LENGTH_LIMIT, summary),
            path: name,
            file_len,
            position: ReadPosition::default(),
            magic_checked: false,
            done: false,
            lidar_calibration: None,
            eo_calibration: None,
            pending_exposure: None,
        }
    }

    pub fn position(&self) -> ReadPosition {
        self.position
    }

    pub fn path(&self) -> &str {
        &self.path
    }

    /// The most recent calibrations seen.
    pub fn calibrations(&self) -> (Option<&PinholeCamera>, Option<&PinholeCamera>) {
        (
            self.lidar_calibration.as_ref(),
            self.eo_calibration.as_ref(),
        )
    }

    fn io_error(&self, source: std::io::Error) -> CaptureError {
        CaptureError::Io {
            path: self.path.clone(),
            source,
        }
    }

    /// Checks the magic, so that a file that is not MCAP at all is told apart from
    /// one that is cut short.
    fn check_magic(&mut self) -> Result<(), CaptureError> {
        let head = self
            .records
            .take_magic(MCAP_MAGIC.len())
            .map_err(|e| self.io_error(e))?;
        self.position.bytes_read = self.records.bytes_read();
        // An empty file is a recording cut before its first byte, not another format.
        if head[..] != MCAP_MAGIC[..head.len()] {
            return Err(CaptureError::NotMcap {
                path: self.path.clone(),
            });
        }
        if head.len() < MCAP_MAGIC.len() {
            return Err(self.truncated());
        }
        Ok(())
    }

    fn truncated(&self) -> CaptureError {
        CaptureError::Truncated {
            path: self.path.clone(),
            file_len: self.file_len.unwrap_or(self.position.bytes_read),
            messages: self.position.messages,
        }
    }

    /// The next raw message, `None` at the end of the file. A damaged stretch of the
    /// file yields a [`CaptureError::Damaged`] and reading goes on after it; a
    /// truncation or an I/O error ends the file.
    pub fn next_message(&mut self) -> Option<Result<mcap::Message<'static>, CaptureError>> {
        if self.done {
            return None;
        }
        if !self.magic_checked {
            self.magic_checked = true;
            if let Err(e) = self.check_magic() {
                self.done = true;
                return Some(Err(e));
            }
        }
        let step = self.records.next_step();
        self.position.bytes_read = self.records.bytes_read();
        match step {
            Step::Message(message) => {
                self.position.messages += 1;
                self.position.last_log_time_ns = Some(message.log_time);
                Some(Ok(message))
            }
            Step::Damaged(damage) => Some(Err(CaptureError::Damaged {
                path: self.path.clone(),
                offset: damage.offset,
                end: damage.end,
                lost_log_time_ns: damage.lost_log_time_ns,
                reason: damage.reason,
            })),
            Step::End => {
                self.done = true;
                None
            }
            Step::Truncated => {
                self.done = true;
                Some(Err(self.truncated()))
            }
            Step::Io(e) => {
                self.done = true;
                Some(Err(self.io_error(e)))
            }
        }
    }

    fn spec_error(&self, message: &mcap::Message<'_>, text: impl Into<String>) -> CaptureError {
        CaptureError::Spec {
            path: self.path.clone(),
            topic: message.channel.topic.clone(),
            log_time_ns: message.log_time,
            message: text.into(),
        }
    }

    /// Checks the channel's encoding and schema name, then decodes the protobuf.
    fn decode_protobuf<M: prost::Message + Default>(
        &self,
        message: &mcap::Message<'_>,
        schema_name: &str,
    ) -> Result<M, CaptureError> {
        let channel = &message.channel;
        if channel.message_encoding != "protobuf" {
            return Err(self.spec_error(
                message,
                format!(
                    "message encoding is {:?}, the format requires \"protobuf\"",
                    channel.message_encoding
                ),
            ));
        }
        match &channel.schema {
            Some(s) if s.name == schema_name && s.encoding == "protobuf" => {}
            Some(s) => {
                return Err(self.spec_error(
                    message,
                    format!(
                        "schema is {:?} ({}), the format requires {schema_name:?} (protobuf)",
                        s.name, s.encoding
                    ),
                ));
            }
            None => {
                return Err(self.spec_error(message, format!("no schema, expected {schema_name}")));
            }
        }
        M::decode(message.data.as_ref())
            .map_err(|e| self.spec_error(message, format!("cannot decode {schema_name}: {e}")))
    }

    /// Decodes, in log order, the messages on `topics` (the others are not decoded)
    /// and hands each event to `on_event`. A damaged stretch is read around and a
    /// message that does not decode is skipped, so what comes after still counts; a
    /// fatal error ends the read with what came before it kept.
    pub fn for_each_event(&mut self, topics: &[&str], mut on_event: impl FnMut(CaptureEvent)) {
        while let Some(next) = self.next_message() {
            let message = match next {
                Ok(m) => m,
                Err(e) if !e.is_fatal() => continue,
                Err(_) => break,
            };
            if !topics.contains(&message.channel.topic.as_str()) {
                continue;
            }
            if let Ok(event) = self.decode(&message) {
                on_event(event);
            }
        }
    }

    /// Decodes one message into an event, updating the calibration state the
    /// reading rules need.
    pub fn decode(&mut self, message: &mcap::Message<'_>) -> Result<CaptureEvent, CaptureError> {
        let log_time_ns = message.log_time;
        let timestamp =
            |t: Option<&foxglove::messages::Timestamp>| t.map_or(log_time_ns, nanos_from_timestamp);
        match message.channel.topic.as_str() {
            topics::LIDAR_CALIBRATION | topics::EO_CALIBRATION => {
                let msg: CameraCalibration =
                    self.decode_protobuf(message, "foxglove.CameraCalibration")?;
                let camera = camera_from_calibration(&msg)
                    .map_err(|e| self.spec_error(message, format!("invalid calibration: {e}")))?;
                if message.channel.topic == topics::LIDAR_CALIBRATION {
                    self.lidar_calibration = Some(camera.clone());
                    Ok(CaptureEvent::LidarCalibration {
                        log_time_ns,
                        camera,
                    })
                } else {
                    self.eo_calibration = Some(camera.clone());
                    Ok(CaptureEvent::EoCalibration {
                        log_time_ns,
                        camera,
                    })
                }
            }
            topics::TF_STATIC => {
                let msg: FrameTransform =
                    self.decode_protobuf(message, "foxglove.FrameTransform")?;
                if msg.parent_frame_id != frame_ids::EO || msg.child_frame_id != frame_ids::LIDAR {
                    return Err(self.spec_error(
                        message,
                        format!(
                            "transform {} -> {} is not the co-boresight extrinsic (parent eo, child lidar)",
                            msg.parent_frame_id, msg.child_frame_id
                        ),
                    ));
                }
                let pose = pose_from_transform(&msg)
                    .map_err(|e| self.spec_error(message, e.to_string()))?;
                Ok(CaptureEvent::EoFromLidar { log_time_ns, pose })
            }
            topics::TEXEL_SENSOR => {
                if message.channel.message_encoding != "json" {
                    return Err(self.spec_error(message, "message encoding must be json"));
                }
                let info: SensorInfo = serde_json::from_slice(&message.data)
                    .map_err(|e| self.spec_error(message, format!("invalid sensor JSON: {e}")))?;
                info.validate()
                    .map_err(|e| self.spec_error(message, e.to_string()))?;
                Ok(CaptureEvent::Sensor { log_time_ns, info })
            }
            topics::TEXEL_ANCHOR => {
                if message.channel.message_encoding != "json" {
                    return Err(self.spec_error(message, "message encoding must be json"));
                }
                let anchor = PoseAnchor::from_json(&message.data)
                    .map_err(|e| self.spec_error(message, e.to_string()))?;
                Ok(CaptureEvent::Anchor(anchor))
            }
            topics::EO_EXPOSURE => {
                if message.channel.message_encoding != "json" {
                    return Err(self.spec_error(message, "message encoding must be json"));
                }
                let record = ExposureRecord::from_json(&message.data)
                    .map_err(|e| self.spec_error(message, e))?;
                self.pending_exposure = Some(record);
                Ok(CaptureEvent::Exposure(record))
            }
            topics::LIDAR_RANGE => {
                let msg: RawImage = self.decode_protobuf(message, "foxglove.RawImage")?;
                self.check_size(
                    message,
                    &msg,
                    self.lidar_calibration.as_ref(),
                    "/lidar/calibration",
                )?;
                let ranges_m =
                    decode_range(&msg.encoding, msg.width, msg.height, msg.step, &msg.data)
                        .map_err(|e| self.spec_error(message, e.to_string()))?;
                Ok(CaptureEvent::Range(RangeFrame {
                    width: msg.width,
                    height: msg.height,
                    ranges_m,
                    timestamp_ns: timestamp(msg.timestamp.as_ref()),
                    seq: message.sequence,
                    intensity: None,
                }))
            }
            topics::LIDAR_INTENSITY => {
                let msg: RawImage = self.decode_protobuf(message, "foxglove.RawImage")?;
                self.check_size(
                    message,
                    &msg,
                    self.lidar_calibration.as_ref(),
                    "/lidar/calibration",
                )?;
                let values =
                    decode_intensity(&msg.encoding, msg.width, msg.height, msg.step, &msg.data)
                        .map_err(|e| self.spec_error(message, e.to_string()))?;
                Ok(CaptureEvent::Intensity {
                    timestamp_ns: timestamp(msg.timestamp.as_ref()),
                    width: msg.width,
                    height: msg.height,
                    values,
                })
            }
            topics::EO_IMAGE => {
                let msg: RawImage = self.decode_protobuf(message, "foxglove.RawImage")?;
                if let Some(cal) = &self.eo_calibration
                    && (cal.width, cal.height) != (msg.width, msg.height)
                {
                    return Err(self.size_error(message, &msg, cal, "/eo/calibration"));
                }
                let rgb = decode_eo(&msg.encoding, msg.width, msg.height, msg.step, &msg.data)
                    .map_err(|e| self.spec_error(message, e.to_string()))?;
                let timestamp_ns = timestamp(msg.timestamp.as_ref());
                Ok(CaptureEvent::Eo(EoFrame {
                    width: msg.width,
                    height: msg.height,
                    rgb,
                    timestamp_ns,
                    exposure: self.take_exposure(timestamp_ns),
                }))
            }
            topics::EO_IMAGE_COMPRESSED => {
                let msg: CompressedImage =
                    self.decode_protobuf(message, "foxglove.CompressedImage")?;
                let (width, height, rgb) = decode_compressed(&msg.format, &msg.data)
                    .map_err(|e| self.spec_error(message, e.to_string()))?;
                if let Some(cal) = &self.eo_calibration
                    && (cal.width, cal.height) != (width, height)
                {
                    return Err(self.spec_error(
                        message,
                        format!(
                            "image is {width}x{height}, /eo/calibration says {}x{}",
                            cal.width, cal.height
                        ),
                    ));
                }
                let timestamp_ns = timestamp(msg.timestamp.as_ref());
                Ok(CaptureEvent::Eo(EoFrame {
                    width,
                    height,
                    rgb,
                    timestamp_ns,
                    exposure: self.take_exposure(timestamp_ns),
                }))
            }
            topic @ (topics::TRUTH_POSE | topics::TEXEL_POSE) => {
                let msg: FrameTransform =
                    self.decode_protobuf(message, "foxglove.FrameTransform")?;
                if msg.parent_frame_id != frame_ids::WORLD || msg.child_frame_id != frame_ids::EO {
                    return Err(self.spec_error(
                        message,
                        format!(
                            "pose {} -> {} must have parent world and child eo",
                            msg.parent_frame_id, msg.child_frame_id
                        ),
                    ));
                }
                let world_from_eo = pose_from_transform(&msg)
                    .map_err(|e| self.spec_error(message, e.to_string()))?;
                Ok(CaptureEvent::Pose {
                    topic: if topic == topics::TRUTH_POSE {
                        PoseTopic::Truth
                    } else {
                        PoseTopic::Texel
                    },
                    timestamp_ns: timestamp(msg.timestamp.as_ref()),
                    world_from_eo,
                })
            }
            other => Ok(CaptureEvent::Other {
                topic: other.to_string(),
                log_time_ns,
            }),
        }
    }

    /// The exposure the last `/eo/exposure` gave the EO frame at `timestamp_ns`, if it
    /// names this frame (a frame without one has no exposure; an exposure without its
    /// frame is dropped when the next frame arrives).
    fn take_exposure(&mut self, timestamp_ns: u64) -> Option<crate::frames::EoExposure> {
        let record = self.pending_exposure.take()?;
        (record.timestamp_ns == timestamp_ns).then_some(record.exposure)
    }

    fn size_error(
        &self,
        message: &mcap::Message<'_>,
        msg: &RawImage,
        calibration: &PinholeCamera,
        calibration_topic: &str,
    ) -> CaptureError {
        self.spec_error(
            message,
            format!(
                "image is {}x{}, {calibration_topic} says {}x{}",
                msg.width, msg.height, calibration.width, calibration.height
            ),
        )
    }

    /// The reading rule for lidar images: a calibration must precede them and match
    /// their size.
    fn check_size(
        &self,
        message: &mcap::Message<'_>,
        msg: &RawImage,
        calibration: Option<&PinholeCamera>,
        calibration_topic: &str,
    ) -> Result<(), CaptureError> {
        match calibration {
            None => Err(self.spec_error(
                message,
                format!("frame before any {calibration_topic} message"),
            )),
            Some(cal) if (cal.width, cal.height) != (msg.width, msg.height) => {
                Err(self.size_error(message, msg, cal, calibration_topic))
            }
            Some(_) => Ok(()),
        }
    }
}

impl<R: Read> Iterator for CaptureReader<R> {
    type Item = Result<CaptureEvent, CaptureError>;

    /// Decoded events in file order. A message that breaks the spec yields an error
    /// and reading goes on; a damaged file yields its error last.
    fn next(&mut self) -> Option<Self::Item> {
        let message = match self.next_message()? {
            Ok(m) => m,
            Err(e) => return Some(Err(e)),
        };
        Some(self.decode(&message))
    }
}
