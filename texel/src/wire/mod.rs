//! The viewer stream's wire format (`docs/wire-protocol.md`, version 2): the messages
//! between the daemon and its viewers (scans listed, then fetched by id), their encoding, and a sans-I/O decoder that
//! tells "incomplete, read more" (`Ok(None)`) from "invalid" (`Err`), checking every
//! length against a limit and against the bytes present before allocating for it.
//!
//! A frame is `u32 body_len` (little-endian, bytes after this field), `u8 kind`, then
//! the kind's fields. The server and the client use the same functions with different
//! [`Limits`]: a server accepts only small client messages.

mod bytes_in;
pub mod client;
mod fetch;
mod listing;
mod radiance;
mod scan;
mod status;
mod tile_catalog;
mod tiles;
pub mod zenoh_keys;

pub use fetch::{DEFAULT_MAX_IN_FLIGHT, FetchPlan};
pub use listing::LISTING_LEN;
pub use radiance::EO_RESPONSE_LEN;
pub use scan::{
    MAX_GRID_SIDE, MAX_TEXTURE_BYTES, Texture, TextureFormat, TextureRef, WireScan, WireScanRef,
    check_sendable,
};
pub use status::{
    LodStatus, ModelStatus, QueueStatus, RecordingStatus, SourceStatus, StageLatency, Status,
};
pub use tile_catalog::{TileCatalog, TileEvent};
pub use tiles::{MAX_TILE_DATA_BYTES, TILE_ID_LEN, TILE_LISTED_LEN, WireTile};

use thiserror::Error;

use crate::EoExposure;
use crate::model::{ScanId, ScanListing};
use crate::pose::{Pose, pose_from_parts, pose_to_parts};
use crate::tile::{TileId, TileListing};
use bytes_in::{BodyReader, PutLe};

/// The protocol version this module speaks: 3 adds the level-of-detail tree's tiles
/// to version 2, 4 the scans' exposures and the camera's response curve (radiance).
pub const PROTOCOL_VERSION: u16 = 4;
/// The oldest version a server still serves (a version 2 client gets everything but
/// the tiles).
pub const MIN_PROTOCOL_VERSION: u16 = 2;
/// Opens every client hello, so that a stray connection (HTTP, another protocol) is
/// refused at its first bytes.
pub const CLIENT_MAGIC: [u8; 4] = *b"TXLV";
/// Bytes before a frame's body: the `u32` length.
pub const LENGTH_PREFIX: usize = 4;
/// The longest token, client name, server name or session name.
pub const MAX_NAME_LEN: usize = 256;
/// The longest refusal or goodbye reason.
pub const MAX_REASON_LEN: usize = 1024;
/// The longest status JSON.
pub const MAX_STATUS_LEN: usize = 256 * 1024;
/// Frames a client may send are at most this long (a hello with its token; a request
/// is 13 bytes).
pub const MAX_CLIENT_FRAME_LEN: u32 = 4096;
/// Frames a server may send are at most this long: a scan of the largest lidar grid
/// (1024², 2 triangles per cell) with the largest texture.
pub const MAX_SERVER_FRAME_LEN: u32 = 160 * 1024 * 1024;

/// How long a frame a decoder accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    pub max_frame_len: u32,
}

impl Limits {
    /// What a server accepts from clients.
    pub const FROM_CLIENT: Self = Self {
        max_frame_len: MAX_CLIENT_FRAME_LEN,
    };
    /// What a client accepts from a server.
    pub const FROM_SERVER: Self = Self {
        max_frame_len: MAX_SERVER_FRAME_LEN,
    };
}

