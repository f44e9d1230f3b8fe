//! The viewer stream client: connect, handshake, receive messages
//! ([`Client`] for tokio, [`BlockingClient`] for a plain thread), and a [`Replica`]
//! that applies them to a local `texel::model::Model` (resets and snapshots
//! included), so every viewer holds the same model as the daemon.

use std::io::Read;
use std::time::Duration;

use bytes::BytesMut;
use texel::model::{Model, ModelError, ModelEvent, ScanId};
use texel::wire::{Limits, Message, PROTOCOL_VERSION, Status, WireError, decode_frame};
use thiserror::Error;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpStream, ToSocketAddrs};

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
struct FrameReader {
    buf: BytesMut,
}

impl FrameReader {
    fn take_message(&mut self) -> Result<Option<Message>, ClientError> {
        match decode_frame(&self.buf, &Limits::FROM_SERVER)? {
            Some((message, used)) => {
                let _ = self.buf.split_to(used);
                Ok(Some(message))
            }
            None => Ok(None),
        }
    }
}

fn hello(token: &str, client_name: &str) -> Result<Vec<u8>, ClientError> {
    Ok(Message::ClientHello {
        version: PROTOCOL_VERSION,
        token: token.to_string(),
        client_name: client_name.to_string(),
    }
    .encode()?)
}

fn welcome(message: Message) -> Result<ServerInfo, ClientError> {
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

/// An async connection to a daemon.
pub struct Client {
    stream: TcpStream,
    frames: FrameReader,
    pub server: ServerInfo,
}

impl Client {
    /// Connects and handshakes (`token` may be empty when the server needs none).
    pub async fn connect(
        addr: impl ToSocketAddrs,
        token: &str,
        client_name: &str,
    ) -> Result<Self, ClientError> {
        let mut stream = TcpStream::connect(addr)
            .await
            .map_err(ClientError::Connect)?;
        let _ = stream.set_nodelay(true);
        stream
            .write_all(&hello(token, client_name)?)
            .await
            .map_err(ClientError::Io)?;
        let mut frames = FrameReader::default();
        let first = read_async(&mut stream, &mut frames)
            .await?
            .ok_or(ClientError::Truncated)?;
        let server = welcome(first)?;
        Ok(Self {
            stream,
            frames,
            server,
        })
    }

    /// The next message; `None` when the server closed the connection cleanly.
    pub async fn next_message(&mut self) -> Result<Option<Message>, ClientError> {
        read_async(&mut self.stream, &mut self.frames).await
    }

    /// Says goodbye and closes.
    pub async fn close(mut self) {
        if let Ok(bytes) = (Message::Goodbye {
            reason: "viewer closed".into(),
        })
        .encode()
        {
            let _ = self.stream.write_all(&bytes).await;
        }
        let _ = self.stream.shutdown().await;
    }
}

async fn read_async(
    stream: &mut TcpStream,
    frames: &mut FrameReader,
) -> Result<Option<Message>, ClientError> {
    loop {
        if let Some(m) = frames.take_message()? {
            return Ok(Some(m));
        }
        let n = stream
            .read_buf(&mut frames.buf)
            .await
            .map_err(ClientError::Io)?;
        if n == 0 {
            return if frames.buf.is_empty() {
                Ok(None)
            } else {
                Err(ClientError::Truncated)
            };
        }
    }
}

/// A blocking connection, for a viewer's network thread.
pub struct BlockingClient {
    stream: std::net::TcpStream,
    frames: FrameReader,
    pub server: ServerInfo,
}

impl BlockingClient {
    /// Connects and handshakes; `timeout` bounds the connection and every read.
    pub fn connect(
        addr: std::net::SocketAddr,
        token: &str,
        client_name: &str,
        timeout: Duration,
    ) -> Result<Self, ClientError> {
        use std::io::Write;
        let mut stream =
            std::net::TcpStream::connect_timeout(&addr, timeout).map_err(ClientError::Connect)?;
        stream
            .set_read_timeout(Some(timeout))
            .map_err(ClientError::Io)?;
        let _ = stream.set_nodelay(true);
        stream
            .write_all(&hello(token, client_name)?)
            .map_err(ClientError::Io)?;
        let mut client = Self {
            stream,
            frames: FrameReader::default(),
            server: ServerInfo {
                version: 0,
                server_name: String::new(),
                session_name: String::new(),
            },
        };
        let first = client.next_message()?.ok_or(ClientError::Truncated)?;
        client.server = welcome(first)?;
        Ok(client)
    }

    /// The next message; `None` when the server closed the connection cleanly.
    pub fn next_message(&mut self) -> Result<Option<Message>, ClientError> {
        let mut chunk = vec![0u8; 64 * 1024];
        loop {
            if let Some(m) = self.frames.take_message()? {
                return Ok(Some(m));
            }
            let n = match self.stream.read(&mut chunk) {
                Ok(n) => n,
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    return Err(ClientError::Timeout(
                        self.stream
                            .read_timeout()
                            .ok()
                            .flatten()
                            .unwrap_or_default(),
                    ));
                }
                Err(e) => return Err(ClientError::Io(e)),
            };
            if n == 0 {
                return if self.frames.buf.is_empty() {
                    Ok(None)
                } else {
                    Err(ClientError::Truncated)
                };
            }
            self.frames.buf.extend_from_slice(&chunk[..n]);
        }
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
    Status,
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

/// A viewer's copy of the daemon's model.
#[derive(Debug, Default)]
pub struct Replica {
    pub model: Model,
    /// True between `SnapshotComplete` and the next `ModelReset`.
    pub live: bool,
    /// How many times the server reset the model (1 for the first snapshot).
    pub resets: u64,
    pub status: Option<Status>,
}

impl Replica {
    pub fn new() -> Self {
        Self::default()
    }

    /// Applies one message (decoding a scan's texture).
    pub fn apply(&mut self, message: Message) -> Result<Applied, ReplicaError> {
        Ok(match message {
            Message::ModelReset { scan_count } => {
                self.model = Model::new();
                self.live = false;
                self.resets += 1;
                Applied::Reset { scan_count }
            }
            Message::SnapshotComplete { .. } => {
                self.live = true;
                Applied::SnapshotComplete
            }
            Message::ScanAdded(wire) => {
                let (id, scan, world_from_scan) = wire.into_scan()?;
                self.model.apply(ModelEvent::ScanAdded {
                    id,
                    scan: std::sync::Arc::new(scan),
                    world_from_scan,
                })?;
                Applied::ScanAdded(id)
            }
            Message::PoseRevised {
                id,
                world_from_scan,
            } => {
                self.model.apply(ModelEvent::PoseRevised {
                    id,
                    world_from_scan,
                })?;
                Applied::PoseRevised(id)
            }
            Message::Status(status) => {
                self.status = Some(*status);
                Applied::Status
            }
            Message::Goodbye { reason } | Message::Refused { reason } => Applied::Goodbye(reason),
            Message::ClientHello { .. } | Message::ServerHello { .. } => Applied::Ignored,
        })
    }
}
