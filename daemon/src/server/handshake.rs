//! The handshake of a pending connection: its hello, read within the handshake timeout
//! (or cut short when its pending place is taken to make room, or at shutdown) and
//! bounded in size by the client frame limit, then checked: protocol version and
//! token, compared in constant time.

use std::time::Duration;

use bytes::BytesMut;
use subtle::ConstantTimeEq;
use texel::wire::{Limits, MIN_PROTOCOL_VERSION, Message, PROTOCOL_VERSION, decode_frame};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio_util::sync::CancellationToken;

/// How waiting for a hello ended.
pub enum HelloOutcome {
    Hello(Message),
    /// Not a valid frame, or the connection failed or closed first.
    Invalid(String),
    TimedOut,
    /// The pending place was taken for a newer connection.
    Evicted,
    Shutdown,
}

/// Waits for the hello, at most `timeout`.
pub async fn read_hello<R: AsyncRead + Unpin + Send>(
    rd: &mut R,
    buf: &mut BytesMut,
    timeout: Duration,
    evicted: &CancellationToken,
    shutdown: &CancellationToken,
) -> HelloOutcome {
    tokio::select! {
        r = tokio::time::timeout(timeout, read_message(rd, buf)) => match r {
            Ok(Ok(m)) => HelloOutcome::Hello(m),
            Ok(Err(e)) => HelloOutcome::Invalid(e),
            Err(_) => HelloOutcome::TimedOut,
        },
        () = evicted.cancelled() => HelloOutcome::Evicted,
        () = shutdown.cancelled() => HelloOutcome::Shutdown,
    }
}

/// Reads one client message, bounded by the client limits: the decoder refuses a
/// frame longer than the limit before waiting for it, so `buf` stays small.
async fn read_message<R: AsyncRead + Unpin + Send>(
    rd: &mut R,
    buf: &mut BytesMut,
) -> Result<Message, String> {
    loop {
        match decode_frame(buf, &Limits::FROM_CLIENT) {
            Ok(Some((message, used))) => {
                let _ = buf.split_to(used);
                return Ok(message);
            }
            Ok(None) => {}
            Err(e) => return Err(format!("invalid message: {e}")),
        }
        match rd.read_buf(buf).await {
            Ok(0) => return Err("closed before its hello".into()),
            Ok(_) => {}
            Err(e) => return Err(format!("read failed: {e}")),
        }
    }
}

/// An admitted client: its name and the protocol version the stream speaks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Admitted {
    pub client_name: String,
    pub version: u16,
}

/// Checks the hello: protocol version and token (required when `token` is set).
/// Versions 2 and 3 are served (2 without the level-of-detail tree).
pub fn admit(hello: Message, token: Option<&str>) -> Result<Admitted, String> {
    let Message::ClientHello {
        version,
        token: given,
        client_name,
    } = hello
    else {
        return Err(format!("expected ClientHello, got {}", hello.kind_name()));
    };
    if version == 1 {
        // Version 1 clients expect every scan's data in the snapshot; this daemon
        // lists scans and sends them on request.
        return Err(format!(
            "protocol version 1 is not served; this daemon speaks version {PROTOCOL_VERSION}: update the viewer"
        ));
    }
    if !(MIN_PROTOCOL_VERSION..=PROTOCOL_VERSION).contains(&version) {
        return Err(format!(
            "protocol version {version} is not supported; this server speaks {MIN_PROTOCOL_VERSION} to {PROTOCOL_VERSION}"
        ));
    }
    if let Some(expected) = token {
        // Constant time in the token's contents, so timing reveals nothing of it.
        let ok: bool = expected.as_bytes().ct_eq(given.as_bytes()).into();
        if !ok {
            return Err("wrong token".into());
        }
    }
    Ok(Admitted {
        client_name,
        version,
    })
}

/// Sends `Refused { reason }` and closes, giving up after `timeout` (a client that
/// does not read is not waited for).
pub async fn refuse<W: AsyncWrite + Unpin + Send>(wr: &mut W, reason: &str, timeout: Duration) {
    let message = Message::Refused {
        reason: reason
            .chars()
            .take(texel::wire::MAX_REASON_LEN / 4)
            .collect(),
    };
    if let Ok(bytes) = message.encode() {
        let _ = tokio::time::timeout(timeout, async {
            let _ = wr.write_all(&bytes).await;
            let _ = wr.shutdown().await;
        })
        .await;
    }
}
