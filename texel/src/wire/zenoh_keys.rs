//! The key expressions under which a daemon publishes its model on Zenoh
//! (`docs/daemon.md`, "On Zenoh"), and the frame-level look at the wire frames they
//! carry (a frame's kind and scan id, and the same frame under another id) that a
//! subscriber merging several cameras needs without decoding scans.
//!
//! Every camera's keys live under `texel/<site>/<camera>/`:
//!
//! | key | what | how |
//! |---|---|---|
//! | `alive` | liveliness token while the daemon runs | liveliness |
//! | `info` | JSON: names, world frame | queryable |
//! | `model` | the snapshot: `ModelReset`, `ScanListed`s coarse first, `SnapshotComplete` | queryable; put again after a resync |
//! | `listing/<id>` | `ScanListed` | put, reliable |
//! | `pose/<id>` | `PoseRevised` | put, reliable |
//! | `withdrawn/<id>` | `ScanWithdrawn` | put, reliable |
//! | `scan/<id>` | `ScanAdded` (and a `PoseRevised` after it when the scan moved) | put, droppable; queryable |
//! | `status` | `Status` | put |
//!
//! A payload is one or more whole wire frames back to back, so the frame reader of
//! the TCP stream reads it.

use thiserror::Error;

use super::{LENGTH_PREFIX, kind};
use crate::model::ScanId;

/// The first chunk of every key.
pub const ROOT: &str = "texel";

#[derive(Debug, Error, PartialEq, Eq)]
pub enum KeyError {
    #[error("{what} {name:?} cannot be a Zenoh key chunk: {why}")]
    BadChunk {
        what: &'static str,
        name: String,
        why: &'static str,
    },
}

/// Checks a site or camera name: one non-empty key chunk without wildcards or the
/// characters Zenoh reserves.
pub fn check_chunk(what: &'static str, name: &str) -> Result<(), KeyError> {
    let bad = |why| {
        Err(KeyError::BadChunk {
            what,
            name: name.to_string(),
            why,
        })
    };
    if name.is_empty() {
        return bad("it is empty");
    }
    if name.len() > 128 {
        return bad("it is longer than 128 bytes");
    }
    if name
        .chars()
        .any(|c| matches!(c, '/' | '*' | '$' | '?' | '#' | '@') || c.is_whitespace())
    {
        return bad("it holds '/', '*', '$', '?', '#', '@' or white space");
    }
    Ok(())
}

/// A camera pattern for subscribers: a chunk as [`check_chunk`] allows, or `*`, or
/// a chunk with `*` inside it (Zenoh's sub-chunk wildcard).
pub fn check_pattern(what: &'static str, pattern: &str) -> Result<(), KeyError> {
    if pattern == "*" {
        return Ok(());
    }
    check_chunk(what, &pattern.replace('*', "x")).map_err(|_| KeyError::BadChunk {
        what,
        name: pattern.to_string(),
        why: "a pattern is one key chunk: names and '*' only",
    })
}

/// One camera's keys.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraKeys {
    prefix: String,
}

impl CameraKeys {
    pub fn new(site: &str, camera: &str) -> Result<Self, KeyError> {
        check_chunk("site", site)?;
        check_chunk("camera", camera)?;
        Ok(Self {
            prefix: format!("{ROOT}/{site}/{camera}"),
        })
    }

    /// `texel/<site>/<camera>`.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }
    pub fn alive(&self) -> String {
        format!("{}/alive", self.prefix)
    }
    pub fn info(&self) -> String {
        format!("{}/info", self.prefix)
    }
    pub fn model(&self) -> String {
        format!("{}/model", self.prefix)
    }
    pub fn status(&self) -> String {
        format!("{}/status", self.prefix)
    }
    pub fn scan(&self, id: ScanId) -> String {
        format!("{}/scan/{id}", self.prefix)
    }
    /// Every scan's data key (what the queryable answers).
    pub fn scans(&self) -> String {
        format!("{}/scan/*", self.prefix)
    }
    pub fn listing(&self, id: ScanId) -> String {
        format!("{}/listing/{id}", self.prefix)
    }
    pub fn pose(&self, id: ScanId) -> String {
        format!("{}/pose/{id}", self.prefix)
    }
    pub fn withdrawn(&self, id: ScanId) -> String {
        format!("{}/withdrawn/{id}", self.prefix)
    }
    /// Everything this camera publishes.
    pub fn all(&self) -> String {
        format!("{}/**", self.prefix)
    }
}

