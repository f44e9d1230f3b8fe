//! The browser's link to the daemon: the wire protocol's byte stream carried in
//! WebSocket binary messages (`/ws` on the page's own host and port), turned into the
//! same [`ViewerEvent`]s the native connection thread sends, with the same handshake,
//! requests by id and reconnection with backoff. Nothing here blocks: the socket's
//! callbacks only queue bytes, and the frame loop pumps them.

use std::cell::RefCell;
use std::rc::Rc;
use std::sync::mpsc::{Receiver, SyncSender, TryRecvError};

use texel::wire::Message;
use texel_client::{ClientError, ExposureJoin, FrameReader, hello, welcome};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::{BinaryType, CloseEvent, MessageEvent, WebSocket};
use web_time::Duration;

use super::page::now_ms;
use super::wake::Wake;
use crate::live::connection::{Ended, forward, request_message};
use crate::live::{ConnectionState, SourceCommand, ViewerEvent, send};

const BACKOFF_MIN: Duration = Duration::from_millis(500);
const BACKOFF_MAX: Duration = Duration::from_secs(8);
/// Silence longer than this counts as a lost link (the daemon sends its status
/// about once a second).
const SILENCE_LIMIT: Duration = Duration::from_secs(10);

/// What the socket's callbacks hand over.
#[derive(Default)]
struct Inbox {
    chunks: Vec<Vec<u8>>,
    closed: Option<String>,
    /// When the socket opened and when its last bytes came (the page's clock, ms).
    opened_ms: Option<f64>,
    last_chunk_ms: f64,
}

/// One open socket with its callbacks (dropping them with the socket keeps the
/// browser from calling into freed closures).
struct Socket {
    ws: WebSocket,
    inbox: Rc<RefCell<Inbox>>,
    _on_open: Closure<dyn FnMut()>,
    _on_message: Closure<dyn FnMut(MessageEvent)>,
    _on_close: Closure<dyn FnMut(CloseEvent)>,
}

impl Drop for Socket {
    fn drop(&mut self) {
        self.ws.set_onopen(None);
        self.ws.set_onmessage(None);
        self.ws.set_onclose(None);
        let _ = self.ws.close();
    }
}

/// Why the link is waiting instead of connected.
enum Waiting {
    /// Until this time (ms on the page's clock).
    Retry { at_ms: f64 },
    /// The daemon refused the hello (a token is missing or wrong): no retry until
    /// the page supplies a token.
    Refused,
}

pub struct Link {
    url: String,
    token: String,
    socket: Option<Socket>,
    waiting: Option<Waiting>,
    frames: FrameReader,
    welcomed: bool,
    synced: bool,
    /// Model resets forwarded: the generation the window's requests are for.
    resets: u64,
    join: ExposureJoin,
    backoff: Duration,
    attempt: u32,
    last_heard_ms: f64,
    /// Bytes received, for the page's report.
    pub bytes_received: u64,
    /// Connections the daemon welcomed (a reconnection counts again).
    pub welcomes: u32,
    /// When the current socket opened, and when the bytes pumped last came (the
    /// page's clock, ms): the load's marks.
    pub opened_ms: Option<f64>,
    pub last_chunk_ms: f64,
    /// The socket's events wake the frame loop.
    wake: Wake,
}

impl Link {
    pub fn new(url: String, token: String, wake: Wake) -> Self {
        Self {
            url,
            token,
            socket: None,
            waiting: None,
            frames: FrameReader::default(),
            welcomed: false,
            synced: false,
            resets: 0,
            join: ExposureJoin::default(),
            backoff: BACKOFF_MIN,
            attempt: 0,
            last_heard_ms: 0.0,
            bytes_received: 0,
            welcomes: 0,
            opened_ms: None,
            last_chunk_ms: 0.0,
            wake,
        }
    }

    /// Whether the daemon welcomed the current socket (otherwise the link is
    /// connecting or waiting to retry, and the frame loop keeps running for it).
    pub fn connected(&self) -> bool {
        self.socket.is_some() && self.welcomed
    }

    /// Whether the daemon refused us (the page then asks for a token).
    pub fn refused(&self) -> bool {
        matches!(self.waiting, Some(Waiting::Refused))
    }

