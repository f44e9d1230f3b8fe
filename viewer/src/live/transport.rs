//! The viewer's blocking link to a daemon: the handshake and message framing of
//! `texel::wire::client` over a TCP stream that the connection thread both reads
//! (the model's updates) and writes (its requests for scans).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

use texel::wire::Message;
use texel_client::{ClientError, FrameReader, ServerInfo, hello, welcome};

pub struct Link {
    stream: TcpStream,
    frames: FrameReader,
    chunk: Vec<u8>,
    pub server: ServerInfo,
}

impl Link {
    /// Connects and handshakes; `timeout` bounds the connection and the handshake.
    pub fn connect(
        addr: SocketAddr,
        token: &str,
        client_name: &str,
        timeout: Duration,
    ) -> Result<Self, ClientError> {
        let mut stream =
            TcpStream::connect_timeout(&addr, timeout).map_err(ClientError::Connect)?;
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
        let mut link = Self {
            stream,
            frames: FrameReader::default(),
            chunk: vec![0u8; 64 * 1024],
            server: ServerInfo {
                version: 0,
                server_name: String::new(),
                session_name: String::new(),
            },
        };
        let first = link.next_message()?.ok_or(ClientError::Truncated)?;
        link.server = welcome(first)?;
        Ok(link)
    }

    /// How long a read waits before it reports a timeout (so the caller can send
    /// what it was asked to between reads).
    pub fn set_read_timeout(&mut self, timeout: Duration) -> Result<(), ClientError> {
        self.stream
            .set_read_timeout(Some(timeout.max(Duration::from_millis(1))))
            .map_err(ClientError::Io)
    }

    /// The next message; `None` when the server closed the connection cleanly.
    pub fn next_message(&mut self) -> Result<Option<Message>, ClientError> {
        loop {
            if let Some(m) = self.frames.take_message()? {
                return Ok(Some(m));
            }
            let n = match self.stream.read(&mut self.chunk) {
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
            self.frames.buf.extend_from_slice(&self.chunk[..n]);
        }
    }

    /// Sends one message whole.
    pub fn send(&mut self, message: &Message) -> Result<(), ClientError> {
        let bytes = message.encode()?;
        self.stream.write_all(&bytes).map_err(ClientError::Io)
    }
}
