//! TCP transports of the viewer stream's client side (`texel::wire::client`): a
//! [`BlockingClient`] for a plain thread and, with the `tokio` feature, an async
//! [`Client`]. A viewer talks to a daemon through these and the protocol alone.

use std::io::Read;
use std::time::Duration;

use texel::wire::Message;
pub use texel::wire::client::{
    Applied, ClientError, FrameReader, Replica, ReplicaError, ServerInfo, Update, hello, update,
    welcome,
};

#[cfg(feature = "tokio")]
mod async_client;
#[cfg(feature = "tokio")]
pub use async_client::Client;

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
