//! The async (tokio) TCP client of the viewer stream.

use texel::wire::Message;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpStream, ToSocketAddrs};

use crate::{ClientError, FrameReader, ServerInfo, hello, welcome};

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