/// Message kinds on the wire.
pub mod kind {
    pub const CLIENT_HELLO: u8 = 0x01;
    pub const SERVER_HELLO: u8 = 0x02;
    pub const REFUSED: u8 = 0x03;
    pub const MODEL_RESET: u8 = 0x10;
    pub const SNAPSHOT_COMPLETE: u8 = 0x11;
    pub const SCAN_ADDED: u8 = 0x12;
    pub const POSE_REVISED: u8 = 0x13;
    pub const SCAN_LISTED: u8 = 0x14;
    pub const SCAN_WITHDRAWN: u8 = 0x15;
    pub const SCAN_UNAVAILABLE: u8 = 0x16;
    pub const TILE_LISTED: u8 = 0x17;
    pub const TILE_WITHDRAWN: u8 = 0x18;
    pub const TILE_DATA: u8 = 0x19;
    pub const TILE_UNAVAILABLE: u8 = 0x1a;
    pub const SCAN_EXPOSURE: u8 = 0x1b;
    pub const EO_RESPONSE: u8 = 0x1c;
    pub const STATUS: u8 = 0x20;
    pub const GOODBYE: u8 = 0x30;
    pub const REQUEST_SCAN: u8 = 0x40;
    pub const REQUEST_TILE: u8 = 0x41;
}

/// Every message of the protocol.
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    /// Client -> server, first: who is asking and with what token.
    ClientHello {
        version: u16,
        token: String,
        client_name: String,
    },
    /// Server -> client: the connection is accepted.
    ServerHello {
        version: u16,
        server_name: String,
        session_name: String,
    },
    /// Server -> client, then the server closes: why the connection was refused.
    Refused { reason: String },
    /// Server -> client: forget the model (and every request not yet answered); a
    /// snapshot of `scan_count` scans follows (one `ScanListed` each), closed by
    /// `SnapshotComplete`. Sent on connecting and whenever a slow client is
    /// resynchronised.
    ModelReset { scan_count: u64 },
    /// Server -> client: the snapshot is complete; live updates follow.
    SnapshotComplete { scan_count: u64 },
    /// Server -> client: a scan's data: a newly registered scan, or the answer to a
    /// `RequestScan`.
    ScanAdded(Box<WireScan>),
    /// Server -> client: a scan's pose was refined.
    PoseRevised { id: ScanId, world_from_scan: Pose },
    /// Server -> client: a served scan without its data (fetch it with `RequestScan`).
    ScanListed {
        id: ScanId,
        listing: ScanListing,
        world_from_scan: Pose,
    },
    /// Server -> client: the scan left the served model; forget it.
    ScanWithdrawn { id: ScanId },
    /// Server -> client: a `RequestScan` cannot be answered (unknown id, withdrawn,
    /// store damaged), and why.
    ScanUnavailable { id: ScanId, reason: String },
    /// Client -> server: send scan `id`'s data (a `ScanAdded`, or `ScanUnavailable`).
    RequestScan { id: ScanId },
    /// Server -> client (version 3): a tile of the level-of-detail tree, new or
    /// rebuilt (a new revision) or with new bounds; fetch its data with `RequestTile`.
    TileListed { id: TileId, listing: TileListing },
    /// Server -> client (version 3): the tile left the tree; forget it.
    TileWithdrawn { id: TileId },
    /// Server -> client (version 3): a tile's data, the answer to a `RequestTile`.
    TileData(Box<WireTile>),
    /// Server -> client (version 3): a `RequestTile` cannot be answered, and why.
    TileUnavailable { id: TileId, reason: String },
    /// Client -> server (version 3): send tile `id`'s data (a `TileData`, or
    /// `TileUnavailable`).
    RequestTile { id: TileId },
    /// Server -> client (version 4): how scan `id`'s EO frame was exposed, sent just
    /// before each `ScanAdded` of a scan whose frame recorded it.
    ScanExposure { id: ScanId, exposure: EoExposure },
    /// Server -> client (version 4): the EO camera's response curve, in the snapshot
    /// after `ModelReset` when the daemon's sensor model has one.
    EoResponse(Box<crate::radiance::EoResponse>),
    /// Server -> client: the daemon's periodic status.
    Status(Box<Status>),
    /// Either way, then the sender closes: why the stream ends.
    Goodbye { reason: String },
}

