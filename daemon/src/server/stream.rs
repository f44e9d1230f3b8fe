//! A viewer's stream after its handshake: the snapshot (scan listings), then live
//! updates from its bounded hub queue and the answers to its scan requests, again
//! after every resync; and the slow-consumer policy.
//!
//! The client's messages are read all along, while frames are written: its requests
//! queue (bounded by `serve.max_requests_in_flight`, beyond which it is disconnected
//! with the reason) and are served one at a time: the scan's frame is fetched on a
//! blocking thread (a store may read it from disk) while live frames keep flowing,
//! then checked against the hub and written between two live frames. A reset (a
//! resync) drops the queued requests, as the client forgets them too.
//!
//! A viewer is slow in one of two ways, each with its own answer:
//! - it reads, but slower than the model grows: its queue overflows and the hub cuts
//!   it off; it gets a fresh snapshot, up to `max_resyncs` times in a row, then is
//!   disconnected (at once with `slow_client = "disconnect"`);
//! - it stops reading: a write that cannot hand the socket a single byte within the
//!   write timeout ends the connection, so its slot returns (a resync would only be
//!   another snapshot it does not read).

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use bytes::{Bytes, BytesMut};
use texel::model::ScanId;
use texel::tile::TileId;
use texel::wire::{Limits, MAX_REASON_LEN, Message, decode_frame};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::config::SlowClientPolicy;
use crate::hub::{FetchError, Hub, HubError};

/// How a viewer's stream ended.
pub enum End {
    ClientLeft,
    Shutdown,
    /// It fell behind more often in a row than the policy allows.
    TooSlow(u32),
    /// A write made no progress within the write timeout.
    Stalled(Duration),
    /// It had more scan requests outstanding than the limit.
    TooManyRequests(usize),
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
            Self::TooManyRequests(limit) => format!(
                "too many scan requests: more than {limit} in flight \
                 (serve.max_requests_in_flight = {limit}); disconnected"
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
    /// Scan and tile requests a client may have outstanding.
    pub max_requests_in_flight: usize,
    /// The client speaks version 3: it may request tiles.
    pub tiles: bool,
    /// The client's protocol version (what its subscription is sent).
    pub version: u16,
}

/// A client's request for data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request {
    Scan(ScanId),
    Tile(TileId),
}

/// Writes one frame. Each write must hand the socket some bytes within
/// `write_timeout`: a viewer reading slowly but steadily keeps going however long the
/// frame, one that stopped reading is cut off.
pub async fn write_frame<W: AsyncWrite + Unpin + Send>(
    wr: &mut W,
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
pub async fn goodbye<W: AsyncWrite + Unpin + Send>(wr: &mut W, reason: &str, timeout: Duration) {
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

/// A request being answered: what was asked and the blocking fetch of its frame.
type Fetching = Option<(Request, JoinHandle<Result<Bytes, FetchError>>)>;

/// Streams the model to a viewer until it leaves, is dropped, or the hub closes.
/// Resyncs are counted in `resynced`.
pub async fn stream_model<R: AsyncRead + Unpin + Send, W: AsyncWrite + Unpin + Send>(
    rd: &mut R,
    wr: &mut W,
    inbuf: &mut BytesMut,
    hub: &Arc<Hub>,
    settings: &StreamSettings<'_>,
    resynced: impl FnMut(),
) -> End {
    let limit = settings.max_requests_in_flight.max(1);
    // Requests received and not yet answered (or dropped at a reset); the queue holds
    // those not yet started, so it never holds more than `limit`.
    let outstanding = AtomicUsize::new(0);
    let (requests_tx, mut requests_rx) = mpsc::channel(limit);
    let (end_tx, mut end_rx) = oneshot::channel();
    let reader = read_client(
        rd,
        inbuf,
        &outstanding,
        limit,
        settings.tiles,
        requests_tx,
        end_tx,
    );
    let writer = write_stream(
        wr,
        hub,
        settings,
        &outstanding,
        &mut requests_rx,
        &mut end_rx,
        resynced,
    );
    tokio::select! {
        end = writer => end,
        () = reader => End::Error("the client reader ended".into()),
    }
}

/// Reads the client's messages until it leaves or misbehaves; then hands the writer
/// the reason (which it acts on between two frames, so a goodbye never lands inside
/// a frame) and waits to be dropped.
async fn read_client<R: AsyncRead + Unpin + Send>(
    rd: &mut R,
    inbuf: &mut BytesMut,
    outstanding: &AtomicUsize,
    limit: usize,
    tiles: bool,
    requests: mpsc::Sender<Request>,
    end_tx: oneshot::Sender<End>,
) {
    let end = 'read: loop {
        // Every whole frame first: the decoder refuses an over-long one before its
        // body is awaited, so `inbuf` stays within a frame and a read.
        loop {
            match decode_frame(inbuf, &Limits::FROM_CLIENT) {
                Ok(Some((message, used))) => {
                    let _ = inbuf.split_to(used);
                    let request = match message {
                        Message::RequestScan { id } => Request::Scan(id),
                        Message::RequestTile { id } if tiles => Request::Tile(id),
                        Message::Goodbye { .. } => break 'read End::ClientLeft,
                        m => {
                            break 'read End::Error(format!(
                                "unexpected {} from the client",
                                m.kind_name()
                            ));
                        }
                    };
                    if outstanding.load(Ordering::Acquire) >= limit {
                        break 'read End::TooManyRequests(limit);
                    }
                    outstanding.fetch_add(1, Ordering::AcqRel);
                    if requests.try_send(request).is_err() {
                        break 'read End::TooManyRequests(limit);
                    }
                }
                Ok(None) => break,
                Err(e) => break 'read End::Error(format!("invalid message: {e}")),
            }
        }
        match rd.read_buf(inbuf).await {
            Ok(0) => break End::ClientLeft,
            Ok(_) => {}
            Err(e) => break End::Error(format!("read failed: {e}")),
        }
    };
    let _ = end_tx.send(end);
    std::future::pending::<()>().await;
}

