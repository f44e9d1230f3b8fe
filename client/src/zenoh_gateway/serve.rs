//! The gateway's loopback server: each viewer says hello, gets the merged listing and
//! then every change, and asks for scans by id, answered from the cache or by a
//! Zenoh query to the camera that has the scan.

use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::{Bytes, BytesMut};
use texel::wire::{Limits, MIN_PROTOCOL_VERSION, Message, decode_frame};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use super::Shared;
use super::cameras::Cameras;

/// The version the gateway speaks (what the cameras publish).
const VERSION: u16 = 2;
/// Frames queued per viewer before it counts as slow and is dropped.
const VIEWER_QUEUE: usize = 1024;
/// Viewers at once (they are on this machine).
const MAX_VIEWERS: usize = 8;
/// The longest pause before asking again after a query ended without an answer.
const RETRY_PAUSE_MAX: Duration = Duration::from_secs(5);
/// How long a viewer has to say hello.
const HELLO_TIMEOUT: Duration = Duration::from_secs(5);

pub(crate) async fn run(listener: TcpListener, shared: Arc<Shared>, stop: CancellationToken) {
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_VIEWERS));
    loop {
        let accepted = tokio::select! {
            a = listener.accept() => a,
            () = stop.cancelled() => break,
        };
        let Ok((stream, _)) = accepted else { continue };
        let Ok(slot) = Arc::clone(&slots).try_acquire_owned() else {
            continue;
        };
        let shared = Arc::clone(&shared);
        let stop = stop.clone();
        tokio::spawn(async move {
            let _slot = slot;
            if let Err(e) = viewer(stream, shared, stop).await {
                tracing::debug!("zenoh gateway: viewer: {e}");
            }
        });
    }
}

async fn viewer(
    mut stream: TcpStream,
    shared: Arc<Shared>,
    stop: CancellationToken,
) -> std::io::Result<()> {
    let _ = stream.set_nodelay(true);
    let mut buf = BytesMut::with_capacity(4096);
    let hello = tokio::time::timeout(HELLO_TIMEOUT, next_message(&mut stream, &mut buf))
        .await
        .map_err(|_| std::io::Error::other("no hello in time"))??;
    let version = match hello {
        Some(Message::ClientHello { version, .. }) if version >= MIN_PROTOCOL_VERSION => version,
        _ => {
            let refusal = Message::Refused {
                reason: format!("expected a hello of version {MIN_PROTOCOL_VERSION} or later"),
            };
            stream.write_all(&encode(&refusal)).await?;
            return Ok(());
        }
    };
    stream
        .write_all(&encode(&Message::ServerHello {
            version: version.min(VERSION),
            server_name: "texel zenoh gateway".into(),
            session_name: "zenoh".into(),
        }))
        .await?;
    // The snapshot and the live queue start under one lock: nothing missed or twice.
    let (tx, mut rx) = mpsc::channel::<Bytes>(VIEWER_QUEUE);
    let snapshot = {
        let mut state = shared.lock();
        state.viewers.push(tx.clone());
        state.snapshot_frames()
    };
    for frame in snapshot {
        stream.write_all(&frame).await?;
    }
    let (mut reader, mut writer) = stream.into_split();
    let answers = tx;
    let reading = async {
        loop {
            let Some(message) = next_message(&mut reader, &mut buf).await? else {
                return Ok::<(), std::io::Error>(());
            };
            match message {
                Message::RequestScan { id } => {
                    let shared = Arc::clone(&shared);
                    let answers = answers.clone();
                    tokio::spawn(async move {
                        let frames = answer(&shared, id).await;
                        let _ = answers.send(frames).await;
                    });
                }
                Message::Goodbye { .. } => return Ok(()),
                _ => {}
            }
        }
    };
    let writing = async {
        while let Some(frame) = rx.recv().await {
            writer.write_all(&frame).await?;
        }
        Ok::<(), std::io::Error>(())
    };
    tokio::select! {
        r = reading => r,
        r = writing => r,
        () = stop.cancelled() => Ok(()),
    }
}