    /// A new token: try again now.
    pub fn set_token(&mut self, token: String) {
        self.token = token;
        self.waiting = None;
    }

    /// Opens the socket when it is time, forwards at most `max_messages` decoded
    /// messages as events and sends the window's requests. Returns how many messages
    /// were forwarded (the caller applies them, then pumps again while there are
    /// more).
    pub fn pump(
        &mut self,
        now_ms: f64,
        max_messages: usize,
        tx: &SyncSender<ViewerEvent>,
        commands: &Receiver<SourceCommand>,
    ) -> usize {
        if self.socket.is_none() {
            self.maybe_connect(now_ms, tx, commands);
            return 0;
        }
        let (chunks, closed) = match &self.socket {
            Some(s) => {
                let mut inbox = s.inbox.borrow_mut();
                self.opened_ms = inbox.opened_ms;
                if !inbox.chunks.is_empty() {
                    self.last_chunk_ms = inbox.last_chunk_ms;
                }
                (std::mem::take(&mut inbox.chunks), inbox.closed.take())
            }
            None => (Vec::new(), None),
        };
        if !chunks.is_empty() {
            self.last_heard_ms = now_ms;
        }
        for chunk in chunks {
            self.bytes_received += chunk.len() as u64;
            self.frames.buf.extend_from_slice(&chunk);
        }
        let mut forwarded = 0;
        while forwarded < max_messages {
            let message = match self.frames.take_message() {
                Ok(Some(m)) => m,
                Ok(None) => break,
                Err(e) => return self.lost(now_ms, format!("bad data from the daemon: {e}"), tx),
            };
            forwarded += 1;
            match self.handle(message, tx) {
                Ok(()) => {}
                Err(Ended::Lost(reason)) => return self.lost(now_ms, reason, tx),
                Err(Ended::Final(reason)) => {
                    self.refuse(reason, tx);
                    return forwarded;
                }
                Err(Ended::Stopped) => return forwarded,
            }
        }
        if let Some(reason) = closed
            && self.frames.buf.is_empty()
        {
            return self.lost(now_ms, reason, tx);
        }
        if self.welcomed && now_ms - self.last_heard_ms > SILENCE_LIMIT.as_secs_f64() * 1e3 {
            let reason = format!("nothing heard for {:.0} s", SILENCE_LIMIT.as_secs_f64());
            return self.lost(now_ms, reason, tx);
        }
        if self.synced {
            self.send_requests(commands);
        }
        forwarded
    }

    fn handle(&mut self, message: Message, tx: &SyncSender<ViewerEvent>) -> Result<(), Ended> {
        if !self.welcomed {
            return match welcome(message) {
                Ok(server) => {
                    self.welcomed = true;
                    self.welcomes = self.welcomes.saturating_add(1);
                    self.backoff = BACKOFF_MIN;
                    self.attempt = 0;
                    send(
                        tx,
                        ViewerEvent::Connection(ConnectionState::Connected {
                            addr: self.url.clone(),
                            server_name: server.server_name,
                            session_name: server.session_name,
                        }),
                    );
                    Ok(())
                }
                Err(ClientError::Refused(reason)) => {
                    Err(Ended::Final(format!("the daemon refused: {reason}")))
                }
                Err(e) => Err(Ended::Lost(e.to_string())),
            };
        }
        if matches!(message, Message::ModelReset { .. }) {
            self.resets += 1;
            self.synced = true;
        }
        match forward(message, tx, &mut self.join)? {
            true => Ok(()),
            false => Err(Ended::Stopped),
        }
    }

    fn send_requests(&mut self, commands: &Receiver<SourceCommand>) {
        let Some(socket) = &self.socket else {
            return;
        };
        loop {
            match commands.try_recv() {
                Ok(command) => {
                    if let Some(bytes) =
                        request_message(command, self.resets).and_then(|m| m.encode().ok())
                    {
                        // A failed send shows as the socket closing.
                        let _ = socket.ws.send_with_u8_array(&bytes);
                    }
                }
                Err(TryRecvError::Empty | TryRecvError::Disconnected) => return,
            }
        }
    }

