//! The browser viewer's side of the viewer port: one HTTP/1.1 request per connection,
//! its head read bounded in size and within the handshake's time, answered with a
//! file of the browser viewer's directory, the WebSocket upgrade of `/ws` (the viewer
//! stream then runs over `websocket`), or an error status; then the connection closes.
//!
//! Nothing here trusts the request: the head is at most `MAX_HEAD` bytes in at most
//! `MAX_HEADERS` headers, parsed by a parser that tells "incomplete" from "invalid";
//! files are looked up by `web_files` and sent in chunks with the viewers' write
//! timeout, at most `MAX_RESPONSES` at once.

use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

use bytes::BytesMut;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::handshake::derive_accept_key;
use tokio_util::sync::CancellationToken;

use super::pending::PendingTicket;
use super::stream::write_frame;
use super::web_files::{self, BUILD_COMMAND, Lookup, not_built_page};
use super::{Shared, websocket};

/// The longest request head: a browser's is well under 2 KiB, cookies included.
const MAX_HEAD: usize = 16 * 1024;
/// The most headers in a request head.
const MAX_HEADERS: usize = 64;
/// A file is read and sent this much at a time.
const CHUNK: usize = 64 * 1024;
/// HTTP responses being sent at once (each holds an open file and a chunk).
pub const MAX_RESPONSES: usize = 32;
/// How long, and how much, unread input is drained before closing: closing a socket
/// with unread input resets the connection, and the client may lose the answer.
const LINGER: Duration = Duration::from_millis(500);
const LINGER_BYTES: usize = 256 * 1024;

/// The first four bytes of the request methods: `GET` and `HEAD` are served, the
/// others told so. No native hello starts with these: they would be its frame length,
/// hundreds of MiB.
const METHODS: [&[u8; 4]; 9] = [
    b"GET ", b"HEAD", b"POST", b"PUT ", b"DELE", b"OPTI", b"PATC", b"CONN", b"TRAC",
];

/// Whether a connection's first bytes are an HTTP request: `None` while too few
/// have arrived to tell.
pub fn may_be_request(first: &[u8]) -> Option<bool> {
    let seen = first.get(..first.len().min(4)).unwrap_or_default();
    if !METHODS.iter().any(|m| m.starts_with(seen)) {
        Some(false)
    } else if seen.len() == 4 {
        Some(true)
    } else {
        None
    }
}

/// The page's address for the log: the bound address (its real port when bound to
/// port 0), and "every interface" for an unspecified address.
pub fn display_url(addr: SocketAddr) -> String {
    if addr.ip().is_unspecified() {
        format!("http://{addr}/ (every interface)")
    } else {
        format!("http://{addr}/")
    }
}

/// What an HTTP connection is answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Refusal {
    status: u16,
    why: &'static str,
    /// Header lines to add, each ending in CRLF.
    extra: &'static str,
}

const fn refusal(status: u16, why: &'static str) -> Refusal {
    Refusal {
        status,
        why,
        extra: "",
    }
}

const TOO_LARGE: Refusal = refusal(431, "the request head is too large");
const MALFORMED: Refusal = refusal(400, "malformed request");

/// What the head says, as far as this server cares.
#[derive(Debug, Default)]
struct Request {
    method: String,
    /// The target's path, without its query or fragment.
    path: String,
    http11: bool,
    upgrade_websocket: bool,
    connection_upgrade: bool,
    ws_version: Option<String>,
    ws_key: Option<String>,
    host: Option<String>,
    origin: Option<String>,
    /// The entity tags of the copy the browser holds.
    if_none_match: Option<String>,
}

