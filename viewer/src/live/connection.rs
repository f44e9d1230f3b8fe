//! A live connection to a daemon on a thread of its own: connect and handshake
//! ([`transport::Link`](super::transport::Link)), decode every message and pass what
//! it asks of the model on as a [`ViewerEvent`] (the consumer holds the only model),
//! and send the requests for scans the consumer makes on its bounded command
//! channel. When the connection is lost, say so and reconnect with exponential
//! backoff. Requests carry the number of resets their asker had seen: the thread sends
//! nothing on a connection before forwarding its first reset and drops requests made
//! before the latest reset (they name scans of a model that is gone; the consumer
//! asks again). A refusal (wrong token,
//! wrong version) ends the thread: retrying cannot fix it.

use std::net::{SocketAddr, ToSocketAddrs};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TryRecvError};
// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::{Duration, Instant};

use texel::wire::Message;
use texel_client::{ClientError, ExposureJoin, Update, update};

use super::transport::Link;
use super::{ConnectionState, SourceCommand, ViewerEvent, send};

/// Between reads the thread sends what the consumer asked for: a read waits at most
/// this long, so a request waits at most this long for the wire.
const POLL: Duration = Duration::from_millis(20);

/// How the connection thread behaves.
#[derive(Debug, Clone)]
pub struct ConnectOptions {
    /// `HOST:PORT`.
    pub addr: String,
    /// Empty when the daemon needs none.
    pub token: String,
    pub client_name: String,
    /// Bounds a connection attempt and every read; a read that times out only
    /// checks for a stop request, so this also sets how quickly the thread stops.
    pub io_timeout: Duration,
    /// A connection that delivers nothing for this long is taken as lost (the daemon
    /// sends a status every second by default).
    pub silence_limit: Duration,
    pub backoff_min: Duration,
    pub backoff_max: Duration,
    /// Reconnect after the daemon ends the stream (false: end the thread).
    pub reconnect: bool,
}

impl ConnectOptions {
    pub fn new(addr: impl Into<String>, token: impl Into<String>) -> Self {
        Self {
            addr: addr.into(),
            token: token.into(),
            client_name: format!("texel-viewer {}", env!("CARGO_PKG_VERSION")),
            io_timeout: Duration::from_millis(500),
            silence_limit: Duration::from_secs(10),
            backoff_min: Duration::from_millis(200),
            backoff_max: Duration::from_secs(5),
            reconnect: true,
        }
    }
}

/// Stops the connection thread when dropped or asked to.
pub struct ConnectionHandle {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ConnectionHandle {
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for ConnectionHandle {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
    }
}

/// Starts the connection thread; events go to `tx`, requests come from `commands`.
pub fn spawn(
    options: ConnectOptions,
    tx: SyncSender<ViewerEvent>,
    commands: Receiver<SourceCommand>,
) -> ConnectionHandle {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&stop);
    let thread = std::thread::Builder::new()
        .name("texel-viewer-net".into())
        .spawn(move || run(&options, &tx, &commands, &flag))
        .ok();
    ConnectionHandle { stop, thread }
}

/// Why one connection ended.
pub(crate) enum Ended {
    /// Try again (after backoff).
    Lost(String),
    /// Do not try again.
    Final(String),
    /// The consumer is gone or a stop was requested.
    Stopped,
}

fn run(
    options: &ConnectOptions,
    tx: &SyncSender<ViewerEvent>,
    commands: &Receiver<SourceCommand>,
    stop: &AtomicBool,
) {
    let mut backoff = options.backoff_min;
    let mut attempt = 0u32;
    // Resets forwarded: the generation of the consumer's model.
    let mut resets = 0u64;
    while !stop.load(Ordering::Acquire) {
        attempt = attempt.saturating_add(1);
        if !send(
            tx,
            ViewerEvent::Connection(ConnectionState::Connecting {
                addr: options.addr.clone(),
                attempt,
            }),
        ) {
            return;
        }
        // Requests made for a connection that was lost concern its model; the new
        // one starts with a reset after which the consumer asks again.
        while commands.try_recv().is_ok() {}
        let (reason, connected) = match connect_once(options, tx, commands, &mut resets, stop) {
            (Ended::Stopped, _) => return,
            (Ended::Final(reason), _) => {
                let _ = send(
                    tx,
                    ViewerEvent::Connection(ConnectionState::Ended { reason }),
                );
                return;
            }
            (Ended::Lost(reason), connected) => (reason, connected),
        };
        if connected {
            // A connection that worked resets the backoff.
            backoff = options.backoff_min;
            attempt = 0;
            if !options.reconnect {
                let _ = send(
                    tx,
                    ViewerEvent::Connection(ConnectionState::Ended { reason }),
                );
                return;
            }
        }
        if !send(
            tx,
            ViewerEvent::Connection(ConnectionState::Retrying {
                addr: options.addr.clone(),
                reason,
                retry_in: backoff,
            }),
        ) {
            return;
        }
        let until = Instant::now() + backoff;
        while Instant::now() < until {
            if stop.load(Ordering::Acquire) {
                return;
            }
            std::thread::sleep(Duration::from_millis(20).min(backoff));
        }
        backoff = (backoff * 2).min(options.backoff_max);
    }
}

