//! `/texel/anchor`, the keyframe a registered frame hangs from, and the registered
//! pose of every frame a capture records: the frame's own last `/texel/pose`, or,
//! when it hangs from another frame, that keyframe's last `/texel/pose` composed
//! with the frame's pose relative to it. A loop closure then records the keyframes
//! it moved, not every frame that moved with them, so the pose stream grows with
//! the frames and not with their square; a capture without anchors reads as before.

use std::collections::HashMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{CaptureError, CaptureEvent, CaptureReader, PoseTopic, topics};

use crate::pose::{Pose, PoseError, pose_from_parts, pose_to_parts};

/// Schema name and JSON schema of `/texel/anchor`.
pub const ANCHOR_SCHEMA_NAME: &str = "texel.Anchor";
pub const ANCHOR_JSON_SCHEMA: &str = r##"{
  "title": "texel.Anchor",
  "description": "The registered frame at `timestamp` hangs from the keyframe at `keyframe`: world_from_eo(frame) = world_from_eo(keyframe) * keyframe_from_eo, where world_from_eo(keyframe) is the keyframe's last /texel/pose.",
  "type": "object",
  "properties": {
    "timestamp": {"$ref": "#/$defs/time"},
    "keyframe": {"$ref": "#/$defs/time"},
    "translation": {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}},
    "rotation": {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}, "w": {"type": "number"}}}
  },
  "required": ["timestamp", "keyframe", "translation", "rotation"],
  "$defs": {
    "time": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}, "required": ["sec", "nsec"]}
  }
}"##;

/// The frame at `timestamp_ns` hangs from the keyframe at `keyframe_timestamp_ns`
/// (itself, for a keyframe) at `keyframe_from_eo`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseAnchor {
    pub timestamp_ns: u64,
    pub keyframe_timestamp_ns: u64,
    pub keyframe_from_eo: Pose,
}