/// `Ok(None)`: incomplete, read more; else the request and the head's length.
fn parse(buf: &[u8]) -> Result<Option<(Request, usize)>, Refusal> {
    let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
    let mut head = httparse::Request::new(&mut headers);
    let used = match head.parse(buf) {
        Ok(httparse::Status::Complete(used)) => used,
        Ok(httparse::Status::Partial) => return Ok(None),
        Err(httparse::Error::TooManyHeaders) => return Err(TOO_LARGE),
        Err(_) => return Err(MALFORMED),
    };
    let (Some(method), Some(target), Some(version)) = (head.method, head.path, head.version) else {
        return Err(MALFORMED);
    };
    // Origin form only: no absolute URLs (this is no proxy) and no `*`.
    if !target.starts_with('/') {
        return Err(refusal(400, "the request target must be a path"));
    }
    let path = target.split(['?', '#']).next().unwrap_or_default();
    let mut request = Request {
        method: method.to_string(),
        path: path.to_string(),
        http11: version == 1,
        ..Request::default()
    };
    for header in head.headers.iter() {
        let Ok(value) = std::str::from_utf8(header.value) else {
            continue;
        };
        let value = value.trim();
        let has_token = |token: &str| {
            value
                .split(',')
                .any(|t| t.trim().eq_ignore_ascii_case(token))
        };
        let name = header.name;
        if name.eq_ignore_ascii_case("upgrade") {
            request.upgrade_websocket |= has_token("websocket");
        } else if name.eq_ignore_ascii_case("connection") {
            request.connection_upgrade |= has_token("upgrade");
        } else if name.eq_ignore_ascii_case("sec-websocket-version") {
            request.ws_version = Some(value.to_string());
        } else if name.eq_ignore_ascii_case("sec-websocket-key") {
            request.ws_key = Some(value.to_string());
        } else if name.eq_ignore_ascii_case("host") {
            request.host = Some(value.to_string());
        } else if name.eq_ignore_ascii_case("origin") {
            request.origin = Some(value.to_string());
        } else if name.eq_ignore_ascii_case("if-none-match") {
            request.if_none_match = Some(value.to_string());
        }
    }
    Ok(Some((request, used)))
}

/// How reading the head ended.
enum Head {
    Request(Request, usize),
    Refused(Refusal),
    /// Closed, failed, evicted or shut down: nobody to answer.
    Gone,
}

/// Reads the request head into `buf` (which may hold its start), never past
/// `MAX_HEAD`, by `deadline`.
async fn read_head(
    stream: &mut TcpStream,
    buf: &mut BytesMut,
    deadline: tokio::time::Instant,
    evicted: &CancellationToken,
    shutdown: &CancellationToken,
) -> Head {
    let read = async {
        loop {
            match parse(buf) {
                Ok(Some((request, used))) => return Head::Request(request, used),
                Ok(None) => {}
                Err(refusal) => return Head::Refused(refusal),
            }
            let room = MAX_HEAD.saturating_sub(buf.len());
            if room == 0 {
                return Head::Refused(TOO_LARGE);
            }
            buf.reserve(room.min(4096));
            match (&mut *stream).take(room as u64).read_buf(buf).await {
                Ok(0) | Err(_) => return Head::Gone,
                Ok(_) => {}
            }
        }
    };
    tokio::select! {
        r = tokio::time::timeout_at(deadline, read) => {
            r.unwrap_or(Head::Refused(refusal(408, "no request head in time")))
        }
        () = evicted.cancelled() => Head::Gone,
        () = shutdown.cancelled() => Head::Gone,
    }
}

