//! The viewer stream's client side without sockets: the handshake messages, a frame
//! reader that tells "incomplete, read more" from "invalid", the [`Update`] each
//! message asks for, and the [`Replica`] that applies them to a local [`Model`]
//! (resets and snapshots included) and says which listed scans to fetch, so every
//! viewer holds the same model as the daemon. Transports (a TCP socket, a WebSocket,
//! an in-process channel) feed it bytes; `texel-client` has the TCP ones.

use std::time::Duration;

use bytes::BytesMut;
use thiserror::Error;

use super::{FetchPlan, Limits, Message, PROTOCOL_VERSION, Status, WireError, decode_frame};
use super::{TileCatalog, TileEvent};
use crate::EoExposure;
use crate::model::{Model, ModelError, ModelEvent, ScanId};
use crate::radiance::EoResponse;
use crate::tile::TileId;

#[derive(Debug, Error)]
pub enum ClientError {
    #[error("cannot connect: {0}")]
    Connect(std::io::Error),
    #[error("connection: {0}")]
    Io(std::io::Error),
    #[error("the server refused the connection: {0}")]
    Refused(String),
    #[error("the server sent an invalid message: {0}")]
    Protocol(#[from] WireError),
    #[error("unexpected {0} during the handshake")]
    Handshake(&'static str),
    #[error("the server closed the connection mid-message")]
    Truncated,
    #[error("no answer within {0:?}")]
    Timeout(Duration),
}

/// What the server said about itself.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServerInfo {
    pub version: u16,
    pub server_name: String,
    pub session_name: String,
}

/// Takes complete frames out of received bytes.
#[derive(Debug, Default)]
pub struct FrameReader {
    /// Bytes received and not yet taken as messages.
    pub buf: BytesMut,
}

impl FrameReader {
    /// The next whole message in the buffer; `Ok(None)`: incomplete, read more.
    pub fn take_message(&mut self) -> Result<Option<Message>, ClientError> {
        match decode_frame(&self.buf, &Limits::FROM_SERVER)? {
            Some((message, used)) => {
                let _ = self.buf.split_to(used);
                Ok(Some(message))
            }
            None => Ok(None),
        }
    }
}

/// The client's opening message, encoded.
pub fn hello(token: &str, client_name: &str) -> Result<Vec<u8>, ClientError> {
    Ok(Message::ClientHello {
        version: PROTOCOL_VERSION,
        token: token.to_string(),
        client_name: client_name.to_string(),
    }
    .encode()?)
}

/// A request for scan `id`'s data, encoded.
pub fn request(id: ScanId) -> Result<Vec<u8>, ClientError> {
    Ok(Message::RequestScan { id }.encode()?)
}

/// A `RequestTile` frame.
pub fn request_tile(id: TileId) -> Result<Vec<u8>, ClientError> {
    Ok(Message::RequestTile { id }.encode()?)
}

/// The server's answer to the hello: who it is, or why it refused.
pub fn welcome(message: Message) -> Result<ServerInfo, ClientError> {
    match message {
        Message::ServerHello {
            version,
            server_name,
            session_name,
        } => Ok(ServerInfo {
            version,
            server_name,
            session_name,
        }),
        Message::Refused { reason } | Message::Goodbye { reason } => {
            Err(ClientError::Refused(reason))
        }
        other => Err(ClientError::Handshake(other.kind_name())),
    }
}

/// What applying a message did to the replica.
#[derive(Debug, Clone, PartialEq)]
pub enum Applied {
    /// The model was cleared; a snapshot follows.
    Reset {
        scan_count: u64,
    },
    SnapshotComplete,
    ScanAdded(ScanId),
    PoseRevised(ScanId),
    ScanListed(ScanId),
    ScanWithdrawn(ScanId),
    /// A request for the scan cannot be answered.
    Unavailable {
        id: ScanId,
        reason: String,
    },
    Status,
    /// A tile of the level-of-detail tree was listed, withdrawn, answered or refused.
    Tile(TileId),
    /// The server ends the stream.
    Goodbye(String),
    /// A message that does not change the model (a stray hello).
    Ignored,
}

#[derive(Debug, Error)]
pub enum ReplicaError {
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error(transparent)]
    Model(#[from] ModelError),
}

/// A viewer's copy of the daemon's whole model: every listed scan, fetched.
#[derive(Debug, Default)]
pub struct Replica {
    pub model: Model,
    /// True between `SnapshotComplete` and the next `ModelReset`.
    pub live: bool,
    /// How many times the server reset the model (1 for the first snapshot).
    pub resets: u64,
    pub status: Option<Status>,
    /// The level-of-detail tree's tiles (protocol version 3).
    pub tiles: TileCatalog,
    /// Which listed scans are missing and which were requested.
    fetch: FetchPlan,
    /// The EO camera's response curve, when the server sent one (version 4).
    pub eo_response: Option<EoResponse>,
    exposures: ExposureJoin,
}

impl Replica {
    pub fn new() -> Self {
        Self::default()
    }