    fn maybe_connect(
        &mut self,
        now_ms: f64,
        tx: &SyncSender<ViewerEvent>,
        commands: &Receiver<SourceCommand>,
    ) {
        match self.waiting {
            Some(Waiting::Refused) => return,
            Some(Waiting::Retry { at_ms }) if now_ms < at_ms => return,
            _ => {}
        }
        self.waiting = None;
        // Requests made for a lost connection concern its model; the new one starts
        // with a reset after which the window asks again.
        while commands.try_recv().is_ok() {}
        self.attempt = self.attempt.saturating_add(1);
        send(
            tx,
            ViewerEvent::Connection(ConnectionState::Connecting {
                addr: self.url.clone(),
                attempt: self.attempt,
            }),
        );
        self.frames = FrameReader::default();
        self.join = ExposureJoin::default();
        self.welcomed = false;
        self.synced = false;
        self.last_heard_ms = now_ms;
        self.opened_ms = None;
        match open(&self.url, &self.token, &self.wake) {
            Ok(socket) => self.socket = Some(socket),
            Err(reason) => {
                self.lost(now_ms, reason, tx);
            }
        }
    }

    fn lost(&mut self, now_ms: f64, reason: String, tx: &SyncSender<ViewerEvent>) -> usize {
        self.socket = None;
        let retry_in = self.backoff;
        self.backoff = (self.backoff * 2).min(BACKOFF_MAX);
        self.waiting = Some(Waiting::Retry {
            at_ms: now_ms + retry_in.as_secs_f64() * 1e3,
        });
        send(
            tx,
            ViewerEvent::Connection(ConnectionState::Retrying {
                addr: self.url.clone(),
                reason,
                retry_in,
            }),
        );
        0
    }

    fn refuse(&mut self, reason: String, tx: &SyncSender<ViewerEvent>) {
        self.socket = None;
        self.waiting = Some(Waiting::Refused);
        send(
            tx,
            ViewerEvent::Connection(ConnectionState::Ended { reason }),
        );
    }
}

/// Opens the socket; its first message is the hello with the token (never the URL:
/// URLs are logged and shared).
fn open(url: &str, token: &str, wake: &Wake) -> Result<Socket, String> {
    let hello = hello(token, "texel-web").map_err(|e| e.to_string())?;
    let ws = WebSocket::new(url).map_err(|e| format!("cannot open {url}: {e:?}"))?;
    ws.set_binary_type(BinaryType::Arraybuffer);
    let inbox = Rc::new(RefCell::new(Inbox::default()));
    let on_open = {
        let ws = ws.clone();
        let inbox = Rc::clone(&inbox);
        let wake = wake.clone();
        Closure::<dyn FnMut()>::new(move || {
            let _ = ws.send_with_u8_array(&hello);
            inbox.borrow_mut().opened_ms = Some(now_ms());
            wake.wake();
        })
    };
    let on_message = {
        let inbox = Rc::clone(&inbox);
        let wake = wake.clone();
        Closure::<dyn FnMut(MessageEvent)>::new(move |event: MessageEvent| {
            if let Ok(buffer) = event.data().dyn_into::<js_sys::ArrayBuffer>() {
                let mut inbox = inbox.borrow_mut();
                inbox.chunks.push(js_sys::Uint8Array::new(&buffer).to_vec());
                inbox.last_chunk_ms = now_ms();
            }
            wake.wake();
        })
    };
    let on_close = {
        let inbox = Rc::clone(&inbox);
        let wake = wake.clone();
        Closure::<dyn FnMut(CloseEvent)>::new(move |event: CloseEvent| {
            wake.wake();
            let reason = match event.reason() {
                r if r.is_empty() => format!("the connection closed (code {})", event.code()),
                r => format!("the connection closed: {r}"),
            };
            inbox.borrow_mut().closed = Some(reason);
        })
    };
    ws.set_onopen(Some(on_open.as_ref().unchecked_ref()));
    ws.set_onmessage(Some(on_message.as_ref().unchecked_ref()));
    ws.set_onclose(Some(on_close.as_ref().unchecked_ref()));
    Ok(Socket {
        ws,
        inbox,
        _on_open: on_open,
        _on_message: on_message,
        _on_close: on_close,
    })
}