/// Why bytes could not be decoded or a message could not be encoded.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum WireError {
    #[error("frame length {len} is outside 1..={max}")]
    FrameLength { len: u64, max: u32 },
    #[error("unknown message kind 0x{0:02x}")]
    UnknownKind(u8),
    #[error("{what}: {message}")]
    Invalid { what: &'static str, message: String },
    #[error("cannot encode {what}: {message}")]
    Encode { what: &'static str, message: String },
}

impl WireError {
    pub(crate) fn invalid(what: &'static str, message: impl Into<String>) -> Self {
        Self::Invalid {
            what,
            message: message.into(),
        }
    }

    pub(crate) fn encode(what: &'static str, message: impl Into<String>) -> Self {
        Self::Encode {
            what,
            message: message.into(),
        }
    }
}

impl Message {
    /// A short name of the message kind, for logs.
    pub fn kind_name(&self) -> &'static str {
        match self {
            Self::ClientHello { .. } => "ClientHello",
            Self::ServerHello { .. } => "ServerHello",
            Self::Refused { .. } => "Refused",
            Self::ModelReset { .. } => "ModelReset",
            Self::SnapshotComplete { .. } => "SnapshotComplete",
            Self::ScanAdded(_) => "ScanAdded",
            Self::PoseRevised { .. } => "PoseRevised",
            Self::ScanListed { .. } => "ScanListed",
            Self::ScanWithdrawn { .. } => "ScanWithdrawn",
            Self::ScanUnavailable { .. } => "ScanUnavailable",
            Self::RequestScan { .. } => "RequestScan",
            Self::TileListed { .. } => "TileListed",
            Self::TileWithdrawn { .. } => "TileWithdrawn",
            Self::TileData(_) => "TileData",
            Self::TileUnavailable { .. } => "TileUnavailable",
            Self::RequestTile { .. } => "RequestTile",
            Self::ScanExposure { .. } => "ScanExposure",
            Self::EoResponse(_) => "EoResponse",
            Self::Status(_) => "Status",
            Self::Goodbye { .. } => "Goodbye",
        }
    }

    /// The whole frame (length prefix, kind, fields). Refuses values the decoder would
    /// refuse (over-long strings, inconsistent scans, non-finite poses), so whatever
    /// encodes also decodes.
    pub fn encode(&self) -> Result<Vec<u8>, WireError> {
        let mut out = vec![0u8; LENGTH_PREFIX];
        match self {
            Self::ClientHello {
                version,
                token,
                client_name,
            } => {
                out.put_u8(kind::CLIENT_HELLO);
                out.extend_from_slice(&CLIENT_MAGIC);
                out.put_u16(*version);
                put_string(&mut out, "ClientHello.token", token, MAX_NAME_LEN)?;
                put_string(
                    &mut out,
                    "ClientHello.client_name",
                    client_name,
                    MAX_NAME_LEN,
                )?;
            }
            Self::ServerHello {
                version,
                server_name,
                session_name,
            } => {
                out.put_u8(kind::SERVER_HELLO);
                out.put_u16(*version);
                put_string(
                    &mut out,
                    "ServerHello.server_name",
                    server_name,
                    MAX_NAME_LEN,
                )?;
                put_string(
                    &mut out,
                    "ServerHello.session_name",
                    session_name,
                    MAX_NAME_LEN,
                )?;
            }
            Self::Refused { reason } => {
                out.put_u8(kind::REFUSED);
                put_string(&mut out, "Refused.reason", reason, MAX_REASON_LEN)?;
            }
            Self::ModelReset { scan_count } => {
                out.put_u8(kind::MODEL_RESET);
                out.put_u64(*scan_count);
            }
            Self::SnapshotComplete { scan_count } => {
                out.put_u8(kind::SNAPSHOT_COMPLETE);
                out.put_u64(*scan_count);
            }
            Self::ScanAdded(scan) => {
                out.put_u8(kind::SCAN_ADDED);
                scan.encode_into(&mut out)?;
            }
            Self::PoseRevised {
                id,
                world_from_scan,
            } => {
                out.put_u8(kind::POSE_REVISED);
                out.put_u64(*id);
                put_pose(&mut out, "PoseRevised.world_from_scan", world_from_scan)?;
            }
            Self::ScanListed {
                id,
                listing,
                world_from_scan,
            } => {
                out.put_u8(kind::SCAN_LISTED);
                listing::put_scan_listed(&mut out, *id, listing, world_from_scan)?;
            }
            Self::ScanWithdrawn { id } => {
                out.put_u8(kind::SCAN_WITHDRAWN);
                out.put_u64(*id);
            }
            Self::ScanExposure { id, exposure } => {
                out.put_u8(kind::SCAN_EXPOSURE);
                radiance::put_scan_exposure(&mut out, *id, exposure)?;
            }
            Self::EoResponse(response) => {
                out.put_u8(kind::EO_RESPONSE);
                radiance::put_eo_response(&mut out, response);
            }
            Self::ScanUnavailable { id, reason } => {
                out.put_u8(kind::SCAN_UNAVAILABLE);
                listing::put_unavailable(&mut out, *id, reason)?;
            }
            Self::RequestScan { id } => {
                out.put_u8(kind::REQUEST_SCAN);
                out.put_u64(*id);
            }
            Self::TileListed { id, listing } => {
                out.put_u8(kind::TILE_LISTED);
                tiles::put_tile_listed(&mut out, *id, listing)?;
            }
            Self::TileWithdrawn { id } => {
                out.put_u8(kind::TILE_WITHDRAWN);
                tiles::put_tile_id(&mut out, *id);
            }
            Self::TileData(tile) => {
                out.put_u8(kind::TILE_DATA);
                tiles::put_tile_data(&mut out, tile)?;
            }
            Self::TileUnavailable { id, reason } => {
                out.put_u8(kind::TILE_UNAVAILABLE);
                tiles::put_tile_unavailable(&mut out, *id, reason)?;
            }
            Self::RequestTile { id } => {
                out.put_u8(kind::REQUEST_TILE);
                tiles::put_tile_id(&mut out, *id);
            }
            Self::Status(status) => {
                out.put_u8(kind::STATUS);
                let json = serde_json::to_string(status)
                    .map_err(|e| WireError::encode("Status", e.to_string()))?;
                put_string(&mut out, "Status", &json, MAX_STATUS_LEN)?;
            }
            Self::Goodbye { reason } => {
                out.put_u8(kind::GOODBYE);
                put_string(&mut out, "Goodbye.reason", reason, MAX_REASON_LEN)?;
            }
        }
        finish_frame(out, self.kind_name())
    }
}