/// The key expression of every camera a subscriber follows: `texel/<site>/<camera>`
/// with patterns (`*` for all).
pub fn cameras_selector(site: &str, camera: &str) -> Result<String, KeyError> {
    check_pattern("site", site)?;
    check_pattern("camera", camera)?;
    Ok(format!("{ROOT}/{site}/{camera}"))
}

/// What a key under a camera names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Topic {
    Alive,
    Info,
    Model,
    Status,
    Scan(ScanId),
    Listing(ScanId),
    Pose(ScanId),
    Withdrawn(ScanId),
}

/// Splits `texel/<site>/<camera>/<topic>[/<id>]`; `None` for any other key.
pub fn parse_key(key: &str) -> Option<(&str, &str, Topic)> {
    let mut parts = key.split('/');
    if parts.next()? != ROOT {
        return None;
    }
    let site = parts.next()?;
    let camera = parts.next()?;
    let name = parts.next()?;
    let id = parts.next();
    if parts.next().is_some() {
        return None;
    }
    let with_id = |make: fn(ScanId) -> Topic| id?.parse::<ScanId>().ok().map(make);
    let topic = match (name, id) {
        ("alive", None) => Topic::Alive,
        ("info", None) => Topic::Info,
        ("model", None) => Topic::Model,
        ("status", None) => Topic::Status,
        ("scan", Some(_)) => with_id(Topic::Scan)?,
        ("listing", Some(_)) => with_id(Topic::Listing)?,
        ("pose", Some(_)) => with_id(Topic::Pose)?,
        ("withdrawn", Some(_)) => with_id(Topic::Withdrawn)?,
        _ => return None,
    };
    Some((site, camera, topic))
}

/// The kinds whose first field is a scan id (`u64` right after the kind byte).
fn kind_has_scan_id(k: u8) -> bool {
    matches!(
        k,
        kind::SCAN_ADDED
            | kind::POSE_REVISED
            | kind::SCAN_LISTED
            | kind::SCAN_WITHDRAWN
            | kind::SCAN_UNAVAILABLE
            | kind::SCAN_EXPOSURE
    )
}

/// A whole frame's kind byte and, for the kinds that name a scan first, its id;
/// `None` when `frame` is not exactly one whole frame.
pub fn frame_head(frame: &[u8]) -> Option<(u8, Option<ScanId>)> {
    let len = frame.get(..LENGTH_PREFIX)?;
    let body_len = u32::from_le_bytes(len.try_into().ok()?) as usize;
    if body_len == 0 || frame.len() != LENGTH_PREFIX + body_len {
        return None;
    }
    let k = frame[LENGTH_PREFIX];
    if !kind_has_scan_id(k) {
        return Some((k, None));
    }
    let id = frame.get(LENGTH_PREFIX + 1..LENGTH_PREFIX + 9)?;
    Some((k, Some(u64::from_le_bytes(id.try_into().ok()?))))
}

/// The same frame naming scan `id` instead (a subscriber gives each camera's scans
/// ids of their own); `None` when the frame names no scan.
pub fn with_scan_id(frame: &[u8], id: ScanId) -> Option<Vec<u8>> {
    frame_head(frame)?.1?;
    let mut out = frame.to_vec();
    out[LENGTH_PREFIX + 1..LENGTH_PREFIX + 9].copy_from_slice(&id.to_le_bytes());
    Some(out)
}