/// The frames answering a request for merged scan `id`: from the cache; else, for a
/// scan just listed live, its data when they arrive; else by asking its camera
/// (`fetch`: in turn, with timeouts from the link's rate, and again on no answer).
async fn answer(shared: &Shared, id: u64) -> Bytes {
    let (prefix, own, bytes) = {
        let state = shared.lock();
        if let Some(data) = state.cached(id) {
            return data;
        }
        if !state.is_listed(id) {
            return unavailable(id, "not listed by any camera followed");
        }
        let Some((prefix, own)) = state.source_of(id) else {
            return unavailable(id, "no camera has this id");
        };
        (prefix, own, state.encoded_bytes(id))
    };
    if let Some(data) = wait_for_live_data(shared, id, &prefix, own, bytes).await {
        return data;
    }
    let Some(plan) = shared
        .links
        .plan_query(&prefix, bytes, shared.query_timeout)
        .await
    else {
        return unavailable(id, "the gateway is stopping");
    };
    let selector = format!("{prefix}/scan/{own}");
    for timeout in plan.timeouts {
        // Arrived live (or asked by another viewer) while this one waited its turn.
        if let Some(data) = shared.lock().cached(id) {
            return data;
        }
        let asked = Instant::now();
        let Some(payload) = shared
            .query_one(&selector, timeout, zenoh::qos::Priority::DataLow)
            .await
        else {
            tracing::debug!("zenoh gateway: no answer for {selector} within {timeout:?}");
            // No answer well before the timeout: the session to the camera went
            // (it reconnects by itself); give it time rather than spend the attempts.
            let left = timeout.saturating_sub(asked.elapsed());
            tokio::time::sleep(left.min(RETRY_PAUSE_MAX)).await;
            continue;
        };
        shared
            .links
            .query_answered(&prefix, payload.len(), asked.elapsed());
        let (n, _) = super::split_id(id);
        return match Cameras::remap_data(n, &payload) {
            Some(frames) => Bytes::from(frames),
            None => unavailable(id, &format!("{prefix}: an answer that is not whole frames")),
        };
    }
    drop(plan.permit);
    unavailable(
        id,
        &format!(
            "{prefix} did not answer for scan {own} ({} attempts)",
            super::fetch::QUERY_ATTEMPTS
        ),
    )
}

/// Scan `id`'s data when the camera's live put of them arrives before the wait its
/// link's rate allows; `None` when not just listed live, or not in time.
async fn wait_for_live_data(
    shared: &Shared,
    id: u64,
    prefix: &str,
    own: texel::model::ScanId,
    bytes: u64,
) -> Option<Bytes> {
    let until = shared.links.live_wait_until(prefix, own, bytes)?;
    loop {
        // Registered before looking, so an arrival in between still wakes us.
        let arrived = shared.links.data_arrived.notified();
        tokio::pin!(arrived);
        arrived.as_mut().enable();
        if let Some(data) = shared.lock().cached(id) {
            return Some(data);
        }
        let deadline = tokio::time::Instant::from_std(until);
        if tokio::time::timeout_at(deadline, arrived).await.is_err() {
            return shared.lock().cached(id);
        }
    }
}

fn unavailable(id: u64, reason: &str) -> Bytes {
    Bytes::from(encode(&Message::ScanUnavailable {
        id,
        reason: reason.to_string(),
    }))
}

fn encode(m: &Message) -> Vec<u8> {
    m.encode().unwrap_or_default()
}

/// The next message from a viewer; `None` at a clean end.
async fn next_message<R: AsyncReadExt + Unpin>(
    reader: &mut R,
    buf: &mut BytesMut,
) -> std::io::Result<Option<Message>> {
    loop {
        match decode_frame(buf, &Limits::FROM_CLIENT) {
            Ok(Some((m, used))) => {
                let _ = buf.split_to(used);
                return Ok(Some(m));
            }
            Ok(None) => {}
            Err(e) => return Err(std::io::Error::other(e.to_string())),
        }
        if reader.read_buf(buf).await? == 0 {
            return Ok(None);
        }
    }
}
