//! The async (tokio) TCP client of the viewer stream.

use texel::model::ScanId;
use texel::wire::{DEFAULT_MAX_IN_FLIGHT, FetchPlan, Message};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpStream, ToSocketAddrs};

use crate::{ClientError, FrameReader, ServerInfo, hello, request, request_tile, welcome};

/// An async connection to a daemon; it requests the listed scans it lacks as it
/// reads (see the crate's documentation).
pub struct Client {
    stream: TcpStream,
    frames: FrameReader,
    pub server: ServerInfo,
    fetch: FetchPlan,
    max_in_flight: usize,
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
            fetch: FetchPlan::new(),
            max_in_flight: DEFAULT_MAX_IN_FLIGHT,
        })
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
    pub async fn request_scan(&mut self, id: ScanId) -> Result<(), ClientError> {
        self.send_raw(&request(id)?).await
    }

    /// Asks for tile `id`'s data (answered by `TileData` or `TileUnavailable`).
    pub async fn request_tile(&mut self, id: texel::tile::TileId) -> Result<(), ClientError> {
        self.send_raw(&request_tile(id)?).await
    }

    /// Writes bytes as they are (a test's hostile or hand-made frames).
    pub async fn send_raw(&mut self, bytes: &[u8]) -> Result<(), ClientError> {
        self.stream.write_all(bytes).await.map_err(ClientError::Io)
    }

    /// The next message; `None` when the server closed the connection cleanly.
    /// Requests the listed scans it still lacks first.
    pub async fn next_message(&mut self) -> Result<Option<Message>, ClientError> {
        let message = read_async(&mut self.stream, &mut self.frames).await?;
        if let Some(m) = &message {
            self.fetch.observe(m);
            if self.max_in_flight > 0 {
                for id in self.fetch.wanted(self.max_in_flight) {
                    self.request_scan(id).await?;
                }
            }
        }
        Ok(message)
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
