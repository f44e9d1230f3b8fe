//! Tiles from a daemon (`docs/wire-protocol.md`, "Tiles"): a [`TileSource`] over its
//! own connection. A reader thread follows the stream (listings, withdrawals, data,
//! refusals) and a writer thread sends the render thread's requests, so the render
//! thread never touches the socket. Every request is answered: with the tile's bytes,
//! the server's refusal, or an error when the connection is reset or lost (the driver
//! then asks again).

use std::collections::{BTreeMap, BTreeSet};
use std::io::Write;
use std::net::SocketAddr;
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use texel::wire::Message;
use texel_client::{BlockingClient, ClientError, request_tile};
use texel_lod::{TileId, TileInfo};

use super::source::{EncodedTile, LoadError, TileEntry, TileSource};

/// Requests the writer thread may have queued; the driver keeps far fewer in flight.
const REQUEST_QUEUE: usize = 256;

/// What the reader thread shares with the render thread.
#[derive(Default)]
struct Shared {
    listing: BTreeMap<TileId, TileEntry>,
    listing_changed: bool,
    /// Requests sent and not yet answered.
    asked: BTreeSet<TileId>,
    answers: Vec<Result<EncodedTile, LoadError>>,
    /// Why the connection ended, once it has.
    ended: Option<String>,
}

/// A daemon's tiles, fetched on request.
pub struct NetTileSource {
    shared: Arc<Mutex<Shared>>,
    requests: SyncSender<TileId>,
    /// The connection, to close it when the source is dropped.
    socket: std::net::TcpStream,
    /// The server's name and session, from its hello.
    pub server: texel_client::ServerInfo,
}

/// Why a daemon's tiles cannot be had.
#[derive(Debug, thiserror::Error)]
pub enum NetTileError {
    #[error(transparent)]
    Client(#[from] ClientError),
    #[error("the daemon speaks protocol version {0}: it serves no tiles (version 3)")]
    NoTiles(u16),
    #[error("cannot start the tile connection's threads: {0}")]
    Thread(std::io::Error),
}

fn lock(shared: &Mutex<Shared>) -> MutexGuard<'_, Shared> {
    shared
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl NetTileSource {
    /// Connects (protocol version 3) and starts the reader and writer threads;
    /// `timeout` bounds the connection and every write.
    pub fn connect(addr: SocketAddr, token: &str, timeout: Duration) -> Result<Self, NetTileError> {
        let mut client = BlockingClient::connect(addr, token, "texel-viewer tiles", timeout)?;
        if client.server.version < 3 {
            return Err(NetTileError::NoTiles(client.server.version));
        }
        // Scans' data is not this connection's business.
        client.set_max_in_flight(0);
        let mut writer = client.try_clone_stream()?;
        let socket = client.try_clone_stream()?;
        let server = client.server.clone();
        let shared = Arc::new(Mutex::new(Shared::default()));
        let (requests, asked_rx): (SyncSender<TileId>, Receiver<TileId>) =
            sync_channel(REQUEST_QUEUE);
        let reader_shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("texel-tiles-read".into())
            .spawn(move || read_loop(client, &reader_shared))
            .map_err(NetTileError::Thread)?;
        let writer_shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("texel-tiles-write".into())
            .spawn(move || {
                while let Ok(id) = asked_rx.recv() {
                    let sent = request_tile(id)
                        .map_err(|e| e.to_string())
                        .and_then(|bytes| writer.write_all(&bytes).map_err(|e| e.to_string()));
                    if let Err(e) = sent {
                        end(
                            &writer_shared,
                            format!("sending a tile request failed: {e}"),
                        );
                        return;
                    }
                }
            })
            .map_err(NetTileError::Thread)?;
        Ok(Self {
            shared,
            requests,
            socket,
            server,
        })
    }
}

/// Ends the connection's life: every unanswered request is answered with `reason`.
fn end(shared: &Mutex<Shared>, reason: String) {
    let mut s = lock(shared);
    let asked = std::mem::take(&mut s.asked);
    s.answers.extend(asked.into_iter().map(|id| {
        Err(LoadError {
            id,
            message: reason.clone(),
        })
    }));
    s.ended.get_or_insert(reason);
}

fn read_loop(mut client: BlockingClient, shared: &Mutex<Shared>) {
    loop {
        let message = match client.next_message() {
            Ok(Some(m)) => m,
            // An idle model sends only statuses: waiting longer is not a failure.
            Err(ClientError::Timeout(_)) => continue,
            Ok(None) => return end(shared, "the daemon closed the connection".into()),
            Err(e) => return end(shared, format!("the connection failed: {e}")),
        };
        let mut s = lock(shared);
        match message {
            Message::ModelReset { .. } => {
                // The server forgot our requests: answer them so they are asked again.
                s.listing.clear();
                s.listing_changed = true;
                let asked = std::mem::take(&mut s.asked);
                s.answers.extend(asked.into_iter().map(|id| {
                    Err(LoadError {
                        id,
                        message: "the stream was reset; asked again".into(),
                    })
                }));
            }
            Message::TileListed { id, listing } => {
                s.listing.insert(
                    id,
                    TileEntry {
                        id,
                        revision: listing.revision,
                        info: TileInfo {
                            bounds_min_m: listing.bounds_min_m,
                            bounds_max_m: listing.bounds_max_m,
                            geometric_error_m: listing.geometric_error_m,
                        },
                    },
                );
                s.listing_changed = true;
            }
            Message::TileWithdrawn { id } => {
                s.listing.remove(&id);
                s.listing_changed = true;
            }
            // Answers to requests this source no longer waits for are dropped.
            Message::TileData(tile) if s.asked.remove(&tile.id) => {
                s.answers.push(Ok(EncodedTile {
                    id: tile.id,
                    revision: tile.revision,
                    bytes: tile.data,
                }));
            }
            Message::TileUnavailable { id, reason } if s.asked.remove(&id) => {
                s.answers.push(Err(LoadError {
                    id,
                    message: reason,
                }));
            }
            Message::Goodbye { reason } | Message::Refused { reason } => {
                drop(s);
                return end(shared, format!("the daemon said goodbye: {reason}"));
            }
            _ => {}
        }
    }
}

impl TileSource for NetTileSource {
    fn poll_listing(&mut self) -> Option<Vec<TileEntry>> {
        let mut s = lock(&self.shared);
        if !std::mem::take(&mut s.listing_changed) {
            return None;
        }
        Some(s.listing.values().copied().collect())
    }

    fn request(&mut self, id: TileId) {
        let mut s = lock(&self.shared);
        let refused = match &s.ended {
            Some(reason) => Some(reason.clone()),
            None if s.asked.contains(&id) => None,
            None => match self.requests.try_send(id) {
                Ok(()) => {
                    s.asked.insert(id);
                    None
                }
                Err(TrySendError::Full(_)) => Some("too many tile requests queued".into()),
                Err(TrySendError::Disconnected(_)) => Some("the connection is closed".into()),
            },
        };
        if let Some(message) = refused {
            s.answers.push(Err(LoadError { id, message }));
        }
    }

    fn receive(&mut self) -> Vec<Result<EncodedTile, LoadError>> {
        std::mem::take(&mut lock(&self.shared).answers)
    }
}

impl Drop for NetTileSource {
    fn drop(&mut self) {
        // The reader wakes to a closed socket and ends; the writer ends with the
        // request channel.
        let _ = self.socket.shutdown(std::net::Shutdown::Both);
    }
}
