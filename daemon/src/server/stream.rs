//! A viewer's stream after its handshake: the snapshot, then live updates from its
//! bounded hub queue, again after every resync; and the slow-consumer policy. A
//! viewer is slow in one of two ways, each with its own answer:
//! - it reads, but slower than the model grows: its queue overflows and the hub cuts
//!   it off; it gets a fresh snapshot, up to `max_resyncs` times in a row, then is
//!   disconnected (at once with `slow_client = "disconnect"`);
//! - it stops reading: a write that cannot hand the socket a single byte within the
//!   write timeout ends the connection, so its slot returns (a resync would only be
//!   another snapshot it does not read).

use std::sync::atomic::Ordering;
use std::time::Duration;

use bytes::{Bytes, BytesMut};
use texel::wire::{Limits, Message, decode_frame};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio_util::sync::CancellationToken;

use crate::config::SlowClientPolicy;
use crate::hub::{Hub, HubError};

/// How a viewer's stream ended.
pub enum End {
    ClientLeft,
    Shutdown,
    /// It fell behind more often in a row than the policy allows.
    TooSlow(u32),
    /// A write made no progress within the write timeout.
    Stalled(Duration),
    Error(String),
}

impl End {
    /// What the viewer is told (if it still reads) and the log says.
    pub fn reason(&self) -> String {
        match self {
            Self::ClientLeft => "the viewer left".into(),
            Self::Shutdown => "the daemon is shutting down".into(),
            Self::TooSlow(resyncs) => {
                format!("too slow: fell behind {resyncs} time(s) in a row; disconnected")
            }
            Self::Stalled(timeout) => format!(
                "too slow: read nothing for {} ms; disconnected",
                timeout.as_millis()
            ),
            Self::Error(e) => e.clone(),
        }
    }
}

/// The connection-wide settings of a stream.
pub struct StreamSettings<'a> {
    pub slow_client: SlowClientPolicy,
    pub max_resyncs: u32,
    pub write_timeout: Duration,
    pub shutdown: &'a CancellationToken,
}

/// Writes one frame. Each write must hand the socket some bytes within
/// `write_timeout`: a viewer reading slowly but steadily keeps going however long the
/// frame, one that stopped reading is cut off.
pub async fn write_frame(
    wr: &mut OwnedWriteHalf,
    frame: &[u8],
    write_timeout: Duration,
    shutdown: &CancellationToken,
) -> Result<(), End> {
    let mut written = 0;
    while let Some(rest) = frame.get(written..).filter(|r| !r.is_empty()) {
        let n = tokio::select! {
            r = tokio::time::timeout(write_timeout, wr.write(rest)) => match r {
                Ok(Ok(0)) => return Err(End::Error("write failed: connection closed".into())),
                Ok(Ok(n)) => n,
                Ok(Err(e)) => return Err(End::Error(format!("write failed: {e}"))),
                Err(_) => return Err(End::Stalled(write_timeout)),
            },
            () = shutdown.cancelled() => return Err(End::Shutdown),
        };
        written += n;
    }
    Ok(())
}

/// Sends a goodbye and closes, giving up after `timeout`.
pub async fn goodbye(wr: &mut OwnedWriteHalf, reason: &str, timeout: Duration) {
    let message = Message::Goodbye {
        reason: reason.to_string(),
    };
    if let Ok(bytes) = message.encode() {
        let _ = tokio::time::timeout(timeout, async {
            let _ = wr.write_all(&bytes).await;
            let _ = wr.shutdown().await;
        })
        .await;
    }
}

/// Streams the model to a viewer until it leaves, is dropped, or the hub closes.
/// Resyncs are counted in `resynced`.
pub async fn stream_model(
    rd: &mut OwnedReadHalf,
    wr: &mut OwnedWriteHalf,
    inbuf: &mut BytesMut,
    hub: &Hub,
    settings: &StreamSettings<'_>,
    mut resynced: impl FnMut(),
) -> End {
    let (write_timeout, shutdown) = (settings.write_timeout, settings.shutdown);
    let mut resyncs = 0u32;
    loop {
        let mut sub = match hub.subscribe() {
            Ok(s) => s,
            Err(HubError::Closed) => return End::Shutdown,
            Err(e) => return End::Error(e.to_string()),
        };
        let client_id = sub.client_id;
        let result = async {
            for frame in &sub.snapshot {
                write_frame(wr, frame, write_timeout, shutdown).await?;
            }
            loop {
                let next: Option<Bytes> = tokio::select! {
                    f = sub.live.recv() => f,
                    r = rd.read_buf(inbuf) => {
                        client_input(r, inbuf)?;
                        continue;
                    }
                    () = shutdown.cancelled() => return Err(End::Shutdown),
                };
                if sub.lagged.load(Ordering::Acquire) {
                    return Ok(());
                }
                match next {
                    Some(frame) => {
                        write_frame(wr, &frame, write_timeout, shutdown).await?;
                        if sub.live.is_empty() {
                            // Caught up: earlier resyncs are forgiven.
                            resyncs = 0;
                        }
                    }
                    // The hub dropped this feed: cut off for lagging, or closed.
                    None if sub.lagged.load(Ordering::Acquire) => return Ok(()),
                    None => return Err(End::Shutdown),
                }
            }
        }
        .await;
        hub.unsubscribe(client_id);
        // `Ok` means the client's queue overflowed.
        if let Err(end) = result {
            return end;
        }
        resyncs += 1;
        if settings.slow_client == SlowClientPolicy::Disconnect || resyncs > settings.max_resyncs {
            return End::TooSlow(resyncs);
        }
        resynced();
    }
}

/// Handles bytes from a client after the handshake: a goodbye or end of stream ends
/// the connection; anything else is a protocol error.
fn client_input(read: std::io::Result<usize>, inbuf: &mut BytesMut) -> Result<(), End> {
    match read {
        Ok(0) => return Err(End::ClientLeft),
        Ok(_) => {}
        Err(e) => return Err(End::Error(format!("read failed: {e}"))),
    }
    match decode_frame(inbuf, &Limits::FROM_CLIENT) {
        Ok(None) => Ok(()),
        Ok(Some((Message::Goodbye { .. }, _))) => Err(End::ClientLeft),
        Ok(Some((m, _))) => Err(End::Error(format!(
            "unexpected {} from the client",
            m.kind_name()
        ))),
        Err(e) => Err(End::Error(format!("invalid message: {e}"))),
    }
}
