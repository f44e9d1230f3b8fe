//! What the publisher answers on Zenoh: `info` (JSON), `model` (the snapshot of
//! listings, coarse first, as one payload of frames) and `scan/<id>` (a scan's
//! frame, read from memory or the store on a blocking thread, or a `ScanUnavailable`
//! saying why not), and the camera's liveliness token.

use std::sync::Arc;

use bytes::Bytes;
use texel::wire::Message;
use texel::wire::zenoh_keys::{CameraKeys, Topic, parse_key};
use tokio::sync::Semaphore;
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::query::{Query, Queryable};
use zenoh::{Session, Wait};

use super::{CameraInfo, PUBLISHED_VERSION, ZenohError};
use crate::hub::Hub;

/// Scan queries answered at once; more wait in Zenoh's queue (bounded there).
const SCAN_QUERIES_IN_FLIGHT: usize = 8;

/// The declarations to undo when the publisher stops.
pub struct Declared {
    token: LivelinessToken,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Declared {
    pub async fn undeclare(self) {
        for t in &self.tasks {
            t.abort();
        }
        let _ = self.token.undeclare().await;
    }
}

async fn queryable(
    session: &Session,
    key: String,
) -> Result<Queryable<FifoChannelHandler<Query>>, ZenohError> {
    session
        .declare_queryable(&key)
        .await
        .map_err(|e| ZenohError::Declare {
            what: format!("queryable {key}"),
            message: e.to_string(),
        })
}

/// Declares the queryables and the liveliness token, each queryable served by a
/// task of its own.
pub async fn declare(
    session: &Session,
    keys: &CameraKeys,
    info: &CameraInfo,
    hub: &Arc<Hub>,
) -> Result<Declared, ZenohError> {
    let info_json = Bytes::from(serde_json::to_vec(info).unwrap_or_default());
    let info_q = queryable(session, keys.info()).await?;
    let model_q = queryable(session, keys.model()).await?;
    let scan_q = queryable(session, keys.scans()).await?;
    let mut tasks = Vec::new();
    tasks.push(tokio::spawn(async move {
        while let Ok(query) = info_q.recv_async().await {
            let key = query.key_expr().to_string();
            reply(query, key, info_json.to_vec()).await;
        }
    }));
    let model_hub = Arc::clone(hub);
    let model_key = keys.model();
    tasks.push(tokio::spawn(async move {
        while let Ok(query) = model_q.recv_async().await {
            // A snapshot taken the way a viewer's is, under the hub's lock.
            let Ok(subscription) = model_hub.subscribe_version(PUBLISHED_VERSION) else {
                let _ = query.reply_err(b"the model is closed".to_vec()).await;
                continue;
            };
            model_hub.unsubscribe(subscription.client_id);
            let payload = subscription.snapshot.concat();
            reply(query, model_key.clone(), payload).await;
        }
    }));
    let scan_hub = Arc::clone(hub);
    tasks.push(tokio::spawn(async move {
        let in_flight = Arc::new(Semaphore::new(SCAN_QUERIES_IN_FLIGHT));
        while let Ok(query) = scan_q.recv_async().await {
            let Ok(permit) = Arc::clone(&in_flight).acquire_owned().await else {
                break;
            };
            let hub = Arc::clone(&scan_hub);
            tokio::spawn(async move {
                let _permit = permit;
                answer_scan(query, hub).await;
            });
        }
    }));
    let token = session
        .liveliness()
        .declare_token(keys.alive())
        .await
        .map_err(|e| ZenohError::Declare {
            what: format!("liveliness token {}", keys.alive()),
            message: e.to_string(),
        })?;
    Ok(Declared { token, tasks })
}

/// Answers a query for one scan's data; a wildcard query gets no reply (ask by id).
async fn answer_scan(query: Query, hub: Arc<Hub>) {
    let key = query.key_expr().to_string();
    let Some((_, _, Topic::Scan(id))) = parse_key(&key) else {
        let _ = query
            .reply_err(b"ask for one scan: .../scan/<id>".to_vec())
            .await;
        return;
    };
    // Read and reply on one blocking thread: the store may be read from disk, and
    // Zenoh sends a reply to completion in the calling thread, waiting for a slow
    // link there.
    let replied = tokio::task::spawn_blocking(move || {
        let payload: Vec<u8> = match hub
            .fetch_scan(id)
            .and_then(|frame| hub.finish_fetch(id, frame))
        {
            Ok(frames) => frames.concat(),
            Err(e) => unavailable(id, &e.to_string()),
        };
        query.reply(key, payload).wait()
    })
    .await;
    if let Ok(Err(e)) = replied {
        tracing::debug!("zenoh: reply for scan {id}: {e}");
    }
}

/// Replies on a blocking thread (see [`answer_scan`]).
async fn reply(query: Query, key: String, payload: Vec<u8>) {
    let _ = tokio::task::spawn_blocking(move || query.reply(key, payload).wait()).await;
}

fn unavailable(id: texel::model::ScanId, reason: &str) -> Vec<u8> {
    let mut end = reason.len().min(texel::wire::MAX_REASON_LEN);
    while !reason.is_char_boundary(end) {
        end -= 1;
    }
    let reason = reason[..end].to_string();
    Message::ScanUnavailable { id, reason }
        .encode()
        .unwrap_or_default()
}