/// Splits a payload of frames back to back; `None` when it does not end on a frame
/// boundary or a frame is empty.
pub fn split_frames(payload: &[u8]) -> Option<Vec<&[u8]>> {
    let mut frames = Vec::new();
    let mut rest = payload;
    while !rest.is_empty() {
        let len = rest.get(..LENGTH_PREFIX)?;
        let body_len = u32::from_le_bytes(len.try_into().ok()?) as usize;
        let end = LENGTH_PREFIX.checked_add(body_len)?;
        if body_len == 0 || end > rest.len() {
            return None;
        }
        frames.push(&rest[..end]);
        rest = &rest[end..];
    }
    Some(frames)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::pose_from_parts;
    use crate::wire::Message;

    #[test]
    fn keys_round_trip_through_parse() {
        let keys = CameraKeys::new("quarry", "cam-2").unwrap();
        assert_eq!(keys.scan(17), "texel/quarry/cam-2/scan/17");
        for (key, topic) in [
            (keys.alive(), Topic::Alive),
            (keys.info(), Topic::Info),
            (keys.model(), Topic::Model),
            (keys.status(), Topic::Status),
            (keys.scan(3), Topic::Scan(3)),
            (keys.listing(4), Topic::Listing(4)),
            (keys.pose(5), Topic::Pose(5)),
            (keys.withdrawn(u64::MAX), Topic::Withdrawn(u64::MAX)),
        ] {
            assert_eq!(parse_key(&key), Some(("quarry", "cam-2", topic)), "{key}");
        }
        for bad in [
            "texel/a/b",
            "texel/a/b/scan",
            "texel/a/b/scan/x",
            "texel/a/b/scan/1/2",
            "other/a/b/info",
            "texel/a/b/model/1",
        ] {
            assert_eq!(parse_key(bad), None, "{bad}");
        }
    }

    #[test]
    fn names_that_would_change_the_key_are_refused() {
        for bad in ["", "a/b", "*", "a b", "$x", "a?", "#", "@x"] {
            assert!(CameraKeys::new("s", bad).is_err(), "{bad:?}");
        }
        assert!(check_pattern("camera", "*").is_ok());
        assert!(check_pattern("camera", "cam-*").is_ok());
        assert!(check_pattern("camera", "a/*").is_err());
        assert!(check_pattern("camera", "**").is_ok());
    }

    #[test]
    fn frame_ids_are_read_and_rewritten_in_place() {
        let pose = pose_from_parts([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0]).unwrap();
        let frame = Message::PoseRevised {
            id: 41,
            world_from_scan: pose,
        }
        .encode()
        .unwrap();
        assert_eq!(frame_head(&frame), Some((kind::POSE_REVISED, Some(41))));
        let moved = with_scan_id(&frame, (3 << 24) | 41).unwrap();
        let (decoded, used) = crate::wire::decode_frame(&moved, &crate::wire::Limits::FROM_SERVER)
            .unwrap()
            .unwrap();
        assert_eq!(used, moved.len());
        assert_eq!(
            decoded,
            Message::PoseRevised {
                id: (3 << 24) | 41,
                world_from_scan: pose
            }
        );
        let status = Message::ModelReset { scan_count: 2 }.encode().unwrap();
        assert_eq!(frame_head(&status), Some((kind::MODEL_RESET, None)));
        assert_eq!(with_scan_id(&status, 1), None);
        // Not exactly one frame.
        assert_eq!(frame_head(&frame[..frame.len() - 1]), None);
        let mut two = frame.clone();
        two.extend_from_slice(&status);
        assert_eq!(frame_head(&two), None);
        assert_eq!(split_frames(&two).unwrap().len(), 2);
        assert_eq!(split_frames(&two[..two.len() - 1]), None);
        assert_eq!(split_frames(&[0, 0, 0, 0]), None);
        assert_eq!(split_frames(&[]).unwrap().len(), 0);
    }
}
