//! The viewer stream server (`docs/wire-protocol.md`): `run(listener, ...)` accepts
//! connections, gives each a pending place (bounded in total and per address,
//! `pending`) while it has the handshake timeout to deliver a valid hello
//! (`handshake`), and only then a viewer slot: unauthenticated connections never
//! hold a slot, so they cannot lock out those with the token. A viewer gets the model
//! so far as a snapshot of listings, then live updates from its bounded queue and
//! the scans it requests by id (`stream`); one that falls
//! behind or stops reading is resynchronised or dropped by policy (`stream`). Closing
//! the hub ends every viewer's stream with the rest of its queue and a goodbye saying
//! why; `shutdown` then stops accepting and waits a bounded time.
//!
//! The same port serves the browser viewer (`[serve] web`): a connection whose first
//! bytes are an HTTP method is an HTTP request (`http`): a file of the browser
//! viewer's page, or the WebSocket upgrade of `/ws`, whose binary messages carry the
//! same byte stream as a TCP connection (`websocket`), through the same handshake,
//! slots and stream as a native viewer.

mod handshake;
mod http;
mod pending;
mod stream;
mod web_files;
mod websocket;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};

use bytes::BytesMut;
use texel::wire::Message;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;

use crate::config::{ServeSection, SlowClientPolicy};
use crate::hub::Hub;
use crate::status::{Counter, Metrics, QueueProbe};
use handshake::HelloOutcome;
use pending::{Admission, PendingHandshakes, PendingLimits};
use stream::{End, StreamSettings};

pub use http::display_url;
pub use web_files::{BUILD_COMMAND as WEB_BUILD_COMMAND, default_web_dir, web_page_missing};

/// How the server treats clients.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// Required from every client when set.
    pub token: Option<String>,
    pub max_clients: usize,
    pub slow_client: SlowClientPolicy,
    pub max_resyncs: u32,
    pub handshake_timeout: Duration,
    pub max_pending_handshakes: usize,
    pub max_pending_handshakes_per_address: usize,
    /// The longest a write to a viewer may go without progress.
    pub write_timeout: Duration,
    pub server_name: String,
    pub session_name: String,
    /// How long the goodbye (or refusal) to each client may take.
    pub goodbye_timeout: Duration,
    /// Scan requests a viewer may have outstanding before it is disconnected.
    pub max_requests_in_flight: usize,
    /// Serve the browser viewer's page and the stream over WebSocket on this port.
    pub web: bool,
    /// Where the browser viewer's files are; `None` when no place could be found (the
    /// page then says it is not built).
    pub web_dir: Option<PathBuf>,
}

impl ServeOptions {
    pub fn from_config(serve: &ServeSection, session_name: &str) -> Self {
        Self {
            token: serve.token.clone(),
            max_clients: serve.max_clients,
            slow_client: serve.slow_client,
            max_resyncs: serve.max_resyncs,
            handshake_timeout: Duration::from_millis(serve.handshake_timeout_ms),
            max_pending_handshakes: serve.max_pending_handshakes,
            max_pending_handshakes_per_address: serve.max_pending_handshakes_per_address,
            write_timeout: Duration::from_millis(serve.write_timeout_ms),
            server_name: concat!("texeld ", env!("CARGO_PKG_VERSION")).to_string(),
            session_name: session_name.to_string(),
            goodbye_timeout: Duration::from_millis(500),
            max_requests_in_flight: serve.max_requests_in_flight,
            web: serve.web,
            web_dir: serve.web_dir.clone().or_else(default_web_dir),
        }
    }
}

/// What every connection task shares.
struct Shared {
    hub: Arc<Hub>,
    options: ServeOptions,
    metrics: Arc<Metrics>,
    slots: Arc<Semaphore>,
    /// Stops accepting and ends pending handshakes.
    shutdown: CancellationToken,
    /// Cancelled only if viewers do not finish in time after `shutdown`.
    hard_stop: CancellationToken,
    /// Places for HTTP responses being sent (a file can take a while), so the
    /// connections that read no viewer stream stay bounded too.
    http_slots: Arc<Semaphore>,
}

/// How a viewer's connection carries the stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Transport {
    Tcp,
    WebSocket,
}

impl Transport {
    fn name(self) -> &'static str {
        match self {
            Self::Tcp => "tcp",
            Self::WebSocket => "websocket",
        }
    }
}