/// Why a `/texel/anchor` message is not one.
#[derive(Debug, thiserror::Error)]
pub enum AnchorError {
    #[error("invalid anchor JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("{field}: nsec {nsec} is not below 1e9")]
    Nanoseconds { field: &'static str, nsec: u64 },
    #[error("{field}: {sec} s is beyond what nanoseconds in 64 bits hold")]
    Seconds { field: &'static str, sec: u64 },
    #[error("keyframe_from_eo: {0}")]
    Pose(#[from] PoseError),
}

/// Foxglove's time convention (`sec`, `nsec`): exact in every JSON reader, where a
/// nanosecond count past 2^53 is not.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub(super) struct Time {
    sec: u64,
    nsec: u64,
}

impl Time {
    pub(super) fn from_nanos(ns: u64) -> Self {
        Self {
            sec: ns / 1_000_000_000,
            nsec: ns % 1_000_000_000,
        }
    }

    pub(super) fn to_nanos(self, field: &'static str) -> Result<u64, AnchorError> {
        if self.nsec >= 1_000_000_000 {
            return Err(AnchorError::Nanoseconds {
                field,
                nsec: self.nsec,
            });
        }
        self.sec
            .checked_mul(1_000_000_000)
            .and_then(|s| s.checked_add(self.nsec))
            .ok_or(AnchorError::Seconds {
                field,
                sec: self.sec,
            })
    }
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct Vector3 {
    x: f64,
    y: f64,
    z: f64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct Quaternion {
    x: f64,
    y: f64,
    z: f64,
    w: f64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct AnchorJson {
    timestamp: Time,
    keyframe: Time,
    translation: Vector3,
    rotation: Quaternion,
}

impl PoseAnchor {
    /// The message's JSON.
    pub fn to_json(&self) -> Result<Vec<u8>, AnchorError> {
        let (t, q) = pose_to_parts(&self.keyframe_from_eo);
        let json = AnchorJson {
            timestamp: Time::from_nanos(self.timestamp_ns),
            keyframe: Time::from_nanos(self.keyframe_timestamp_ns),
            translation: Vector3 {
                x: t[0],
                y: t[1],
                z: t[2],
            },
            rotation: Quaternion {
                x: q[0],
                y: q[1],
                z: q[2],
                w: q[3],
            },
        };
        Ok(serde_json::to_vec(&json)?)
    }

    /// Parses a message (unknown fields are ignored, as the format's reading rules
    /// ask of JSON topics; a rotation is normalised, a zero or non-finite one is an
    /// error).
    pub fn from_json(data: &[u8]) -> Result<Self, AnchorError> {
        let json: AnchorJson = serde_json::from_slice(data)?;
        let t = json.translation;
        let q = json.rotation;
        Ok(Self {
            timestamp_ns: json.timestamp.to_nanos("timestamp")?,
            keyframe_timestamp_ns: json.keyframe.to_nanos("keyframe")?,
            keyframe_from_eo: pose_from_parts([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])?,
        })
    }
}

/// The registered pose of every frame of a capture, from its `/texel/pose` and
/// `/texel/anchor` messages in any order (for each kind, a later message about the
/// same frame supersedes an earlier one).
#[derive(Debug, Clone, Default)]
pub struct RegisteredPoses {
    /// Frame timestamps in the order of their first `/texel/pose` (the order in
    /// which registration gave them ids).
    order: Vec<u64>,
    latest: HashMap<u64, Pose>,
    anchors: HashMap<u64, (u64, Pose)>,
}

impl RegisteredPoses {
    /// A `/texel/pose` message.
    pub fn insert_pose(&mut self, timestamp_ns: u64, world_from_eo: Pose) {
        if self.latest.insert(timestamp_ns, world_from_eo).is_none() {
            self.order.push(timestamp_ns);
        }
    }

    /// A `/texel/anchor` message.
    pub fn insert_anchor(&mut self, anchor: PoseAnchor) {
        self.anchors.insert(
            anchor.timestamp_ns,
            (anchor.keyframe_timestamp_ns, anchor.keyframe_from_eo),
        );
    }

    /// The registered pose of the frame at `timestamp_ns`: only a frame with a
    /// `/texel/pose` of its own is registered. A frame hanging from a keyframe the
    /// capture has no pose for (a recording cut short) keeps its own.
    pub fn get(&self, timestamp_ns: u64) -> Option<Pose> {
        let own = self.latest.get(&timestamp_ns)?;
        let derived = self
            .anchors
            .get(&timestamp_ns)
            .filter(|(keyframe, _)| *keyframe != timestamp_ns)
            .and_then(|(keyframe, keyframe_from_eo)| {
                Some(self.latest.get(keyframe)? * keyframe_from_eo)
            });
        Some(derived.unwrap_or(*own))
    }

    /// Registered frame timestamps, in the order of their first `/texel/pose`.
    pub fn timestamps(&self) -> &[u64] {
        &self.order
    }

    /// Every registered frame and its pose, in the order of `timestamps`.
    pub fn iter(&self) -> impl Iterator<Item = (u64, Pose)> + '_ {
        self.order.iter().filter_map(|&t| Some((t, self.get(t)?)))
    }

    pub fn len(&self) -> usize {
        self.order.len()
    }

    pub fn is_empty(&self) -> bool {
        self.order.is_empty()
    }

    /// Takes a capture's event if it is a `/texel/pose` or a `/texel/anchor`.
    pub fn take_event(&mut self, event: &CaptureEvent) {
        match event {
            CaptureEvent::Pose {
                topic: PoseTopic::Texel,
                timestamp_ns,
                world_from_eo,
            } => self.insert_pose(*timestamp_ns, *world_from_eo),
            CaptureEvent::Anchor(anchor) => self.insert_anchor(*anchor),
            _ => {}
        }
    }

    /// Reads a capture's `/texel/pose` and `/texel/anchor` messages into the table
    /// (only those topics are decoded). Those after a damaged stretch still count; a
    /// fatal error ends the read with what came before it kept.
    pub fn read_capture(&mut self, path: &Path) -> Result<(), CaptureError> {
        let mut reader = CaptureReader::open(path)?;
        reader.for_each_event(&[topics::TEXEL_POSE, topics::TEXEL_ANCHOR], |event| {
            self.take_event(&event);
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;
    use crate::pose::pose_difference;
    use nalgebra::{Translation3, UnitQuaternion};
    use proptest::prelude::*;

    fn pose(x: f64, y: f64, yaw: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(x, y, 0.5),
            UnitQuaternion::from_euler_angles(0.1, -0.2, yaw),
        )
    }

    #[test]
    fn an_anchor_round_trips_through_json_exactly() {
        let anchor = PoseAnchor {
            timestamp_ns: 1_700_000_000_123_456_789,
            keyframe_timestamp_ns: 1_699_999_999_999_999_999,
            keyframe_from_eo: pose(1.25, -3.5, 2.9),
        };
        let back = PoseAnchor::from_json(&anchor.to_json().unwrap()).unwrap();
        // The schema the channel carries is JSON itself.
        serde_json::from_str::<serde_json::Value>(ANCHOR_JSON_SCHEMA).unwrap();
        assert_eq!(back.timestamp_ns, anchor.timestamp_ns);
        assert_eq!(back.keyframe_timestamp_ns, anchor.keyframe_timestamp_ns);
        let (angle, dist) = pose_difference(&back.keyframe_from_eo, &anchor.keyframe_from_eo);
        assert!(angle < 1e-15 && dist < 1e-15, "{angle} {dist}");
    }

    #[test]
    fn a_bad_anchor_names_what_is_wrong() {
        let cases = [
            (&br#"{"timestamp":{"sec":1,"nsec":0}}"#[..], "missing field"),
            (
                br#"{"timestamp":{"sec":1,"nsec":1000000000},"keyframe":{"sec":0,"nsec":0},"translation":{"x":0,"y":0,"z":0},"rotation":{"x":0,"y":0,"z":0,"w":1}}"#,
                "timestamp: nsec",
            ),
            (
                br#"{"timestamp":{"sec":1,"nsec":0},"keyframe":{"sec":18446744073,"nsec":999999999},"translation":{"x":0,"y":0,"z":0},"rotation":{"x":0,"y":0,"z":0,"w":1}}"#,
                "keyframe: 18446744073 s",
            ),
            (
                br#"{"timestamp":{"sec":1,"nsec":0},"keyframe":{"sec":0,"nsec":0},"translation":{"x":0,"y":0,"z":0},"rotation":{"x":0,"y":0,"z":0,"w":0}}"#,
                "keyframe_from_eo",
            ),
            (&b"{"[..], "invalid anchor JSON"),
        ];
        for (data, expected) in cases {
            let e = PoseAnchor::from_json(data).unwrap_err().to_string();
            assert!(e.contains(expected), "{e} lacks {expected}");
        }
    }

    #[test]
    fn a_capture_without_anchors_reads_its_last_poses() {
        let mut p = RegisteredPoses::default();
        p.insert_pose(30, pose(0.0, 0.0, 0.0));
        p.insert_pose(10, pose(1.0, 0.0, 0.0)); // registered after 30 (a retry)
        p.insert_pose(30, pose(3.0, 0.0, 0.0)); // a revision
        assert_eq!(p.timestamps(), &[30, 10]);
        assert_eq!(p.get(30), Some(pose(3.0, 0.0, 0.0)));
        assert_eq!(p.get(10), Some(pose(1.0, 0.0, 0.0)));
        assert_eq!(p.get(20), None);
    }

    #[test]
    fn a_frame_without_its_keyframes_pose_keeps_its_own() {
        let mut p = RegisteredPoses::default();
        p.insert_pose(20, pose(2.0, 0.0, 0.0));
        p.insert_anchor(PoseAnchor {
            timestamp_ns: 20,
            keyframe_timestamp_ns: 10,
            keyframe_from_eo: pose(9.0, 9.0, 1.0),
        });
        assert_eq!(p.get(20), Some(pose(2.0, 0.0, 0.0)));
        // An anchor alone does not register a frame.
        p.insert_anchor(PoseAnchor {
            timestamp_ns: 40,
            keyframe_timestamp_ns: 20,
            keyframe_from_eo: Pose::identity(),
        });
        assert_eq!(p.get(40), None);
        assert_eq!(p.len(), 1);
    }

    /// A registration's history: keyframes and the frames hanging from them, moved
    /// by loop closures and re-hung, recorded as the daemon records it (a frame's
    /// pose when placed, its anchor, a keyframe's pose when it moves); the poses
    /// read back are the registration's current ones.
    #[derive(Debug, Clone)]
    enum Step {
        Place {
            keyframe: usize,
            offset: (f64, f64, f64),
            promote: bool,
        },
        Move {
            keyframe: usize,
            by: (f64, f64, f64),
        },
        Rehang {
            frame: usize,
            keyframe: usize,
        },
    }

    fn step() -> impl Strategy<Value = Step> {
        let offset = (-3.0..3.0f64, -3.0..3.0f64, -3.0..3.0f64);
        prop_oneof![
            (any::<usize>(), offset.clone(), any::<bool>()).prop_map(
                |(keyframe, offset, promote)| {
                    Step::Place {
                        keyframe,
                        offset,
                        promote,
                    }
                }
            ),
            (any::<usize>(), offset).prop_map(|(keyframe, by)| Step::Move { keyframe, by }),
            (any::<usize>(), any::<usize>())
                .prop_map(|(frame, keyframe)| Step::Rehang { frame, keyframe }),
        ]
    }

    proptest! {
        #[test]
        fn poses_read_back_are_the_registrations_current_ones(
            steps in proptest::collection::vec(step(), 1..80)
        ) {
            // The registration: keyframe poses, and per frame (keyframe, relative pose).
            let mut keyframes: Vec<(u64, Pose)> = vec![(0, pose(0.0, 0.0, 0.0))];
            let mut frames: Vec<(u64, usize, Pose)> = vec![(0, 0, Pose::identity())];
            let mut recorded = RegisteredPoses::default();
            recorded.insert_pose(0, keyframes[0].1);
            let anchor = |frame: u64, kf: u64, rel: Pose| PoseAnchor {
                timestamp_ns: frame,
                keyframe_timestamp_ns: kf,
                keyframe_from_eo: rel,
            };
            recorded.insert_anchor(anchor(0, 0, Pose::identity()));
            for s in steps {
                match s {
                    Step::Place { keyframe, offset: (x, y, yaw), promote } => {
                        let t = frames.len() as u64 * 10;
                        let k = keyframe % keyframes.len();
                        let world = keyframes[k].1 * pose(x, y, yaw);
                        recorded.insert_pose(t, world);
                        if promote {
                            keyframes.push((t, world));
                            frames.push((t, keyframes.len() - 1, Pose::identity()));
                            recorded.insert_anchor(anchor(t, t, Pose::identity()));
                        } else {
                            frames.push((t, k, pose(x, y, yaw)));
                            recorded.insert_anchor(anchor(t, keyframes[k].0, pose(x, y, yaw)));
                        }
                    }
                    Step::Move { keyframe, by: (x, y, yaw) } => {
                        let k = keyframe % keyframes.len();
                        keyframes[k].1 = pose(x, y, yaw) * keyframes[k].1;
                        recorded.insert_pose(keyframes[k].0, keyframes[k].1);
                    }
                    Step::Rehang { frame, keyframe } => {
                        let f = frame % frames.len();
                        let k = keyframe % keyframes.len();
                        let (t, old, rel) = frames[f];
                        if keyframes[old].0 == t {
                            continue; // a keyframe hangs from itself for good
                        }
                        let world = keyframes[old].1 * rel;
                        let rel = keyframes[k].1.inverse() * world;
                        frames[f] = (t, k, rel);
                        recorded.insert_anchor(anchor(t, keyframes[k].0, rel));
                    }
                }
            }
            prop_assert_eq!(recorded.len(), frames.len());
            for &(t, k, rel) in &frames {
                let expected = keyframes[k].1 * rel;
                let got = recorded.get(t).unwrap();
                let (angle, dist) = pose_difference(&got, &expected);
                prop_assert!(angle < 1e-9 && dist < 1e-9, "frame {} off by {} rad {} m", t, angle, dist);
            }
        }
    }
}