/// The reason the reader gave, if it ended: it explains a failed write better.
fn reader_end(end_rx: &mut oneshot::Receiver<End>, fallback: End) -> End {
    end_rx.try_recv().unwrap_or(fallback)
}

/// Snapshots, live frames and request answers, until the stream ends.
async fn write_stream<W: AsyncWrite + Unpin + Send>(
    wr: &mut W,
    hub: &Arc<Hub>,
    settings: &StreamSettings<'_>,
    outstanding: &AtomicUsize,
    requests: &mut mpsc::Receiver<Request>,
    end_rx: &mut oneshot::Receiver<End>,
    mut resynced: impl FnMut(),
) -> End {
    let (write_timeout, shutdown) = (settings.write_timeout, settings.shutdown);
    let mut resyncs = 0u32;
    let mut fetching: Fetching = None;
    loop {
        let mut sub = match hub.subscribe_version(settings.version) {
            Ok(s) => s,
            Err(HubError::Closed) => return End::Shutdown,
            Err(e) => return End::Error(e.to_string()),
        };
        // The snapshot starts with a reset: the client forgets its requests, and so
        // does the server.
        if fetching.take().is_some() {
            outstanding.fetch_sub(1, Ordering::AcqRel);
        }
        while requests.try_recv().is_ok() {
            outstanding.fetch_sub(1, Ordering::AcqRel);
        }
        let client_id = sub.client_id;
        let result = async {
            for frame in &sub.snapshot {
                if let Ok(end) = end_rx.try_recv() {
                    return Err(end);
                }
                write_frame(wr, frame, write_timeout, shutdown).await?;
            }
            loop {
                let idle = fetching.is_none();
                tokio::select! {
                    end = &mut *end_rx => {
                        return Err(end.unwrap_or(End::ClientLeft));
                    }
                    () = shutdown.cancelled() => return Err(End::Shutdown),
                    next = sub.live.recv() => {
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
                    Some(request) = requests.recv(), if idle => {
                        let hub = Arc::clone(hub);
                        let task = tokio::task::spawn_blocking(move || match request {
                            Request::Scan(id) => hub.fetch_scan(id),
                            Request::Tile(id) => hub.fetch_tile(id),
                        });
                        fetching = Some((request, task));
                    }
                    fetched = async {
                        match fetching.as_mut() {
                            Some((_, task)) => task.await,
                            None => std::future::pending().await,
                        }
                    }, if !idle => {
                        let Some((request, _)) = fetching.take() else {
                            continue;
                        };
                        let answer = match (fetched, request) {
                            (Ok(Ok(frame)), Request::Scan(id)) => {
                                hub.finish_fetch_for(id, frame, settings.version >= 4)
                            }
                            // A tile's data is complete in itself: a rebuild since is
                            // listed with a newer revision, which the client fetches.
                            (Ok(Ok(frame)), Request::Tile(_)) => {
                                hub.note_tile_sent(frame.len());
                                Ok(vec![frame])
                            }
                            (Ok(Err(e)), _) => Err(e),
                            (Err(e), request) => Err(FetchError::Failed {
                                what: describe(request),
                                message: format!("the read failed: {e}"),
                            }),
                        };
                        let written = answer_request(wr, request, answer, settings).await;
                        // Counted until answered, as the client counts it.
                        outstanding.fetch_sub(1, Ordering::AcqRel);
                        written?;
                        if sub.lagged.load(Ordering::Acquire) {
                            return Ok(());
                        }
                    }
                }
            }
        }
        .await;
        hub.unsubscribe(client_id);
        // `Ok` means the client's queue overflowed.
        if let Err(end) = result {
            return match end {
                End::Error(_) | End::Stalled(_) => reader_end(end_rx, end),
                end => end,
            };
        }
        resyncs += 1;
        if settings.slow_client == SlowClientPolicy::Disconnect || resyncs > settings.max_resyncs {
            return End::TooSlow(resyncs);
        }
        resynced();
    }
}

/// "scan 7" or "tile 2/-1/3", for messages.
fn describe(request: Request) -> String {
    match request {
        Request::Scan(id) => format!("scan {id}"),
        Request::Tile(id) => format!("tile {}", id.path()),
    }
}

/// Writes the answer to a request: the scan's or tile's frames, or why it is
/// unavailable.
async fn answer_request<W: AsyncWrite + Unpin + Send>(
    wr: &mut W,
    request: Request,
    answer: Result<Vec<Bytes>, FetchError>,
    settings: &StreamSettings<'_>,
) -> Result<(), End> {
    let (write_timeout, shutdown) = (settings.write_timeout, settings.shutdown);
    match answer {
        Ok(frames) => {
            for frame in &frames {
                write_frame(wr, frame, write_timeout, shutdown).await?;
            }
            Ok(())
        }
        Err(FetchError::Closed) => Err(End::Shutdown),
        Err(e) => {
            let reason: String = e.to_string().chars().take(MAX_REASON_LEN / 4).collect();
            let message = match request {
                Request::Scan(id) => Message::ScanUnavailable { id, reason },
                Request::Tile(id) => Message::TileUnavailable { id, reason },
            };
            let frame = message
                .encode()
                .map_err(|e| End::Error(format!("cannot encode an answer: {e}")))?;
            write_frame(wr, &frame, write_timeout, shutdown).await
        }
    }
}
