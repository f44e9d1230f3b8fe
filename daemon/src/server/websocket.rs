//! The viewer stream over WebSocket: after the upgrade (`http`), a bridge between the
//! WebSocket's binary messages and an in-memory byte pipe, with the native viewer's
//! connection logic (hello and token, slot, snapshot, stream, slow-client policy,
//! goodbye) on the pipe's other end, unchanged.
//!
//! Each client message's bytes go into the pipe as they are, so message boundaries
//! carry no meaning (a wire frame may span messages, a message hold several); the
//! server sends whatever the pipe yields in one read as one binary message. The pipe
//! is bounded: a browser that stops reading fills it and the socket, and the stream's
//! write timeout drops it as it drops a native viewer. Text messages are not part of
//! the protocol and end the connection.

use std::net::SocketAddr;
use std::sync::Mutex;

use bytes::BytesMut;
use futures_util::{SinkExt, StreamExt};
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};
use tokio::net::TcpStream;
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::Message as WsMessage;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, Role, WebSocketConfig};
use tokio_util::sync::CancellationToken;

use super::pending::PendingTicket;
use super::{Shared, Transport};

/// The largest message or frame a client may send: its messages are a hello (at most
/// 4 KiB, `texel::wire::MAX_CLIENT_FRAME_LEN`) and 13-byte requests.
const MAX_CLIENT_MESSAGE: usize = 64 * 1024;
/// The most the server sends in one message.
const CHUNK: usize = 64 * 1024;
/// The pipe between the bridge and the viewer's connection logic, each way.
const PIPE: usize = 256 * 1024;

/// Runs a viewer over an upgraded connection (`early`: bytes that followed the request
/// head). The pending place is kept until the hello, which gets a handshake timeout of
/// its own from the upgrade on.
pub async fn serve(
    stream: TcpStream,
    early: Vec<u8>,
    peer: SocketAddr,
    ticket: PendingTicket,
    shared: &Shared,
) {
    let config = WebSocketConfig::default()
        // Client messages are tiny; the default 128 KiB read buffer is for bulk input.
        .read_buffer_size(8 * 1024)
        .write_buffer_size(CHUNK)
        .max_write_buffer_size(4 * CHUNK)
        .max_message_size(Some(MAX_CLIENT_MESSAGE))
        .max_frame_size(Some(MAX_CLIENT_MESSAGE));
    let ws = WebSocketStream::from_partially_read(stream, early, Role::Server, Some(config)).await;
    let (viewer_end, bridge_end) = tokio::io::duplex(PIPE);
    let viewer_done = CancellationToken::new();
    let viewer = async {
        let (rd, wr) = tokio::io::split(viewer_end);
        let deadline = tokio::time::Instant::now() + shared.options.handshake_timeout;
        let inbuf = BytesMut::with_capacity(1024);
        super::viewer(
            rd,
            wr,
            inbuf,
            peer,
            ticket,
            None,
            deadline,
            Transport::WebSocket,
            shared,
        )
        .await;
        // The pipe's end is dropped here: the bridge sends what is left, then closes.
        viewer_done.cancel();
    };
    let bridge = async {
        // The goodbye gets the same bounded time to reach the browser as a native one.
        let linger = async {
            viewer_done.cancelled().await;
            tokio::time::sleep(shared.options.goodbye_timeout).await;
        };
        tokio::select! {
            () = bridge(ws, bridge_end, peer) => {}
            () = linger => {}
        }
    };
    tokio::join!(viewer, bridge);
}

/// Carries bytes both ways until both directions have ended: client messages into the
/// pipe (its end closed when the client closes or misbehaves, which the viewer reads
/// as the client leaving), the pipe's bytes out as binary messages, then a close.
async fn bridge(ws: WebSocketStream<TcpStream>, pipe: DuplexStream, peer: SocketAddr) {
    let (mut sink, mut source) = ws.split();
    let (mut from_viewer, mut to_viewer) = tokio::io::split(pipe);
    // Why the client's input was cut, for the close frame.
    let close_frame: Mutex<Option<CloseFrame>> = Mutex::new(None);
    let set_close = |code, reason: &'static str| {
        let mut frame = close_frame
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        *frame = Some(CloseFrame {
            code,
            reason: reason.into(),
        });
    };
    let inbound = async {
        while let Some(message) = source.next().await {
            match message {
                Ok(WsMessage::Binary(bytes)) => {
                    if to_viewer.write_all(&bytes).await.is_err() {
                        break;
                    }
                }
                Ok(WsMessage::Text(_)) => {
                    tracing::debug!(%peer, "websocket: a text message; the stream is binary");
                    set_close(CloseCode::Unsupported, "the viewer stream is binary");
                    break;
                }
                // Pings are answered by the library; a close is answered as the stream
                // ends (reading on sends the reply, then yields nothing).
                Ok(_) => {}
                Err(e) => {
                    tracing::debug!(%peer, "websocket: {e}");
                    set_close(CloseCode::Protocol, "invalid WebSocket input");
                    break;
                }
            }
        }
        let _ = to_viewer.shutdown().await;
    };
    let outbound = async {
        let mut buf = BytesMut::with_capacity(CHUNK);
        loop {
            buf.reserve(CHUNK);
            match (&mut from_viewer)
                .take(CHUNK as u64)
                .read_buf(&mut buf)
                .await
            {
                Ok(0) | Err(_) => break,
                Ok(_) => {
                    let message = WsMessage::Binary(buf.split().freeze());
                    if sink.send(message).await.is_err() {
                        return;
                    }
                }
            }
        }
        let frame = close_frame
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take();
        let _ = sink.send(WsMessage::Close(frame)).await;
    };
    tokio::join!(inbound, outbound);
}
