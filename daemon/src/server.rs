//! The viewer stream server (`docs/wire-protocol.md`): `run(listener, ...)` accepts
//! connections up to a limit, checks each client's hello (version, token compared in
//! constant time), sends the model so far as a snapshot, then live updates from its
//! bounded queue. A client that falls behind is resynchronised or disconnected by
//! policy. Closing the hub ends every client's stream with the rest of its queue and
//! a goodbye saying why; `shutdown` then stops accepting and waits a bounded time.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use bytes::{Bytes, BytesMut};
use subtle::ConstantTimeEq;
use texel::wire::{Limits, Message, PROTOCOL_VERSION, decode_frame};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;

use crate::config::{ServeSection, SlowClientPolicy};
use crate::hub::{Hub, HubError};
use crate::status::{Counter, Metrics};

/// How the server treats clients.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// Required from every client when set.
    pub token: Option<String>,
    pub max_clients: usize,
    pub slow_client: SlowClientPolicy,
    pub max_resyncs: u32,
    pub handshake_timeout: Duration,
    pub server_name: String,
    pub session_name: String,
    /// How long the goodbye to each client may take at shutdown.
    pub goodbye_timeout: Duration,
}

impl ServeOptions {
    pub fn from_config(serve: &ServeSection, session_name: &str) -> Self {
        Self {
            token: serve.token.clone(),
            max_clients: serve.max_clients,
            slow_client: serve.slow_client,
            max_resyncs: serve.max_resyncs,
            handshake_timeout: Duration::from_millis(serve.handshake_timeout_ms),
            server_name: concat!("texeld ", env!("CARGO_PKG_VERSION")).to_string(),
            session_name: session_name.to_string(),
            goodbye_timeout: Duration::from_millis(500),
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
    let options = Arc::new(options);
    // Cancelled only if clients do not finish in time after `shutdown`.
    let hard_stop = CancellationToken::new();
    let slots = Arc::new(Semaphore::new(options.max_clients));
    let mut tasks = JoinSet::new();
    loop {
        let accepted = tokio::select! {
            () = shutdown.cancelled() => break,
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
        match Arc::clone(&slots).try_acquire_owned() {
            Ok(permit) => {
                let (hub, options, metrics, stop) = (
                    Arc::clone(&hub),
                    Arc::clone(&options),
                    Arc::clone(&metrics),
                    hard_stop.clone(),
                );
                tasks.spawn(async move {
                    metrics.clients.fetch_add(1, Ordering::Relaxed);
                    serve_client(stream, peer, &hub, &options, &metrics, &stop).await;
                    metrics.clients.fetch_sub(1, Ordering::Relaxed);
                    drop(permit);
                });
            }
            Err(_) => {
                metrics.add(Counter::ClientsRefused, 1);
                tracing::warn!(%peer, "refused: {} clients already connected", options.max_clients);
                let reason = format!("server full: {} clients connected", options.max_clients);
                let timeout = options.goodbye_timeout;
                tasks.spawn(async move {
                    let mut stream = stream;
                    let _ = tokio::time::timeout(
                        timeout,
                        send_and_close(&mut stream, Message::Refused { reason }),
                    )
                    .await;
                });
            }
        }
    }
    // Connection tasks end by themselves once the hub is closed (they send what is
    // queued, then a goodbye); a client too slow for that is cut short.
    let drained = tokio::time::timeout(options.goodbye_timeout, async {
        while tasks.join_next().await.is_some() {}
    })
    .await;
    if drained.is_err() {
        hard_stop.cancel();
        let cut = tokio::time::timeout(options.goodbye_timeout, async {
            while tasks.join_next().await.is_some() {}
        })
        .await;
        if cut.is_err() {
            tasks.abort_all();
        }
    }
}

async fn send_and_close(stream: &mut TcpStream, message: Message) {
    if let Ok(bytes) = message.encode() {
        let _ = stream.write_all(&bytes).await;
    }
    let _ = stream.shutdown().await;
}

/// How a connection ended, for the log.
enum End {
    ClientLeft,
    Shutdown,
    Error(String),
}

/// Reads one client message (the hello), bounded by the client limits.
async fn read_message(rd: &mut OwnedReadHalf, buf: &mut BytesMut) -> Result<Message, String> {
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

async fn write_frame(
    wr: &mut OwnedWriteHalf,
    frame: &[u8],
    shutdown: &CancellationToken,
) -> Result<(), End> {
    tokio::select! {
        r = wr.write_all(frame) => r.map_err(|e| End::Error(format!("write failed: {e}"))),
        () = shutdown.cancelled() => Err(End::Shutdown),
    }
}

async fn goodbye(wr: &mut OwnedWriteHalf, reason: &str, timeout: Duration) {
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

/// Checks the hello: protocol version and token.
fn admit(hello: Message, options: &ServeOptions) -> Result<String, String> {
    let Message::ClientHello {
        version,
        token,
        client_name,
    } = hello
    else {
        return Err(format!("expected ClientHello, got {}", hello.kind_name()));
    };
    if version != PROTOCOL_VERSION {
        return Err(format!(
            "protocol version {version} is not supported; this server speaks {PROTOCOL_VERSION}"
        ));
    }
    if let Some(expected) = &options.token {
        // Constant time in the token's contents, so timing reveals nothing of it.
        let ok: bool = expected.as_bytes().ct_eq(token.as_bytes()).into();
        if !ok {
            return Err("wrong token".into());
        }
    }
    Ok(client_name)
}

async fn serve_client(
    stream: TcpStream,
    peer: SocketAddr,
    hub: &Hub,
    options: &ServeOptions,
    metrics: &Metrics,
    shutdown: &CancellationToken,
) {
    let (mut rd, mut wr) = stream.into_split();
    let mut inbuf = BytesMut::with_capacity(1024);
    // 1. Handshake, bounded in time and size.
    let hello =
        match tokio::time::timeout(options.handshake_timeout, read_message(&mut rd, &mut inbuf))
            .await
        {
            Ok(Ok(m)) => m,
            Ok(Err(e)) => {
                metrics.add(Counter::ClientsRefused, 1);
                tracing::warn!(%peer, "refused: {e}");
                refuse(&mut wr, &e, options).await;
                return;
            }
            Err(_) => {
                metrics.add(Counter::ClientsRefused, 1);
                tracing::warn!(%peer, "refused: no hello within {:?}", options.handshake_timeout);
                refuse(&mut wr, "no hello in time", options).await;
                return;
            }
        };
    let client_name = match admit(hello, options) {
        Ok(name) => name,
        Err(reason) => {
            metrics.add(Counter::ClientsRefused, 1);
            tracing::warn!(%peer, "refused: {reason}");
            refuse(&mut wr, &reason, options).await;
            return;
        }
    };
    let welcome = Message::ServerHello {
        version: PROTOCOL_VERSION,
        server_name: options.server_name.clone(),
        session_name: options.session_name.clone(),
    };
    let Ok(welcome) = welcome.encode() else {
        return;
    };
    if write_frame(&mut wr, &welcome, shutdown).await.is_err() {
        return;
    }
    tracing::info!(%peer, client = %client_name, "viewer connected");
    // 2. Snapshot, then live updates; again after every resync.
    let end = stream_model(
        &mut rd, &mut wr, &mut inbuf, hub, options, metrics, shutdown,
    )
    .await;
    match end {
        End::ClientLeft => tracing::info!(%peer, "viewer left"),
        End::Shutdown => {
            let reason = hub
                .closed_reason()
                .unwrap_or_else(|| "the daemon is shutting down".into());
            goodbye(&mut wr, &reason, options.goodbye_timeout).await;
            tracing::info!(%peer, "viewer told: {reason}");
        }
        End::Error(e) => {
            goodbye(&mut wr, &e, options.goodbye_timeout).await;
            tracing::warn!(%peer, "viewer dropped: {e}");
        }
    }
}

async fn refuse(wr: &mut OwnedWriteHalf, reason: &str, options: &ServeOptions) {
    let message = Message::Refused {
        reason: reason
            .chars()
            .take(texel::wire::MAX_REASON_LEN / 4)
            .collect(),
    };
    if let Ok(bytes) = message.encode() {
        let _ = tokio::time::timeout(options.goodbye_timeout, async {
            let _ = wr.write_all(&bytes).await;
            let _ = wr.shutdown().await;
        })
        .await;
    }
}

async fn stream_model(
    rd: &mut OwnedReadHalf,
    wr: &mut OwnedWriteHalf,
    inbuf: &mut BytesMut,
    hub: &Hub,
    options: &ServeOptions,
    metrics: &Metrics,
    shutdown: &CancellationToken,
) -> End {
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
                write_frame(wr, frame, shutdown).await?;
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
                        write_frame(wr, &frame, shutdown).await?;
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
        if options.slow_client == SlowClientPolicy::Disconnect || resyncs > options.max_resyncs {
            metrics.add(Counter::ClientsDropped, 1);
            return End::Error(format!(
                "too slow: fell behind {resyncs} time(s) in a row; disconnected"
            ));
        }
        metrics.add(Counter::ClientsResynced, 1);
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