/// Resolves `HOST:PORT` (the first address).
pub fn resolve(addr: &str) -> Result<SocketAddr, String> {
    addr.to_socket_addrs()
        .map_err(|e| format!("cannot resolve {addr}: {e}"))?
        .next()
        .ok_or_else(|| format!("{addr} resolves to no address"))
}

/// One connection, until it ends; the flag says whether the handshake succeeded.
fn connect_once(
    options: &ConnectOptions,
    tx: &SyncSender<ViewerEvent>,
    commands: &Receiver<SourceCommand>,
    resets: &mut u64,
    stop: &AtomicBool,
) -> (Ended, bool) {
    let addr = match resolve(&options.addr) {
        Ok(a) => a,
        Err(e) => return (Ended::Lost(e), false),
    };
    // Per connection: an exposure belongs to the scan that follows it on this stream.
    let mut join = ExposureJoin::default();
    let exposures = &mut join;
    let mut client = match Link::connect(
        addr,
        &options.token,
        &options.client_name,
        options.io_timeout.max(Duration::from_millis(50)),
    ) {
        Ok(c) => c,
        Err(ClientError::Refused(reason)) => {
            return (Ended::Final(format!("the daemon refused: {reason}")), false);
        }
        Err(e) => return (Ended::Lost(e.to_string()), false),
    };
    if !send(
        tx,
        ViewerEvent::Connection(ConnectionState::Connected {
            addr: options.addr.clone(),
            server_name: client.server.server_name.clone(),
            session_name: client.server.session_name.clone(),
        }),
    ) {
        return (Ended::Stopped, true);
    }
    if let Err(e) = client.set_read_timeout(POLL.min(options.io_timeout)) {
        return (Ended::Lost(e.to_string()), true);
    }
    let mut last_heard = Instant::now();
    // Nothing is sent before this connection's snapshot has begun.
    let mut synced = false;
    loop {
        if stop.load(Ordering::Acquire) {
            return (Ended::Stopped, true);
        }
        if synced && let Err(ended) = send_requests(&mut client, commands, *resets) {
            return (ended, true);
        }
        let message = match client.next_message() {
            Ok(Some(m)) => m,
            Ok(None) => return (Ended::Lost("the daemon closed the connection".into()), true),
            Err(ClientError::Timeout(_)) => {
                if last_heard.elapsed() > options.silence_limit {
                    return (
                        Ended::Lost(format!(
                            "nothing heard for {:.0} s",
                            options.silence_limit.as_secs_f64()
                        )),
                        true,
                    );
                }
                continue;
            }
            Err(e) => return (Ended::Lost(e.to_string()), true),
        };
        last_heard = Instant::now();
        if matches!(message, Message::ModelReset { .. }) {
            *resets += 1;
            synced = true;
        }
        match forward(message, tx, exposures) {
            Ok(true) => {}
            Ok(false) => return (Ended::Stopped, true),
            Err(ended) => return (ended, true),
        }
    }
}

/// Sends every request waiting on the command channel that was made for the
/// model of generation `resets`; drops older ones.
fn send_requests(
    link: &mut Link,
    commands: &Receiver<SourceCommand>,
    resets: u64,
) -> Result<(), Ended> {
    loop {
        match commands.try_recv() {
            Ok(command) => {
                if let Some(message) = request_message(command, resets) {
                    link.send(&message)
                        .map_err(|e| Ended::Lost(format!("sending a request: {e}")))?;
                }
            }
            Err(TryRecvError::Empty) => return Ok(()),
            // The consumer is gone; the event channel says so at the next send.
            Err(TryRecvError::Disconnected) => return Ok(()),
        }
    }
}

/// The wire message of a command, `None` when it is stale.
pub(crate) fn request_message(command: SourceCommand, resets: u64) -> Option<Message> {
    match command {
        SourceCommand::RequestScan { id, generation } => {
            (generation == resets).then_some(Message::RequestScan { id })
        }
    }
}

/// Decodes one message and forwards what it asks of the model (the window's model
/// is the only copy: this thread keeps none). `Ok(false)`: the consumer is gone.
pub(crate) fn forward(
    message: Message,
    tx: &SyncSender<ViewerEvent>,
    exposures: &mut ExposureJoin,
) -> Result<bool, Ended> {
    let received = Instant::now();
    let update =
        update(message).map_err(|e| Ended::Lost(format!("bad message from the daemon: {e}")))?;
    let event = match update {
        Update::Reset { .. } => ViewerEvent::Reset,
        Update::SnapshotComplete { scan_count } => {
            ViewerEvent::SnapshotComplete { scans: scan_count }
        }
        Update::Model(mut event) => {
            exposures.attach(&mut event);
            ViewerEvent::Model { event, received }
        }
        Update::Exposure { id, exposure } => {
            exposures.hold(id, exposure);
            return Ok(true);
        }
        Update::Response(response) => ViewerEvent::EoResponse(response),
        Update::Status(status) => ViewerEvent::Status { status, received },
        Update::Goodbye(reason) => {
            return Err(Ended::Lost(format!(
                "the daemon ended the stream: {reason}"
            )));
        }
        // The consumer asked for it: it stops asking until the scan is listed again.
        Update::Unavailable { id, reason } => ViewerEvent::ScanUnavailable { id, reason },
        Update::Ignored => return Ok(true),
        // The window does not draw the level-of-detail tree yet (`crate::tiles` does,
        // headless): its events are not forwarded.
        Update::Tile(_) => return Ok(true),
    };
    Ok(send(tx, event))
}