    /// The scans to request now (sent as `RequestScan` by the caller), counted as
    /// requested: listed, not resident, not yet requested, highest
    /// `listing.priority` first, at most `max_in_flight` outstanding in all. An
    /// answer (`ScanAdded`, `ScanUnavailable`) or a withdrawal ends a request; a
    /// `ModelReset` forgets them all.
    pub fn wanted(&mut self, max_in_flight: usize) -> Vec<ScanId> {
        self.fetch.wanted(max_in_flight)
    }

    /// Requests sent and not yet answered.
    pub fn in_flight(&self) -> usize {
        self.fetch.in_flight()
    }

    /// The snapshot is complete and every listed scan is resident, but those the
    /// server said are unavailable.
    pub fn complete(&self) -> bool {
        self.live && self.fetch.complete()
    }

    /// Applies one message (decoding a scan's texture).
    pub fn apply(&mut self, message: Message) -> Result<Applied, ReplicaError> {
        self.fetch.observe(&message);
        Ok(match update(message)? {
            Update::Reset { scan_count } => {
                self.model = Model::new();
                self.tiles.clear();
                self.live = false;
                self.resets += 1;
                Applied::Reset { scan_count }
            }
            Update::SnapshotComplete { .. } => {
                self.live = true;
                Applied::SnapshotComplete
            }
            Update::Model(mut event) => {
                self.exposures.attach(&mut event);
                let applied = match &event {
                    ModelEvent::ScanAdded { id, .. } => Applied::ScanAdded(*id),
                    ModelEvent::PoseRevised { id, .. } => Applied::PoseRevised(*id),
                    ModelEvent::ScanListed { id, .. } => Applied::ScanListed(*id),
                    ModelEvent::ScanWithdrawn { id } => Applied::ScanWithdrawn(*id),
                    ModelEvent::ScanEvicted { .. } => Applied::Ignored,
                };
                self.model.apply(event)?;
                applied
            }
            Update::Status(status) => {
                self.status = Some(*status);
                Applied::Status
            }
            Update::Unavailable { id, reason } => Applied::Unavailable { id, reason },
            Update::Tile(event) => {
                let id = match &event {
                    TileEvent::Listed { id, .. }
                    | TileEvent::Withdrawn { id }
                    | TileEvent::Unavailable { id, .. } => *id,
                    TileEvent::Data(tile) => tile.id,
                };
                self.tiles.apply(event);
                Applied::Tile(id)
            }
            Update::Exposure { id, exposure } => {
                self.exposures.hold(id, exposure);
                Applied::Ignored
            }
            Update::Response(response) => {
                self.eo_response = Some(*response);
                Applied::Ignored
            }
            Update::Goodbye(reason) => Applied::Goodbye(reason),
            Update::Ignored => Applied::Ignored,
        })
    }
}

/// What a server message asks of a client's model, decoded (a scan's texture
/// included) but not applied: a client that keeps its model elsewhere (the viewer's
/// window, a browser) forwards these instead of holding a [`Replica`] as a second copy.
#[derive(Debug, Clone)]
pub enum Update {
    /// Forget the model; a snapshot of `scan_count` scans follows.
    Reset {
        scan_count: u64,
    },
    /// The snapshot is complete; live updates follow.
    SnapshotComplete {
        scan_count: u64,
    },
    /// A scan joins the model (its data, or its listing), moves or leaves it.
    Model(ModelEvent),
    /// A request for scan `id` cannot be answered, and why.
    Unavailable {
        id: ScanId,
        reason: String,
    },
    Status(Box<Status>),
    /// How scan `id`'s EO frame was exposed (version 4): it belongs to the
    /// `ScanAdded` that follows ([`ExposureJoin`]).
    Exposure {
        id: ScanId,
        exposure: EoExposure,
    },
    /// The EO camera's response curve (version 4).
    Response(Box<EoResponse>),
    /// A change to the level-of-detail tree (version 3).
    Tile(TileEvent),
    /// The server ends the stream (a goodbye, or a refusal after the handshake).
    Goodbye(String),
    /// A message that does not concern the model (a stray hello).
    Ignored,
}

/// Joins a `ScanExposure` to the `ScanAdded` after it (the server sends them in that
/// order, as a capture records `/eo/exposure` before its frame): holds the last
/// exposure received, sets it on the next scan's EO frame if the ids match, and
/// forgets it at any `ScanAdded`. One slot: a server cannot make it grow.
#[derive(Debug, Default)]
pub struct ExposureJoin {
    pending: Option<(ScanId, EoExposure)>,
}

impl ExposureJoin {
    pub fn hold(&mut self, id: ScanId, exposure: EoExposure) {
        self.pending = Some((id, exposure));
    }

