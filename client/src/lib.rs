//! TCP transports of the viewer stream's client side (`texel::wire::client`): a
//! [`BlockingClient`] for a plain thread and, with the `tokio` feature, an async
//! [`Client`]. A viewer talks to a daemon through these and the protocol alone.
//!
//! The daemon lists its scans and sends their data on request (protocol version 2):
//! by default a client requests every listed scan by itself, highest priority first,
//! at most [`DEFAULT_MAX_IN_FLIGHT`] outstanding, as it reads, so a caller that only
//! reads messages still ends up with the whole model. A viewer that fetches within a
//! budget turns this off (`set_max_in_flight(0)`) and sends its own requests.

use std::io::Read;
use std::time::Duration;

use texel::wire::Message;
pub use texel::wire::client::{
    Applied, ClientError, ExposureJoin, FrameReader, Replica, ReplicaError, ServerInfo, Update,
    hello, request, request_tile, update, welcome,
};
pub use texel::wire::{DEFAULT_MAX_IN_FLIGHT, FetchPlan, TileCatalog, TileEvent};

#[cfg(feature = "tokio")]
mod async_client;
#[cfg(feature = "tokio")]
pub use async_client::Client;
#[cfg(feature = "zenoh")]
pub mod zenoh_gateway;

/// A blocking connection, for a viewer's network thread.
pub struct BlockingClient {
    stream: std::net::TcpStream,
    frames: FrameReader,
    pub server: ServerInfo,
    fetch: FetchPlan,
    max_in_flight: usize,
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
        stream
            .set_write_timeout(Some(timeout))
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
            fetch: FetchPlan::new(),
            max_in_flight: DEFAULT_MAX_IN_FLIGHT,
        };
        let first = client.next_message()?.ok_or(ClientError::Truncated)?;
        client.server = welcome(first)?;
        Ok(client)
    }

    /// How many scan requests the client keeps outstanding by itself; 0: none (the
    /// caller sends its own with [`Self::request_scan`]).
    pub fn set_max_in_flight(&mut self, max_in_flight: usize) {
        self.max_in_flight = max_in_flight;
    }

    /// What the client knows of the listed scans and its requests.
    pub fn fetch_plan(&self) -> &FetchPlan {
        &self.fetch
    }

    /// Asks for scan `id`'s data (answered by `ScanAdded` or `ScanUnavailable`).
    pub fn request_scan(&mut self, id: texel::model::ScanId) -> Result<(), ClientError> {
        use std::io::Write;
        self.stream
            .write_all(&request(id)?)
            .map_err(ClientError::Io)
    }

    /// Asks for tile `id`'s data (answered by `TileData` or `TileUnavailable`).
    pub fn request_tile(&mut self, id: texel::tile::TileId) -> Result<(), ClientError> {
        use std::io::Write;
        self.stream
            .write_all(&request_tile(id)?)
            .map_err(ClientError::Io)
    }

    /// A second handle on the connection, for a thread that only writes requests
    /// while this one blocks reading.
    pub fn try_clone_stream(&self) -> Result<std::net::TcpStream, ClientError> {
        self.stream.try_clone().map_err(ClientError::Io)
    }

    /// The next message; `None` when the server closed the connection cleanly.
    /// Requests the listed scans it still lacks first (see the crate's documentation).
    pub fn next_message(&mut self) -> Result<Option<Message>, ClientError> {
        let message = self.read_message()?;
        if let Some(m) = &message {
            self.fetch.observe(m);
            if self.max_in_flight > 0 {
                for id in self.fetch.wanted(self.max_in_flight) {
                    self.request_scan(id)?;
                }
            }
        }
        Ok(message)
    }

    fn read_message(&mut self) -> Result<Option<Message>, ClientError> {
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