/// Answers one HTTP request, its first bytes in `buf`. The connection keeps its
/// pending place while its head is read, and a WebSocket until its hello.
pub async fn serve(
    mut stream: TcpStream,
    peer: SocketAddr,
    mut buf: BytesMut,
    ticket: PendingTicket,
    deadline: tokio::time::Instant,
    shared: &Shared,
) {
    let head = read_head(
        &mut stream,
        &mut buf,
        deadline,
        &ticket.evicted,
        &shared.shutdown,
    )
    .await;
    let (request, used) = match head {
        Head::Request(request, used) => (request, used),
        Head::Refused(refusal) => {
            drop(ticket);
            tracing::debug!(%peer, status = refusal.status, "http: {}", refusal.why);
            refuse(stream, refusal, false, shared).await;
            return;
        }
        Head::Gone => return,
    };
    let head_only = request.method == "HEAD";
    if request.method == "GET" && request.path == "/ws" {
        match accept_key(&request, shared.options.token.is_some()) {
            Ok(accept) => {
                let answer = format!(
                    "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n\
                     Connection: Upgrade\r\nSec-WebSocket-Accept: {accept}\r\n\r\n"
                );
                let (timeout, stop) = (shared.options.write_timeout, &shared.hard_stop);
                if write_frame(&mut stream, answer.as_bytes(), timeout, stop)
                    .await
                    .is_ok()
                {
                    // Whatever followed the head is the first WebSocket bytes.
                    let early = buf.get(used..).unwrap_or_default().to_vec();
                    websocket::serve(stream, early, peer, ticket, shared).await;
                }
            }
            Err(refusal) => {
                drop(ticket);
                tracing::debug!(%peer, status = refusal.status, "http /ws: {}", refusal.why);
                refuse(stream, refusal, false, shared).await;
            }
        }
        return;
    }
    drop(ticket);
    if request.method != "GET" && !head_only {
        let refusal = Refusal {
            status: 405,
            why: "only GET and HEAD are served here",
            extra: "Allow: GET, HEAD\r\n",
        };
        refuse(stream, refusal, false, shared).await;
        return;
    }
    // Files take a while to send: their number is bounded like everything else.
    let Ok(_permit) = shared.http_slots.try_acquire() else {
        let busy = refusal(503, "too many requests at once; retry");
        refuse(stream, busy, head_only, shared).await;
        return;
    };
    let dir = shared.options.web_dir.as_deref();
    match web_files::lookup(dir, &request.path).await {
        Lookup::Found(file, len, content_type, tag) => {
            let extra = format!("ETag: {tag}\r\n");
            if request
                .if_none_match
                .as_deref()
                .is_some_and(|held| web_files::matches_tag(held, &tag))
            {
                // The browser's copy is current: it reuses it (and the wasm it
                // compiled from it).
                tracing::debug!(%peer, path = %request.path, "http: 304");
                let head = response_head(304, content_type, len, &extra);
                send(&mut stream, &head, &[], true, shared).await;
            } else {
                tracing::debug!(%peer, path = %request.path, len, "http: 200");
                let head = response_head(200, content_type, len, &extra);
                send_file(&mut stream, &head, file, len, head_only, shared).await;
            }
            linger_close(stream).await;
        }
        Lookup::NotBuilt => {
            tracing::warn!(
                %peer,
                "the browser viewer was asked for but is not built (no index.html in {}); \
                 build it with `{BUILD_COMMAND}`",
                dir.map_or_else(|| "the web directory".into(), |d| d.display().to_string())
            );
            let body = not_built_page();
            let head = response_head(503, "text/html; charset=utf-8", body.len() as u64, "");
            send(&mut stream, &head, body.as_bytes(), head_only, shared).await;
            linger_close(stream).await;
        }
        Lookup::TooLarge => {
            let too_large = refusal(403, "the file is too large to serve");
            refuse(stream, too_large, head_only, shared).await;
        }
        Lookup::Missing => {
            tracing::debug!(%peer, path = %request.path, "http: 404");
            refuse(stream, refusal(404, "not found"), head_only, shared).await;
        }
    }
}

/// The `Sec-WebSocket-Accept` for a valid upgrade request, or why it is refused.
fn accept_key(request: &Request, token_required: bool) -> Result<String, Refusal> {
    if !request.upgrade_websocket {
        return Err(Refusal {
            status: 426,
            why: "/ws is the viewer stream over WebSocket: connect with a WebSocket client",
            extra: "Upgrade: websocket\r\n",
        });
    }
    if !request.http11 || !request.connection_upgrade {
        return Err(refusal(
            400,
            "a WebSocket upgrade needs HTTP/1.1 and Connection: upgrade",
        ));
    }
    if request.ws_version.as_deref() != Some("13") {
        return Err(Refusal {
            status: 426,
            why: "only WebSocket version 13 is spoken",
            extra: "Sec-WebSocket-Version: 13\r\n",
        });
    }
    let Some(key) = request
        .ws_key
        .as_deref()
        .filter(|k| (1..=64).contains(&k.len()))
    else {
        return Err(refusal(400, "no Sec-WebSocket-Key"));
    };
    if !origin_allowed(request, token_required) {
        return Err(refusal(
            403,
            "this daemon's stream is open to its own page only",
        ));
    }
    Ok(derive_accept_key(key.as_bytes()))
}