    /// Gives a `ScanAdded` event its exposure, if the last one held was for its id.
    pub fn attach(&mut self, event: &mut ModelEvent) {
        let ModelEvent::ScanAdded { id, scan, .. } = event else {
            return;
        };
        if let Some((held, exposure)) = self.pending.take()
            && held == *id
        {
            // Both are fresh from decoding: `make_mut` copies nothing.
            let scan = std::sync::Arc::make_mut(scan);
            std::sync::Arc::make_mut(&mut scan.texture).exposure = Some(exposure);
        }
    }
}

/// Decodes one server message into the [`Update`] it asks for.
pub fn update(message: Message) -> Result<Update, WireError> {
    Ok(match message {
        Message::ModelReset { scan_count } => Update::Reset { scan_count },
        Message::SnapshotComplete { scan_count } => Update::SnapshotComplete { scan_count },
        Message::ScanAdded(wire) => {
            let (id, scan, world_from_scan) = wire.into_scan()?;
            Update::Model(ModelEvent::ScanAdded {
                id,
                scan: std::sync::Arc::new(scan),
                world_from_scan,
            })
        }
        Message::PoseRevised {
            id,
            world_from_scan,
        } => Update::Model(ModelEvent::PoseRevised {
            id,
            world_from_scan,
        }),
        Message::ScanListed {
            id,
            listing,
            world_from_scan,
        } => Update::Model(ModelEvent::ScanListed {
            id,
            listing,
            world_from_scan,
        }),
        Message::ScanWithdrawn { id } => Update::Model(ModelEvent::ScanWithdrawn { id }),
        Message::ScanUnavailable { id, reason } => Update::Unavailable { id, reason },
        Message::Status(status) => Update::Status(status),
        Message::ScanExposure { id, exposure } => Update::Exposure { id, exposure },
        Message::EoResponse(response) => Update::Response(response),
        Message::Goodbye { reason } | Message::Refused { reason } => Update::Goodbye(reason),
        Message::TileListed { id, listing } => Update::Tile(TileEvent::Listed { id, listing }),
        Message::TileWithdrawn { id } => Update::Tile(TileEvent::Withdrawn { id }),
        Message::TileData(tile) => Update::Tile(TileEvent::Data(tile)),
        Message::TileUnavailable { id, reason } => {
            Update::Tile(TileEvent::Unavailable { id, reason })
        }
        Message::ClientHello { .. }
        | Message::ServerHello { .. }
        | Message::RequestScan { .. }
        | Message::RequestTile { .. } => Update::Ignored,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;
    use crate::fuzzing::sample_messages;
    use crate::model::ScanListing;
    use crate::pose::Pose;

    fn listed(id: ScanId, priority: f32) -> Message {
        Message::ScanListed {
            id,
            listing: ScanListing {
                timestamp_ns: id,
                bounds_min_m: [0.0; 3],
                bounds_max_m: [1.0; 3],
                cop_m: [0.0; 3],
                priority,
                encoded_bytes: 10,
            },
            world_from_scan: Pose::translation(id as f64, 0.0, 0.0),
        }
    }

    /// The sample `ScanAdded` and the scan it carries.
    fn sample_scan() -> (Message, Box<crate::wire::WireScan>) {
        let scan = sample_messages()
            .into_iter()
            .find(|m| matches!(m, Message::ScanAdded(_)))
            .unwrap();
        let Message::ScanAdded(wire) = &scan else {
            unreachable!()
        };
        let wire = wire.clone();
        (scan, wire)
    }

    #[test]
    fn an_exposure_joins_the_scan_after_it_and_no_other() {
        let (scan, wire) = sample_scan();
        let id = wire.id;
        let exposure = EoExposure {
            exposure_time_s: 0.02,
            gain: 1.0,
        };
        let mut replica = Replica::new();
        replica
            .apply(Message::ModelReset { scan_count: 0 })
            .unwrap();
        // For another scan: not attached, and forgotten at this ScanAdded.
        replica
            .apply(Message::ScanExposure {
                id: id + 1,
                exposure,
            })
            .unwrap();
        replica.apply(scan.clone()).unwrap();
        let got = |r: &Replica| {
            r.model
                .get(id)
                .unwrap()
                .scan
                .as_ref()
                .unwrap()
                .texture
                .exposure
        };
        assert_eq!(got(&replica), None);
        replica
            .apply(Message::ModelReset { scan_count: 0 })
            .unwrap();
        replica
            .apply(Message::ScanExposure { id, exposure })
            .unwrap();
        replica.apply(scan).unwrap();
        assert_eq!(got(&replica), Some(exposure));
        replica
            .apply(Message::EoResponse(Box::new(EoResponse::srgb())))
            .unwrap();
        assert_eq!(replica.eo_response, Some(EoResponse::srgb()));
    }

    #[test]
    fn a_replica_asks_for_what_it_lacks_and_is_complete_once_answered() {
        let (_, wire) = sample_scan();
        let with_id = |id| {
            let mut w = wire.clone();
            w.id = id;
            Message::ScanAdded(w)
        };
        let mut r = Replica::new();
        r.apply(Message::ModelReset { scan_count: 3 }).unwrap();
        for (id, priority) in [(0, 0.5), (1, 2.0), (2, 1.0)] {
            assert_eq!(
                r.apply(listed(id, priority)).unwrap(),
                Applied::ScanListed(id)
            );
        }
        r.apply(Message::SnapshotComplete { scan_count: 3 })
            .unwrap();
        assert!(!r.complete());
        assert_eq!(r.wanted(2), vec![1, 2]);
        assert_eq!(r.wanted(2), Vec::<ScanId>::new());
        assert_eq!(r.apply(with_id(1)).unwrap(), Applied::ScanAdded(1));
        let unavailable = Message::ScanUnavailable {
            id: 2,
            reason: "gone".into(),
        };
        assert_eq!(
            r.apply(unavailable).unwrap(),
            Applied::Unavailable {
                id: 2,
                reason: "gone".into()
            }
        );
        assert_eq!(r.wanted(2), vec![0]);
        r.apply(Message::ScanWithdrawn { id: 0 }).unwrap();
        assert_eq!(r.in_flight(), 0);
        assert!(r.complete(), "scan 2 is unavailable, scan 0 withdrawn");
        assert_eq!(r.model.len(), 2);
        assert_eq!(r.model.resident_len(), 1);
        // A fetched scan takes the pose its frame carries (a revision follows if any).
        assert_eq!(
            r.model.get(1).unwrap().world_from_scan,
            wire.world_from_scan
        );
        r.apply(Message::ModelReset { scan_count: 0 }).unwrap();
        assert_eq!((r.model.len(), r.in_flight(), r.complete()), (0, 0, false));
    }
}
