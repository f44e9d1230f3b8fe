//! The Foxglove channels of a live session, in the session's own `foxglove::Context`
//! (so sessions in one process never mix), the messages they latch for late joiners,
//! and the server listener that hands a new subscriber what it latched.

use std::sync::{Arc, Mutex, MutexGuard};

use foxglove::messages::{CameraCalibration, FrameTransform, RawImage, SceneUpdate};
use foxglove::websocket::{ChannelView, Client, ServerListener};
use foxglove::{Channel, ChannelId, Context, RawChannel, Schema, SinkId};
use texel::capture::{SENSOR_JSON_SCHEMA, SENSOR_SCHEMA_NAME, topics};
use tokio::sync::mpsc;

use super::FoxgloveLiveError;

/// The live-only topics.
pub mod live_topics {
    /// `foxglove.SceneUpdate`: one entity per served scan, its textured mesh as a
    /// binary glTF model primitive.
    pub const SCAN: &str = "/texel/scan";
    /// JSON: the daemon's periodic status.
    pub const STATUS: &str = "/texel/status";
}

/// Schema name and JSON schema of `/texel/status`.
pub const STATUS_SCHEMA_NAME: &str = "texel.Status";
const STATUS_JSON_SCHEMA: &str = r#"{
  "title": "texel.Status",
  "description": "The daemon's periodic status (docs/daemon.md, Status), and what the Foxglove server dropped",
  "type": "object"
}"#;

/// What a subscriber that comes late still needs: the sensor's calibrations and
/// extrinsic, its facts, and the last pose of each pose topic.
#[derive(Default)]
pub struct Latched {
    pub lidar_calibration: Option<CameraCalibration>,
    pub eo_calibration: Option<CameraCalibration>,
    pub tf_static: Option<FrameTransform>,
    pub sensor: Option<Vec<u8>>,
    pub texel_pose: Option<FrameTransform>,
    pub truth_pose: Option<FrameTransform>,
}

/// Every channel of the live session.
pub struct Channels {
    pub lidar_calibration: Channel<CameraCalibration>,
    pub eo_calibration: Channel<CameraCalibration>,
    pub tf_static: Channel<FrameTransform>,
    /// `/texel/sensor`, JSON as in the recording.
    pub sensor: Arc<RawChannel>,
    pub lidar_range: Channel<RawImage>,
    pub lidar_intensity: Channel<RawImage>,
    pub eo_image: Channel<RawImage>,
    pub truth_pose: Channel<FrameTransform>,
    pub texel_pose: Channel<FrameTransform>,
    pub scan: Channel<SceneUpdate>,
    pub status: Arc<RawChannel>,
    latched: Mutex<Latched>,
    /// The context the channels live in: channels close when it is dropped.
    _context: Arc<Context>,
}

fn json_channel(
    ctx: &Arc<Context>,
    topic: &str,
    schema_name: &str,
    schema: &'static str,
) -> Result<Arc<RawChannel>, FoxgloveLiveError> {
    ctx.channel_builder(topic)
        .message_encoding("json")
        .schema(Schema::new(schema_name, "jsonschema", schema.as_bytes()))
        .build_raw()
        .map_err(|e| FoxgloveLiveError::Channel {
            topic: topic.to_string(),
            message: e.to_string(),
        })
}

impl Channels {
    /// Creates the channels in `ctx` (before the server starts, so every client is
    /// told of them when it connects).
    pub fn new(ctx: &Arc<Context>) -> Result<Self, FoxgloveLiveError> {
        Ok(Self {
            lidar_calibration: ctx.channel_builder(topics::LIDAR_CALIBRATION).build(),
            eo_calibration: ctx.channel_builder(topics::EO_CALIBRATION).build(),
            tf_static: ctx.channel_builder(topics::TF_STATIC).build(),
            sensor: json_channel(
                ctx,
                topics::TEXEL_SENSOR,
                SENSOR_SCHEMA_NAME,
                SENSOR_JSON_SCHEMA,
            )?,
            lidar_range: ctx.channel_builder(topics::LIDAR_RANGE).build(),
            lidar_intensity: ctx.channel_builder(topics::LIDAR_INTENSITY).build(),
            eo_image: ctx.channel_builder(topics::EO_IMAGE).build(),
            truth_pose: ctx.channel_builder(topics::TRUTH_POSE).build(),
            texel_pose: ctx.channel_builder(topics::TEXEL_POSE).build(),
            scan: ctx.channel_builder(live_topics::SCAN).build(),
            status: json_channel(
                ctx,
                live_topics::STATUS,
                STATUS_SCHEMA_NAME,
                STATUS_JSON_SCHEMA,
            )?,
            latched: Mutex::new(Latched::default()),
            _context: Arc::clone(ctx),
        })
    }

    pub fn latched(&self) -> MutexGuard<'_, Latched> {
        self.latched
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Sends what `channel` latched to one subscriber (`sink`): never waits (the
    /// foxglove crate queues it for that client).
    pub fn relog_latched(&self, channel: ChannelId, sink: SinkId) {
        let latched = self.latched();
        let to = Some(sink);
        let calibration = |c: &Channel<CameraCalibration>, m: &Option<CameraCalibration>| {
            if let Some(m) = m.as_ref().filter(|_| c.id() == channel) {
                c.log_to_sink(m, to);
            }
        };
        calibration(&self.lidar_calibration, &latched.lidar_calibration);
        calibration(&self.eo_calibration, &latched.eo_calibration);
        for (c, m) in [
            (&self.tf_static, &latched.tf_static),
            (&self.texel_pose, &latched.texel_pose),
            (&self.truth_pose, &latched.truth_pose),
        ] {
            if let Some(m) = m.as_ref().filter(|_| c.id() == channel) {
                c.log_to_sink(m, to);
            }
        }
        if let Some(json) = latched
            .sensor
            .as_ref()
            .filter(|_| self.sensor.id() == channel)
        {
            self.sensor.log_to_sink(json, to);
        }
    }
}

/// Told by the server of each subscription: a latched topic is sent its latched
/// messages at once; a subscriber of `/texel/scan` is handed to the scene thread,
/// which sends it the whole served model.
pub struct Listener {
    pub channels: Arc<Channels>,
    /// New `/texel/scan` subscribers (bounded; a full queue drops the request,
    /// logged: that subscriber then sees only later scans until it subscribes again).
    pub joins: mpsc::Sender<SinkId>,
}

impl ServerListener for Listener {
    fn on_subscribe(&self, client: Client, channel: ChannelView) {
        let Some(sink) = client.sink_id() else {
            return;
        };
        if channel.id() == self.channels.scan.id() {
            if self.joins.try_send(sink).is_err() {
                tracing::warn!(
                    "foxglove: too many {} subscriptions at once; client {:?} is sent only \
                     later scans (subscribe again for the whole model)",
                    live_topics::SCAN,
                    client.id()
                );
            }
        } else {
            self.channels.relog_latched(channel.id(), sink);
        }
    }
}