/// Whether a browser page may open the stream. With a token, any page may try: the
/// token in the hello decides. Without one (a daemon on loopback), only this daemon's
/// own page, addressed by a loopback name: a site open in the same browser could
/// otherwise read the model, even through a name of its own pointed at 127.0.0.1.
/// Programs that send no `Origin` are not browsers and are let through.
fn origin_allowed(request: &Request, token_required: bool) -> bool {
    let Some(origin) = request.origin.as_deref() else {
        return true;
    };
    if token_required {
        return true;
    }
    let Some(host) = request.host.as_deref() else {
        return false;
    };
    let name = match host.strip_prefix('[') {
        Some(v6) => v6.split(']').next().unwrap_or_default(),
        None => host.rsplit_once(':').map_or(host, |(name, _)| name),
    };
    let local = name.eq_ignore_ascii_case("localhost")
        || name.parse::<IpAddr>().is_ok_and(|ip| ip.is_loopback());
    let same = origin
        .strip_prefix("http://")
        .is_some_and(|o| o.eq_ignore_ascii_case(host));
    local && same
}

fn reason_phrase(status: u16) -> &'static str {
    match status {
        200 => "OK",
        304 => "Not Modified",
        400 => "Bad Request",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        426 => "Upgrade Required",
        431 => "Request Header Fields Too Large",
        503 => "Service Unavailable",
        _ => "Error",
    }
}

/// A response head. `no-cache`: the browser asks again each time (with the file's
/// entity tag), so a rebuilt viewer is picked up at once and an unchanged one is not
/// sent again.
fn response_head(status: u16, content_type: &str, len: u64, extra: &str) -> String {
    format!(
        "HTTP/1.1 {status} {}\r\nContent-Type: {content_type}\r\nContent-Length: {len}\r\n\
         Cache-Control: no-cache\r\nX-Content-Type-Options: nosniff\r\nConnection: close\r\n\
         {extra}\r\n",
        reason_phrase(status)
    )
}

/// Answers an error status with its reason as a short text, and closes.
async fn refuse(mut stream: TcpStream, refusal: Refusal, head_only: bool, shared: &Shared) {
    let body = format!(
        "{} {}: {}\n",
        refusal.status,
        reason_phrase(refusal.status),
        refusal.why
    );
    let head = response_head(
        refusal.status,
        "text/plain; charset=utf-8",
        body.len() as u64,
        refusal.extra,
    );
    send(&mut stream, &head, body.as_bytes(), head_only, shared).await;
    linger_close(stream).await;
}

/// Writes a head and a body, each write bounded by the viewers' write timeout.
async fn send(stream: &mut TcpStream, head: &str, body: &[u8], head_only: bool, shared: &Shared) {
    let (timeout, stop) = (shared.options.write_timeout, &shared.hard_stop);
    if write_frame(stream, head.as_bytes(), timeout, stop)
        .await
        .is_ok()
        && !head_only
    {
        let _ = write_frame(stream, body, timeout, stop).await;
    }
}