/// Fills in the length prefix of a frame written after [`LENGTH_PREFIX`] placeholder
/// bytes; refuses a body beyond [`MAX_SERVER_FRAME_LEN`].
fn finish_frame(mut out: Vec<u8>, what: &'static str) -> Result<Vec<u8>, WireError> {
    let body_len = out.len().saturating_sub(LENGTH_PREFIX);
    if body_len > MAX_SERVER_FRAME_LEN as usize {
        return Err(WireError::encode(
            what,
            format!("{body_len} bytes exceed the frame limit {MAX_SERVER_FRAME_LEN}"),
        ));
    }
    if let Some(prefix) = out.get_mut(..LENGTH_PREFIX) {
        prefix.copy_from_slice(&(body_len as u32).to_le_bytes());
    }
    Ok(out)
}

/// The length of the frame at the start of `buf` (prefix included) if its prefix is
/// complete: `Ok(None)` means read more, `Err` that the length is out of bounds. The
/// length is checked before a single byte of the body is awaited.
pub fn frame_len(buf: &[u8], limits: &Limits) -> Result<Option<usize>, WireError> {
    let Some(prefix) = buf.get(..LENGTH_PREFIX) else {
        return Ok(None);
    };
    let len = u32::from_le_bytes([prefix[0], prefix[1], prefix[2], prefix[3]]);
    if len == 0 || len > limits.max_frame_len {
        return Err(WireError::FrameLength {
            len: u64::from(len),
            max: limits.max_frame_len,
        });
    }
    Ok(Some(LENGTH_PREFIX + len as usize))
}

