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

mod handshake;
mod pending;
mod stream;

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};

use bytes::BytesMut;
use texel::wire::Message;
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

/// One connection: the handshake in its pending place, then a viewer slot.
async fn connection(
    stream: TcpStream,
    peer: SocketAddr,
    ticket: pending::PendingTicket,
    shared: &Shared,
) {
    let (options, metrics) = (&shared.options, &shared.metrics);
    let (mut rd, mut wr) = stream.into_split();
    let mut inbuf = BytesMut::with_capacity(1024);
    let outcome = handshake::read_hello(
        &mut rd,
        &mut inbuf,
        options.handshake_timeout,
        &ticket.evicted,
        &shared.shutdown,
    )
    .await;
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
                serve_viewer(&mut rd, &mut wr, &mut inbuf, peer, &admitted, shared).await;
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
async fn serve_viewer(
    rd: &mut tokio::net::tcp::OwnedReadHalf,
    wr: &mut tokio::net::tcp::OwnedWriteHalf,
    inbuf: &mut BytesMut,
    peer: SocketAddr,
    admitted: &handshake::Admitted,
    shared: &Shared,
) {
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
                    tracing::info!(%peer, client = %client_name, "viewer connected");
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
