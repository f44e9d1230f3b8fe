//! The Zenoh side of a viewer (`texel-viewer --zenoh`): a gateway that follows every
//! camera matching a key pattern on Zenoh (`texel::wire::zenoh_keys`) and serves
//! their models, merged, as one viewer stream on a loopback port, so the viewer's own
//! connection (handshake, requests by id, reconnect) reads Zenoh unchanged.
//!
//! Merging: camera *k* (numbered from 1 in the order they appear) gives its scan
//! *i* the id `k << 24 | i` ([`global_id`]), so each camera's scans keep their own
//! ids and the viewer's scan-colour mode colours them by camera. A camera is found by
//! its liveliness token; the gateway then asks it for its model (the listing, coarse
//! first) while holding back what arrives live meanwhile, and applies that after the
//! listing. Scans' data come from what the cameras put live (kept within a byte
//! budget) or, when missed or evicted, from a query by id (`fetch`: paced to each
//! camera's link).

mod cameras;
mod fetch;
mod serve;
#[cfg(test)]
mod tests_support {
    /// Where a frame's kind byte is (after its length).
    pub const KIND_AT: usize = texel::wire::LENGTH_PREFIX;
}

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use thiserror::Error;
use tokio::net::TcpListener;
use tokio_util::sync::{CancellationToken, DropGuard};
use zenoh::qos::Priority;

use texel::model::ScanId;
use texel::wire::zenoh_keys::{self, KeyError, Topic, parse_key};

pub use cameras::CameraView;
use cameras::Cameras;
use fetch::Links;

/// Camera numbers take the top 8 bits of a 32-bit scan id.
pub const CAMERA_SHIFT: u32 = 24;
/// Scans of one camera beyond this id cannot be merged.
pub const MAX_LOCAL_ID: ScanId = (1 << CAMERA_SHIFT) - 1;
/// Cameras one gateway follows.
pub const MAX_CAMERAS: usize = 255;

/// The merged id of camera `camera`'s (1-based) scan `local`; `None` past the limits.
pub fn global_id(camera: usize, local: ScanId) -> Option<ScanId> {
    if camera == 0 || camera > MAX_CAMERAS || local > MAX_LOCAL_ID {
        return None;
    }
    Some(((camera as ScanId) << CAMERA_SHIFT) | local)
}

/// Camera number and own id of a merged id.
pub fn split_id(global: ScanId) -> (usize, ScanId) {
    ((global >> CAMERA_SHIFT) as usize, global & MAX_LOCAL_ID)
}

#[derive(Debug, Error)]
pub enum GatewayError {
    #[error(transparent)]
    Keys(#[from] KeyError),
    #[error("cannot open the zenoh session: {0}")]
    Open(String),
    #[error("zenoh {what}: {message}")]
    Declare { what: String, message: String },
    #[error("cannot listen on loopback: {0}")]
    Listen(std::io::Error),
}

/// What a gateway follows and how.
pub struct GatewayOptions {
    /// `<site>` pattern (`*` for every site).
    pub site: String,
    /// `<camera>` pattern (`*` for every camera).
    pub camera: String,
    pub zenoh: zenoh::Config,
    /// Scans' data kept from live puts, in bytes; beyond it the oldest are dropped
    /// (and asked for again if a viewer wants them).
    pub data_cache_bytes: usize,
    /// How long a query (a model, a scan) may take at least; a scan's query is given
    /// longer when the camera's measured link rate says it needs it, and is asked
    /// again (`fetch`) before the scan is reported unavailable.
    pub query_timeout: Duration,
}

impl GatewayOptions {
    pub fn new(site: &str, camera: &str, zenoh: zenoh::Config) -> Self {
        Self {
            site: site.to_string(),
            camera: camera.to_string(),
            zenoh,
            data_cache_bytes: 256 << 20,
            query_timeout: Duration::from_secs(10),
        }
    }
}

/// A running gateway: viewers connect to [`Gateway::addr`].
pub struct Gateway {
    pub addr: SocketAddr,
    shared: Arc<Shared>,
    /// Cancels the gateway's tasks when the gateway is dropped.
    _stop: DropGuard,
}

impl Gateway {
    /// Opens Zenoh, subscribes to the cameras and starts serving on `127.0.0.1:0`.
    pub async fn start(options: GatewayOptions) -> Result<Self, GatewayError> {
        let selector = zenoh_keys::cameras_selector(&options.site, &options.camera)?;
        let mut config = options.zenoh;
        // Zenoh's open waits up to the scouting delay (500 ms) for the peers named in
        // `connect` to be up; the gateway follows cameras whenever their tokens
        // appear, so it needs no such wait (a late joiner sees the model sooner).
        config
            .insert_json5("open/return_conditions/connect_scouted", "false")
            .map_err(|e| GatewayError::Open(e.to_string()))?;
        let session = zenoh::open(config)
            .await
            .map_err(|e| GatewayError::Open(e.to_string()))?;
        let listener = TcpListener::bind(("127.0.0.1", 0))
            .await
            .map_err(GatewayError::Listen)?;
        let addr = listener.local_addr().map_err(GatewayError::Listen)?;
        let shared = Arc::new(Shared {
            session: session.clone(),
            state: Mutex::new(Cameras::new(options.data_cache_bytes)),
            links: Links::default(),
            query_timeout: options.query_timeout,
        });
        let stop = CancellationToken::new();
        let declare = |what: &str, e: zenoh::Error| GatewayError::Declare {
            what: format!("{what} {selector}"),
            message: e.to_string(),
        };
        // Live samples first, then the liveliness tokens with their history: what a
        // camera puts while its model is asked for is held back, never lost.
        let samples = session
            .declare_subscriber(format!("{selector}/**"))
            .await
            .map_err(|e| declare("subscriber", e))?;
        let alive = session
            .liveliness()
            .declare_subscriber(format!("{selector}/alive"))
            .history(true)
            .await
            .map_err(|e| declare("liveliness subscriber", e))?;
        let s = Arc::clone(&shared);
        let st = stop.clone();
        tokio::spawn(async move {
            loop {
                let sample = tokio::select! {
                    s = samples.recv_async() => s,
                    () = st.cancelled() => break,
                };
                let Ok(sample) = sample else { break };
                let key = sample.key_expr().to_string();
                let payload = sample.payload().to_bytes().to_vec();
                Arc::clone(&s).on_sample(&key, payload);
            }
        });
        let s = Arc::clone(&shared);
        let st = stop.clone();
        tokio::spawn(async move {
            loop {
                let token = tokio::select! {
                    t = alive.recv_async() => t,
                    () = st.cancelled() => break,
                };
                let Ok(token) = token else { break };
                let key = token.key_expr().to_string();
                let joined = token.kind() == zenoh::sample::SampleKind::Put;
                Arc::clone(&s).on_liveliness(&key, joined);
            }
        });
        tokio::spawn(serve::run(listener, Arc::clone(&shared), stop.clone()));
        Ok(Self {
            addr,
            shared,
            _stop: stop.drop_guard(),
        })
    }