/// Decodes the frame at the start of `buf`: `Ok(None)` when more bytes are needed,
/// `Ok(Some((message, consumed)))` for a complete frame, `Err` for one that can never
/// become valid (the connection should be closed).
pub fn decode_frame(buf: &[u8], limits: &Limits) -> Result<Option<(Message, usize)>, WireError> {
    let Some(total) = frame_len(buf, limits)? else {
        return Ok(None);
    };
    let Some(frame) = buf.get(LENGTH_PREFIX..total) else {
        return Ok(None);
    };
    let message = decode_body(frame)?;
    Ok(Some((message, total)))
}

/// Decodes one frame body (kind byte and fields).
fn decode_body(frame: &[u8]) -> Result<Message, WireError> {
    let (&k, body) = frame
        .split_first()
        .ok_or_else(|| WireError::invalid("frame", "empty body"))?;
    let message = match k {
        kind::CLIENT_HELLO => {
            let mut r = BodyReader::new(body, "ClientHello");
            if r.take(4, "magic")? != CLIENT_MAGIC {
                return Err(WireError::invalid(
                    "ClientHello",
                    "bad magic (not a Texel viewer)",
                ));
            }
            let version = r.u16("version")?;
            let token = r.string("token", MAX_NAME_LEN)?;
            let client_name = r.string("client_name", MAX_NAME_LEN)?;
            r.finish()?;
            Message::ClientHello {
                version,
                token,
                client_name,
            }
        }
        kind::SERVER_HELLO => {
            let mut r = BodyReader::new(body, "ServerHello");
            let version = r.u16("version")?;
            let server_name = r.string("server_name", MAX_NAME_LEN)?;
            let session_name = r.string("session_name", MAX_NAME_LEN)?;
            r.finish()?;
            Message::ServerHello {
                version,
                server_name,
                session_name,
            }
        }
        kind::REFUSED => {
            let mut r = BodyReader::new(body, "Refused");
            let reason = r.string("reason", MAX_REASON_LEN)?;
            r.finish()?;
            Message::Refused { reason }
        }
        kind::MODEL_RESET => {
            let mut r = BodyReader::new(body, "ModelReset");
            let scan_count = r.u64("scan_count")?;
            r.finish()?;
            Message::ModelReset { scan_count }
        }
        kind::SNAPSHOT_COMPLETE => {
            let mut r = BodyReader::new(body, "SnapshotComplete");
            let scan_count = r.u64("scan_count")?;
            r.finish()?;
            Message::SnapshotComplete { scan_count }
        }
        kind::SCAN_ADDED => Message::ScanAdded(Box::new(WireScan::decode(body)?)),
        kind::POSE_REVISED => {
            let mut r = BodyReader::new(body, "PoseRevised");
            let id = r.u64("id")?;
            let world_from_scan = read_pose(&mut r, "world_from_scan")?;
            r.finish()?;
            Message::PoseRevised {
                id,
                world_from_scan,
            }
        }
        kind::SCAN_LISTED => {
            let (id, listing, world_from_scan) = listing::read_scan_listed(body)?;
            Message::ScanListed {
                id,
                listing,
                world_from_scan,
            }
        }
        kind::SCAN_WITHDRAWN => Message::ScanWithdrawn {
            id: listing::read_id(body, "ScanWithdrawn")?,
        },
        kind::SCAN_EXPOSURE => {
            let (id, exposure) = radiance::read_scan_exposure(body)?;
            Message::ScanExposure { id, exposure }
        }
        kind::EO_RESPONSE => Message::EoResponse(Box::new(radiance::read_eo_response(body)?)),
        kind::SCAN_UNAVAILABLE => {
            let (id, reason) = listing::read_unavailable(body)?;
            Message::ScanUnavailable { id, reason }
        }
        kind::REQUEST_SCAN => Message::RequestScan {
            id: listing::read_id(body, "RequestScan")?,
        },
        kind::TILE_LISTED => {
            let (id, listing) = tiles::read_tile_listed(body)?;
            Message::TileListed { id, listing }
        }
        kind::TILE_WITHDRAWN => Message::TileWithdrawn {
            id: tiles::read_tile_only(body, "TileWithdrawn")?,
        },
        kind::TILE_DATA => Message::TileData(Box::new(tiles::read_tile_data(body)?)),
        kind::TILE_UNAVAILABLE => {
            let (id, reason) = tiles::read_tile_unavailable(body)?;
            Message::TileUnavailable { id, reason }
        }
        kind::REQUEST_TILE => Message::RequestTile {
            id: tiles::read_tile_only(body, "RequestTile")?,
        },
        kind::STATUS => {
            let mut r = BodyReader::new(body, "Status");
            let json = r.string("json", MAX_STATUS_LEN)?;
            r.finish()?;
            let status: Status = serde_json::from_str(&json)
                .map_err(|e| WireError::invalid("Status", e.to_string()))?;
            Message::Status(Box::new(status))
        }
        kind::GOODBYE => {
            let mut r = BodyReader::new(body, "Goodbye");
            let reason = r.string("reason", MAX_REASON_LEN)?;
            r.finish()?;
            Message::Goodbye { reason }
        }
        other => return Err(WireError::UnknownKind(other)),
    };
    Ok(message)
}