/// Accepts viewers until `shutdown`; then waits (bounded by the goodbye timeout,
/// twice) for the connections to finish, which they do once the hub is closed.
pub async fn run(
    listener: TcpListener,
    hub: Arc<Hub>,
    options: ServeOptions,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
) {
    let pending = PendingHandshakes::new(PendingLimits {
        total: options.max_pending_handshakes,
        per_address: options.max_pending_handshakes_per_address,
    });
    let shared = Arc::new(Shared {
        slots: Arc::new(Semaphore::new(options.max_clients)),
        hub,
        options,
        metrics,
        shutdown,
        hard_stop: CancellationToken::new(),
        http_slots: Arc::new(Semaphore::new(http::MAX_RESPONSES)),
    });
    // The status shows the pending handshakes as a queue, until the server ends.
    let probe: Weak<PendingHandshakes> = Arc::downgrade(&pending);
    shared.metrics.add_queue(QueueProbe {
        name: "pending_handshakes",
        capacity: shared.options.max_pending_handshakes,
        depth: Box::new(move || probe.upgrade().map(|p| p.count())),
    });
    let mut tasks = JoinSet::new();
    loop {
        let accepted = tokio::select! {
            () = shared.shutdown.cancelled() => break,
            a = listener.accept() => a,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors and the like: wait rather than spin.
                tracing::warn!("accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        // Reap finished connection tasks so the set stays small.
        while tasks.try_join_next().is_some() {}
        let _ = stream.set_nodelay(true);
        let (ticket, admission) = pending.admit(peer.ip(), Instant::now());
        if let Admission::EvictedOldest(source) = admission {
            shared.metrics.add(Counter::HandshakesEvicted, 1);
            // Debug only: under a flood this is every connection; the counter shows it.
            tracing::debug!(%peer, "evicted the oldest pending handshake from {source:?}");
        }
        let shared = Arc::clone(&shared);
        tasks.spawn(async move { connection(stream, peer, ticket, &shared).await });
    }
    // Pending handshakes end with `shutdown`; viewers end by themselves once the hub is
    // closed (they send what is queued, then a goodbye); one too slow for that is cut
    // short.
    let timeout = shared.options.goodbye_timeout;
    let drained = tokio::time::timeout(timeout, async {
        while tasks.join_next().await.is_some() {}
    })
    .await;
    if drained.is_err() {
        shared.hard_stop.cancel();
        let cut = tokio::time::timeout(timeout, async {
            while tasks.join_next().await.is_some() {}
        })
        .await;
        if cut.is_err() {
            tasks.abort_all();
        }
    }
}

/// One connection: the handshake in its pending place, then a viewer slot. With the
/// browser viewer on, its first bytes tell an HTTP request (`http`) from a native hello.
async fn connection(
    mut stream: TcpStream,
    peer: SocketAddr,
    ticket: pending::PendingTicket,
    shared: &Shared,
) {
    let deadline = tokio::time::Instant::now() + shared.options.handshake_timeout;
    let mut inbuf = BytesMut::with_capacity(1024);
    let mut early = None;
    if shared.options.web {
        match sniff(&mut stream, &mut inbuf, deadline, &ticket.evicted, shared).await {
            Ok(true) => {
                http::serve(stream, peer, inbuf, ticket, deadline, shared).await;
                return;
            }
            Ok(false) => {}
            Err(outcome) => early = Some(outcome),
        }
    }
    let (rd, wr) = stream.into_split();
    viewer(
        rd,
        wr,
        inbuf,
        peer,
        ticket,
        early,
        deadline,
        Transport::Tcp,
        shared,
    )
    .await;
}

/// Reads until the first four bytes tell an HTTP request (`true`) from anything else,
/// a native hello above all (`false`), within the handshake's time; the bytes stay in
/// `buf` for whichever reads on. A connection that ends sooner goes the hello's way,
/// which says why it is refused.
async fn sniff(
    stream: &mut TcpStream,
    buf: &mut BytesMut,
    deadline: tokio::time::Instant,
    evicted: &CancellationToken,
    shared: &Shared,
) -> Result<bool, HelloOutcome> {
    let read = async {
        loop {
            if let Some(http) = http::may_be_request(buf) {
                return Ok(http);
            }
            match stream.read_buf(buf).await {
                Ok(0) => return Ok(false),
                Ok(_) => {}
                Err(e) => return Err(HelloOutcome::Invalid(format!("read failed: {e}"))),
            }
        }
    };
    tokio::select! {
        r = tokio::time::timeout_at(deadline, read) => r.unwrap_or(Err(HelloOutcome::TimedOut)),
        () = evicted.cancelled() => Err(HelloOutcome::Evicted),
        () = shared.shutdown.cancelled() => Err(HelloOutcome::Shutdown),
    }
}

/// A viewer's connection over any transport: its hello (unless `early` says how
/// waiting for it already ended) by `deadline` in its pending place, then a viewer
/// slot, or the refusal.
#[allow(clippy::too_many_arguments)] // one call per transport, each with all of these
async fn viewer<R, W>(
    mut rd: R,
    mut wr: W,
    mut inbuf: BytesMut,
    peer: SocketAddr,
    ticket: pending::PendingTicket,
    early: Option<HelloOutcome>,
    deadline: tokio::time::Instant,
    transport: Transport,
    shared: &Shared,
) where
    R: AsyncRead + Unpin + Send,
    W: AsyncWrite + Unpin + Send,
{
    let (options, metrics) = (&shared.options, &shared.metrics);
    let outcome = match early {
        Some(outcome) => outcome,
        None => {
            let left = deadline.saturating_duration_since(tokio::time::Instant::now());
            handshake::read_hello(&mut rd, &mut inbuf, left, &ticket.evicted, &shared.shutdown)
                .await
        }
    };
    // Hello or not, the connection no longer waits for one.
    drop(ticket);
    let refusal = match outcome {
        HelloOutcome::Hello(hello) => match handshake::admit(hello, options.token.as_deref()) {
            Ok(admitted) => {
                let Ok(slot) = Arc::clone(&shared.slots).try_acquire_owned() else {
                    metrics.add(Counter::ClientsRefused, 1);
                    tracing::warn!(%peer, "refused: {} viewers already connected", options.max_clients);
                    let reason = format!("server full: {} clients connected", options.max_clients);
                    handshake::refuse(&mut wr, &reason, options.goodbye_timeout).await;
                    return;
                };
                metrics.clients.fetch_add(1, Ordering::Relaxed);
                let conn = (peer, transport);
                serve_viewer(&mut rd, &mut wr, &mut inbuf, conn, &admitted, shared).await;
                metrics.clients.fetch_sub(1, Ordering::Relaxed);
                drop(slot);
                return;
            }
            Err(reason) => {
                metrics.add(Counter::ClientsRefused, 1);
                tracing::warn!(%peer, "refused: {reason}");
                reason
            }
        },
        HelloOutcome::Invalid(reason) => {
            metrics.add(Counter::ClientsRefused, 1);
            tracing::warn!(%peer, "refused: {reason}");
            reason
        }
        HelloOutcome::TimedOut => {
            metrics.add(Counter::HandshakeTimeouts, 1);
            let ms = options.handshake_timeout.as_millis();
            tracing::debug!(%peer, "closed: no hello within {ms} ms");
            format!("no hello within {ms} ms")
        }
        HelloOutcome::Evicted => "too many pending handshakes from your address; retry".into(),
        HelloOutcome::Shutdown => "the daemon is shutting down".into(),
    };
    handshake::refuse(&mut wr, &refusal, options.goodbye_timeout).await;
}

/// An admitted viewer holding a slot: welcome, stream, goodbye.
async fn serve_viewer<R, W>(
    rd: &mut R,
    wr: &mut W,
    inbuf: &mut BytesMut,
    (peer, transport): (SocketAddr, Transport),
    admitted: &handshake::Admitted,
    shared: &Shared,
) where
    R: AsyncRead + Unpin + Send,
    W: AsyncWrite + Unpin + Send,
{
    let transport = transport.name();
    let client_name = &admitted.client_name;
    let (options, metrics) = (&shared.options, &shared.metrics);
    let settings = StreamSettings {
        slow_client: options.slow_client,
        max_resyncs: options.max_resyncs,
        write_timeout: options.write_timeout,
        shutdown: &shared.hard_stop,
        max_requests_in_flight: options.max_requests_in_flight,
        tiles: admitted.version >= 3,
        version: admitted.version,
    };
    // The stream speaks the client's version (each one this server serves).
    let welcome = Message::ServerHello {
        version: admitted.version,
        server_name: options.server_name.clone(),
        session_name: options.session_name.clone(),
    };
    let end = match welcome.encode() {
        Ok(welcome) => {
            match stream::write_frame(wr, &welcome, settings.write_timeout, settings.shutdown).await
            {
                Ok(()) => {
                    tracing::info!(%peer, client = %client_name, transport, "viewer connected");
                    // Snapshot, then live updates; again after every resync.
                    stream::stream_model(rd, wr, inbuf, &shared.hub, &settings, || {
                        metrics.add(Counter::ClientsResynced, 1);
                    })
                    .await
                }
                Err(end) => end,
            }
        }
        Err(e) => End::Error(format!("cannot encode the welcome: {e}")),
    };
    match &end {
        End::ClientLeft => {
            tracing::info!(%peer, "viewer left");
            return;
        }
        End::Shutdown => {}
        End::TooSlow(_) => metrics.add(Counter::ClientsDropped, 1),
        End::Stalled(_) => {
            metrics.add(Counter::ClientsDropped, 1);
            metrics.add(Counter::ClientsWriteTimeouts, 1);
        }
        End::TooManyRequests(_) => metrics.add(Counter::ClientsDropped, 1),
        End::Error(_) => {}
    }
    let reason = match end {
        End::Shutdown => shared.hub.closed_reason().unwrap_or_else(|| end.reason()),
        _ => end.reason(),
    };
    // Bounded: a stalled viewer would not take the goodbye either.
    stream::goodbye(wr, &reason, options.goodbye_timeout).await;
    match end {
        End::Shutdown => tracing::info!(%peer, "viewer told: {reason}"),
        _ => tracing::warn!(%peer, "viewer dropped: {reason}"),
    }
}
