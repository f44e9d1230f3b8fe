//! The frames thread: what the recorder is given (the live tap's copy), offered to
//! Foxglove as the recording holds it: the sensor model as `/lidar/calibration`,
//! `/eo/calibration`, `/tf_static` and `/texel/sensor` (latched for late joiners),
//! each range frame as `/lidar/range` (32FC1 metres, and `/lidar/intensity`), each EO
//! frame as `/eo/image` (rgb8), and every true and estimated pose as `/truth/pose` and
//! `/texel/pose` (the last of each latched). The messages are built by
//! `texel::capture::messages`, as the capture writer builds them.
//!
//! A frame is converted only while someone subscribes to its topic; the foxglove
//! crate then queues the message for each subscriber without waiting.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use texel::SensorModel;
use texel::capture::messages::{self, FrameMessageError};
use texel::capture::{CameraRole, EoEncoding, PoseTopic, RangeEncoding};

use super::LiveCounters;
use super::channels::Channels;
use crate::pipeline::tap::TapReceiver;
use crate::record::RecordItem;

/// Runs until every producer of the tap has gone (the pipeline drained).
pub fn run(mut tap: TapReceiver, channels: Arc<Channels>, counters: Arc<LiveCounters>) {
    let mut sensor: Option<Arc<SensorModel>> = None;
    // Calibrations are stamped with the latest frame time, as the recorder does.
    let mut latest_ns = 0u64;
    while let Some(item) = tap.blocking_recv() {
        match item {
            RecordItem::Sensor(model) => {
                if sensor.as_deref() != Some(&*model) {
                    publish_sensor(&channels, &model, latest_ns, &counters);
                    sensor = Some(model);
                }
            }
            RecordItem::Range(frame) => {
                latest_ns = latest_ns.max(frame.timestamp_ns);
                let c = &channels;
                if c.lidar_range.has_sinks() || c.lidar_intensity.has_sinks() {
                    match messages::range_images(&frame, RangeEncoding::F32Metres) {
                        Ok((range, intensity)) => {
                            c.lidar_range.log(&range);
                            if let Some(intensity) = intensity {
                                c.lidar_intensity.log(&intensity);
                            }
                            counters.frames_sent.fetch_add(1, Ordering::Relaxed);
                        }
                        Err(e) => frame_error(&counters, &e),
                    }
                }
            }
            RecordItem::Eo(frame) => {
                latest_ns = latest_ns.max(frame.timestamp_ns);
                if channels.eo_image.has_sinks() {
                    match messages::eo_image(&frame, EoEncoding::Rgb8) {
                        Ok(image) => {
                            channels.eo_image.log(&image);
                            counters.frames_sent.fetch_add(1, Ordering::Relaxed);
                        }
                        Err(e) => frame_error(&counters, &e),
                    }
                }
            }
            RecordItem::Pose {
                topic,
                timestamp_ns,
                world_from_eo,
                ..
            } => {
                // A revision carries its frame's timestamp, as in the recording.
                let message = messages::world_from_eo(&world_from_eo, timestamp_ns);
                let mut latched = channels.latched();
                let (channel, slot) = match topic {
                    PoseTopic::Texel => (&channels.texel_pose, &mut latched.texel_pose),
                    PoseTopic::Truth => (&channels.truth_pose, &mut latched.truth_pose),
                };
                channel.log(&message);
                *slot = Some(message);
            }
            RecordItem::Anchor(_) | RecordItem::Tick => {}
        }
    }
}

/// Publishes (and latches) a sensor model's calibrations, extrinsic and facts.
fn publish_sensor(
    channels: &Channels,
    model: &SensorModel,
    timestamp_ns: u64,
    counters: &LiveCounters,
) {
    let lidar = messages::calibration(model, CameraRole::Lidar, timestamp_ns);
    let eo = messages::calibration(model, CameraRole::Eo, timestamp_ns);
    let tf = messages::eo_from_lidar(&model.eo_from_lidar, timestamp_ns);
    let json = match messages::sensor_json(model) {
        Ok(json) => Some(json),
        Err(e) => {
            counters.frame_errors.fetch_add(1, Ordering::Relaxed);
            tracing::warn!("foxglove: the sensor's facts cannot be written as JSON: {e}");
            None
        }
    };
    // Latched before it is logged, under one lock: a subscriber that comes in
    // between is sent it once, not never.
    let mut latched = channels.latched();
    channels.lidar_calibration.log(&lidar);
    channels.eo_calibration.log(&eo);
    channels.tf_static.log(&tf);
    if let Some(json) = &json {
        channels.sensor.log(json);
    }
    latched.lidar_calibration = Some(lidar);
    latched.eo_calibration = Some(eo);
    latched.tf_static = Some(tf);
    latched.sensor = json;
}

fn frame_error(counters: &LiveCounters, e: &FrameMessageError) {
    if counters.frame_errors.fetch_add(1, Ordering::Relaxed) == 0 {
        tracing::warn!("foxglove: a frame cannot be offered (counted as frame_errors): {e}");
    }
}