/// Writes a head and `len` bytes of `file`, a chunk at a time.
async fn send_file(
    stream: &mut TcpStream,
    head: &str,
    file: tokio::fs::File,
    len: u64,
    head_only: bool,
    shared: &Shared,
) {
    let (timeout, stop) = (shared.options.write_timeout, &shared.hard_stop);
    if write_frame(stream, head.as_bytes(), timeout, stop)
        .await
        .is_err()
        || head_only
    {
        return;
    }
    // Never more than the length announced, even if the file grew since.
    let mut file = file.take(len);
    let mut chunk = vec![0u8; CHUNK];
    loop {
        let n = match file.read(&mut chunk).await {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        let Some(bytes) = chunk.get(..n) else { return };
        if write_frame(stream, bytes, timeout, stop).await.is_err() {
            return;
        }
    }
}

/// Closes after the answer: shuts the sending side, then drains what the client may
/// still send (bounded in time and bytes) so the close does not reset the connection
/// before the client has read the answer.
async fn linger_close(mut stream: TcpStream) {
    let _ = stream.shutdown().await;
    let _ = tokio::time::timeout(LINGER, async {
        let mut sink = [0u8; 4096];
        let mut drained = 0;
        while drained < LINGER_BYTES {
            match stream.read(&mut sink).await {
                Ok(0) | Err(_) => break,
                Ok(n) => drained += n,
            }
        }
    })
    .await;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_bytes_tell_http_from_a_hello() {
        assert_eq!(may_be_request(b""), None);
        assert_eq!(may_be_request(b"GE"), None);
        assert_eq!(may_be_request(b"GET /"), Some(true));
        assert_eq!(may_be_request(b"HEAD"), Some(true));
        assert_eq!(may_be_request(b"GETX"), Some(false));
        let hello = texel::wire::Message::ClientHello {
            version: texel::wire::PROTOCOL_VERSION,
            token: String::new(),
            client_name: "v".into(),
        }
        .encode()
        .unwrap_or_default();
        assert_eq!(may_be_request(&hello), Some(false));
    }

    #[test]
    fn heads_are_incomplete_invalid_or_parsed() {
        assert!(matches!(parse(b"GET / HTTP/1.1\r\nHost: a"), Ok(None)));
        assert!(parse(b"GET / HTTP/1.1\r\n\x01\r\n\r\n").is_err());
        assert!(parse(b"GET http://a/ HTTP/1.1\r\n\r\n").is_err());
        let whole = b"GET /?mode=blended HTTP/1.1\r\nHost: a\r\n\r\nxy";
        let Ok(Some((r, used))) = parse(whole) else {
            panic!("a whole head");
        };
        // The bytes after the head are not the head's.
        assert_eq!((r.path.as_str(), used), ("/", whole.len() - 2));
        let many = format!(
            "GET / HTTP/1.1\r\n{}\r\n",
            "A: b\r\n".repeat(MAX_HEADERS + 1)
        );
        assert_eq!(parse(many.as_bytes()).err(), Some(TOO_LARGE));
    }

    #[test]
    fn without_a_token_only_the_daemons_own_page_opens_the_stream() {
        let request = |host: &str, origin: Option<&str>| Request {
            host: Some(host.into()),
            origin: origin.map(Into::into),
            ..Request::default()
        };
        let own = request("127.0.0.1:7878", Some("http://127.0.0.1:7878"));
        assert!(origin_allowed(&own, false));
        assert!(origin_allowed(
            &request("[::1]:80", Some("http://[::1]:80")),
            false
        ));
        assert!(origin_allowed(
            &request("localhost:1", Some("http://localhost:1")),
            false
        ));
        assert!(origin_allowed(&request("localhost:1", None), false));
        let other = request("127.0.0.1:7878", Some("http://evil.example"));
        assert!(!origin_allowed(&other, false));
        assert!(origin_allowed(&other, true));
        let rebound = request("evil.example:7878", Some("http://evil.example:7878"));
        assert!(!origin_allowed(&rebound, false));
    }

    #[test]
    fn addresses_show_as_urls() {
        let url = |s: &str| display_url(s.parse().unwrap_or(SocketAddr::from(([0; 4], 1))));
        assert_eq!(url("127.0.0.1:7878"), "http://127.0.0.1:7878/");
        assert_eq!(url("[::1]:7878"), "http://[::1]:7878/");
        assert_eq!(url("0.0.0.0:80"), "http://0.0.0.0:80/ (every interface)");
        assert_eq!(url("[::]:80"), "http://[::]:80/ (every interface)");
    }
}