pub(crate) fn put_string(
    out: &mut Vec<u8>,
    what: &'static str,
    s: &str,
    max: usize,
) -> Result<(), WireError> {
    if s.len() > max {
        return Err(WireError::encode(
            what,
            format!("{} bytes exceed the limit {max}", s.len()),
        ));
    }
    out.put_bytes(s.as_bytes());
    Ok(())
}

/// A pose as translation (x, y, z) and unit quaternion (x, y, z, w), 7 × f64.
pub(crate) fn put_pose(
    out: &mut Vec<u8>,
    what: &'static str,
    pose: &Pose,
) -> Result<(), WireError> {
    let (t, q) = pose_to_parts(pose);
    if t.iter().chain(q.iter()).any(|v| !v.is_finite()) {
        return Err(WireError::encode(what, "non-finite pose"));
    }
    for v in t.iter().chain(q.iter()) {
        out.put_f64(*v);
    }
    Ok(())
}

/// Reads a pose. A quaternion already of unit length (to rounding) is taken as it is,
/// so poses round-trip bit for bit; any other non-zero one is normalised.
pub(crate) fn read_pose(r: &mut BodyReader<'_>, field: &'static str) -> Result<Pose, WireError> {
    let mut v = [0.0f64; 7];
    for x in &mut v {
        *x = r.f64(field)?;
    }
    // Checked here with compact messages (a hostile value's full decimal expansion
    // could be a thousand characters long).
    if v.iter().any(|x| !x.is_finite()) {
        return Err(WireError::invalid("pose", format!("{field}: not finite")));
    }
    let q = nalgebra::Quaternion::new(v[6], v[3], v[4], v[5]);
    if q.norm() < 1e-9 {
        return Err(WireError::invalid(
            "pose",
            format!(
                "{field}: quaternion of length {:.3e} is not a rotation",
                q.norm()
            ),
        ));
    }
    let pose = pose_from_parts([v[0], v[1], v[2]], [v[3], v[4], v[5], v[6]])
        .map_err(|_| WireError::invalid("pose", format!("{field}: not a rigid pose")))?;
    if (q.norm() - 1.0).abs() <= 8.0 * f64::EPSILON {
        Ok(Pose::from_parts(
            pose.translation,
            nalgebra::UnitQuaternion::new_unchecked(q),
        ))
    } else {
        Ok(pose)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_exposures_and_response_curves_are_invalid_by_name() {
        let exposure = |t: f64, g: f64| {
            let mut body = vec![0u8; 4];
            body.push(kind::SCAN_EXPOSURE);
            body.extend_from_slice(&3u64.to_le_bytes());
            body.extend_from_slice(&t.to_le_bytes());
            body.extend_from_slice(&g.to_le_bytes());
            let len = (body.len() - 4) as u32;
            body[..4].copy_from_slice(&len.to_le_bytes());
            decode_frame(&body, &Limits::FROM_SERVER)
        };
        assert!(exposure(0.01, 1.0).unwrap().is_some());
        for (t, g) in [(0.0, 1.0), (f64::NAN, 1.0), (0.01, -2.0), (1.0e9, 1.0)] {
            let e = exposure(t, g).unwrap_err().to_string();
            assert!(e.contains("ScanExposure"), "{e}");
        }
        // A curve that falls by more than the tolerance is refused, as from a file.
        let mut frame = Message::EoResponse(Box::new(crate::radiance::EoResponse::srgb()))
            .encode()
            .unwrap();
        let at = LENGTH_PREFIX + 1 + 8 * 200;
        frame[at..at + 8].copy_from_slice(&(-50.0f64).to_le_bytes());
        let e = decode_frame(&frame, &Limits::FROM_SERVER)
            .unwrap_err()
            .to_string();
        assert!(e.contains("EoResponse"), "{e}");
        // Encoding refuses what decoding would.
        let bad = Message::ScanExposure {
            id: 1,
            exposure: EoExposure {
                exposure_time_s: f64::INFINITY,
                gain: 1.0,
            },
        };
        assert!(bad.encode().is_err());
    }

    #[test]
    fn short_messages_round_trip_and_split_reads_are_incomplete() {
        let messages = [
            Message::ClientHello {
                version: PROTOCOL_VERSION,
                token: "secret".into(),
                client_name: "viewer".into(),
            },
            Message::ServerHello {
                version: 1,
                server_name: "texeld".into(),
                session_name: "lab".into(),
            },
            Message::Refused {
                reason: "wrong token".into(),
            },
            Message::ModelReset { scan_count: 3 },
            Message::SnapshotComplete { scan_count: 3 },
            Message::PoseRevised {
                id: 7,
                world_from_scan: Pose::translation(1.0, 2.0, 3.0),
            },
            Message::ScanWithdrawn { id: 4 },
            Message::ScanUnavailable {
                id: 5,
                reason: "scan 5 is not in the served model".into(),
            },
            Message::RequestScan { id: u64::MAX },
            Message::ScanExposure {
                id: 9,
                exposure: EoExposure {
                    exposure_time_s: 0.004,
                    gain: 1.5,
                },
            },
            Message::EoResponse(Box::new(crate::radiance::EoResponse::srgb())),
            Message::Goodbye {
                reason: "shutting down".into(),
            },
        ];
        for m in &messages {
            let bytes = m.encode().unwrap();
            for cut in 0..bytes.len() {
                assert_eq!(
                    decode_frame(&bytes[..cut], &Limits::FROM_SERVER).unwrap(),
                    None
                );
            }
            let (back, used) = decode_frame(&bytes, &Limits::FROM_SERVER).unwrap().unwrap();
            assert_eq!(&back, m);
            assert_eq!(used, bytes.len());
        }
    }

    #[test]
    fn oversize_lengths_are_invalid_before_the_body_arrives() {
        let mut prefix = (MAX_CLIENT_FRAME_LEN + 1).to_le_bytes().to_vec();
        assert!(matches!(
            decode_frame(&prefix, &Limits::FROM_CLIENT),
            Err(WireError::FrameLength { .. })
        ));
        prefix = 0u32.to_le_bytes().to_vec();
        assert!(decode_frame(&prefix, &Limits::FROM_CLIENT).is_err());
        // "GET / HTTP/1.1" is a frame length of about 542 million.
        assert!(decode_frame(b"GET / HTTP/1.1\r\n", &Limits::FROM_CLIENT).is_err());
    }

    #[test]
    fn over_long_strings_do_not_encode() {
        let m = Message::ClientHello {
            version: 1,
            token: "x".repeat(MAX_NAME_LEN + 1),
            client_name: String::new(),
        };
        assert!(matches!(m.encode(), Err(WireError::Encode { .. })));
    }
}