    /// The cameras followed so far.
    pub fn cameras(&self) -> Vec<CameraView> {
        self.shared.lock().views()
    }

    /// The measured rate of camera `prefix`'s link (`texel/<site>/<camera>`), in bytes
    /// per second, from the scans' data seen arriving; `None` before any.
    pub fn link_bytes_per_s(&self, prefix: &str) -> Option<f64> {
        self.shared.links.rate(prefix)
    }
}

/// What the gateway's tasks share.
pub(crate) struct Shared {
    session: zenoh::Session,
    state: Mutex<Cameras>,
    links: Links,
    query_timeout: Duration,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Cameras> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn on_liveliness(self: Arc<Self>, key: &str, joined: bool) {
        let Some((site, camera, Topic::Alive)) = parse_key(key) else {
            return;
        };
        let prefix = format!("{}/{site}/{camera}", zenoh_keys::ROOT);
        if !joined {
            self.lock().left(&prefix);
            return;
        }
        let Some(index) = self.lock().joined(&prefix) else {
            tracing::warn!("zenoh: more than {MAX_CAMERAS} cameras; {prefix} is not shown");
            return;
        };
        tokio::spawn(async move { self.fetch_model(index, prefix).await });
    }

    fn on_sample(self: Arc<Self>, key: &str, payload: Vec<u8>) {
        let Some((site, camera, topic)) = parse_key(key) else {
            return;
        };
        let prefix = format!("{}/{site}/{camera}", zenoh_keys::ROOT);
        let data_bytes = payload.len();
        {
            let mut state = self.lock();
            match topic {
                Topic::Model => state.snapshot(&prefix, &payload),
                Topic::Alive | Topic::Info => {}
                _ => state.live(&prefix, topic, payload),
            }
        }
        match topic {
            Topic::Listing(id) => self.links.listed(&prefix, id),
            Topic::Scan(id) => self.links.data_arrived(&prefix, id, data_bytes),
            _ => {}
        }
    }

    /// Asks camera `index` for its info and model and applies them.
    async fn fetch_model(&self, index: usize, prefix: String) {
        let info = self
            .query_one(
                &format!("{prefix}/info"),
                self.query_timeout,
                Priority::Data,
            )
            .await;
        if let Some(info) = info {
            self.lock().set_info(index, &info);
        }
        match self
            .query_one(
                &format!("{prefix}/model"),
                self.query_timeout,
                Priority::Data,
            )
            .await
        {
            Some(model) => self.lock().snapshot(&prefix, &model),
            None => tracing::warn!("zenoh: {prefix} did not answer for its model"),
        }
    }

    /// The first reply's payload to a query, or `None` (no answer, an error reply).
    /// The camera replies at the query's priority: scans' data are asked for at
    /// `DataLow`, as the camera puts them, so that on a slow link its listings,
    /// revisions and statuses (at `Data`) are not queued behind them.
    pub(crate) async fn query_one(
        &self,
        selector: &str,
        timeout: Duration,
        priority: Priority,
    ) -> Option<Vec<u8>> {
        let replies = self
            .session
            .get(selector)
            .priority(priority)
            .timeout(timeout)
            .await
            .ok()?;
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                return Some(sample.payload().to_bytes().to_vec());
            }
        }
        None
    }
}
