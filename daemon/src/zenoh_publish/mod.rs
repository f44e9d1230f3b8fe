//! Publishing the model on Zenoh (`[zenoh]`, `docs/daemon.md` "On Zenoh"): the
//! publisher is one more subscriber of the hub, speaking protocol version 2, that
//! puts each live frame under the camera's keys (`texel::wire::zenoh_keys`) and
//! answers queries for the model's snapshot (coarse first) and for scans by id, so a
//! late joiner gets the whole model from this daemon without it resending anything
//! to the others.
//!
//! Radio links: listings, pose revisions, withdrawals and statuses are reliable and
//! blocking (Zenoh holds them until the link takes them; the hub cuts this publisher
//! off and it republishes the snapshot if that takes too long), scans' data are put
//! with congestion control `Drop` at a lower priority: a subscriber that misses one
//! asks for it by id. The camera's pipeline never waits for any of it: every put
//! and every reply runs on a blocking thread (Zenoh completes them in the calling
//! thread), and the hub's queue to this publisher is bounded like a viewer's.

mod config;
mod queries;

use std::sync::Arc;
use std::sync::atomic::Ordering;

use bytes::Bytes;
use thiserror::Error;
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::{Session, Wait};

use crate::config::SessionConfig;
use crate::hub::{Hub, Subscription};
use texel::wire::zenoh_keys::{CameraKeys, frame_head};

pub use config::zenoh_config;

/// The protocol version published: everything but the level-of-detail tiles and the
/// radiance messages (those name ids a multi-camera subscriber would have to map).
pub const PUBLISHED_VERSION: u16 = 2;

/// Scans whose data are being read for publication at once; a new scan beyond this
/// is only listed (subscribers ask for its data).
const DATA_PUTS_IN_FLIGHT: usize = 4;

#[derive(Debug, Error)]
pub enum ZenohError {
    #[error("zenoh config {key}: {message}")]
    Config { key: String, message: String },
    #[error("{key} {path}: {message}")]
    File {
        key: &'static str,
        path: String,
        message: String,
    },
    #[error("cannot open the zenoh session: {0}")]
    Open(String),
    #[error("zenoh {what}: {message}")]
    Declare { what: String, message: String },
    #[error("zenoh keys: {0}")]
    Keys(#[from] texel::wire::zenoh_keys::KeyError),
    #[error("the model closed before publishing began")]
    Closed,
}

/// What `info` answers: who this camera is and which frame its poses are in.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CameraInfo {
    pub site: String,
    pub camera: String,
    pub world_frame: String,
    pub session_name: String,
    pub server_name: String,
    pub protocol_version: u16,
}

/// A running publisher.
pub struct ZenohPublisher {
    pub keys: CameraKeys,
    /// Where this daemon listens for Zenoh (real ports, for `tcp/...:0`).
    pub locators: Vec<String>,
    task: tokio::task::JoinHandle<()>,
}

impl ZenohPublisher {
    /// Opens Zenoh, declares the camera's liveliness token and queryables and starts
    /// forwarding the hub's frames; stops when `shutdown` is cancelled or the hub
    /// closes.
    pub async fn start(
        config: &SessionConfig,
        hub: Arc<Hub>,
        shutdown: CancellationToken,
    ) -> Result<Self, ZenohError> {
        let section = &config.zenoh;
        let camera = section.camera_name(&config.session.name);
        let keys = CameraKeys::new(&section.site, &camera)?;
        let info = CameraInfo {
            site: section.site.clone(),
            camera,
            world_frame: world_frame(config),
            session_name: config.session.name.clone(),
            server_name: format!("texeld {}", env!("CARGO_PKG_VERSION")),
            protocol_version: PUBLISHED_VERSION,
        };
        let locators = config::with_ports_chosen(&section.listen)?;
        let mut section = section.clone();
        section.listen = locators.clone();
        let session = zenoh::open(zenoh_config(&section)?)
            .await
            .map_err(|e| ZenohError::Open(e.to_string()))?;
        let subscription = hub
            .subscribe_version(PUBLISHED_VERSION)
            .map_err(|_| ZenohError::Closed)?;
        let declared = queries::declare(&session, &keys, &info, &hub).await?;
        tracing::info!(
            "zenoh: publishing {} ({}, world frame {:?}) on {}",
            keys.prefix(),
            section.mode.name(),
            info.world_frame,
            if locators.is_empty() {
                "no listening endpoint".to_string()
            } else {
                locators.join(", ")
            }
        );
        let forward = Forward {
            session,
            keys: keys.clone(),
            hub,
            data_puts: Arc::new(Semaphore::new(DATA_PUTS_IN_FLIGHT)),
        };
        let task = tokio::spawn(async move {
            forward.run(subscription, shutdown).await;
            // Undeclare the queryables and the liveliness token before closing, so
            // subscribers see the camera leave at once.
            declared.undeclare().await;
            let _ = forward.session.close().await;
        });
        Ok(Self {
            keys,
            locators,
            task,
        })
    }

    /// Waits for the publisher to stop (after the hub closed or shutdown).
    pub async fn wait(self) {
        let _ = self.task.await;
    }
}

/// The world frame `info` names (`[zenoh] world_frame`, doc there).
fn world_frame(config: &SessionConfig) -> String {
    if let Some(frame) = &config.zenoh.world_frame {
        return frame.clone();
    }
    #[cfg(feature = "sim")]
    let scene = config.source.sim.first().map(|s| &s.scene).or(config
        .source
        .sim_serial
        .first()
        .map(|s| &s.scene));
    #[cfg(not(feature = "sim"))]
    let scene: Option<&std::path::PathBuf> = None;
    match scene.and_then(|p| p.file_stem()) {
        Some(stem) => format!("sim:{}", stem.to_string_lossy()),
        None => format!(
            "{}/{}",
            config.zenoh.site,
            config.zenoh.camera_name(&config.session.name)
        ),
    }
}

struct Forward {
    session: Session,
    keys: CameraKeys,
    hub: Arc<Hub>,
    data_puts: Arc<Semaphore>,
}

impl Forward {
    async fn run(&self, mut subscription: Subscription, shutdown: CancellationToken) {
        loop {
            let frame = tokio::select! {
                frame = subscription.live.recv() => frame,
                () = shutdown.cancelled() => None,
            };
            let Some(frame) = frame else { break };
            if !self.publish(frame).await {
                break;
            }
            if subscription.lagged.load(Ordering::Acquire) {
                // The hub cut us off: start again from a snapshot, put on `model` so
                // subscribers re-read the listings they may have missed.
                self.hub.unsubscribe(subscription.client_id);
                match self.hub.subscribe_version(PUBLISHED_VERSION) {
                    Ok(s) => subscription = s,
                    Err(_) => break,
                }
                tracing::warn!("zenoh: the links fell behind the model; republishing its listing");
                let snapshot: Vec<u8> = subscription.snapshot.concat();
                self.put_reliable(self.keys.model(), Bytes::from(snapshot))
                    .await;
            }
        }
        self.hub.unsubscribe(subscription.client_id);
    }

    /// Puts one live frame under its key; false once the stream has ended.
    async fn publish(&self, frame: Bytes) -> bool {
        use texel::wire::kind as kinds;
        let Some((kind, id)) = frame_head(&frame) else {
            return true;
        };
        match (kind, id) {
            // A new scan: its listing, reliable, then its data, droppable.
            (kinds::SCAN_ADDED, Some(id)) => {
                if let Some(listing) = self.hub.listing_frame(id) {
                    self.put_reliable(self.keys.listing(id), listing).await;
                    self.put_droppable(self.keys.scan(id), frame).await;
                }
            }
            // A scan served again (retirement restored it): its data are read back.
            (kinds::SCAN_LISTED, Some(id)) => {
                self.put_reliable(self.keys.listing(id), frame).await;
                self.put_data(id);
            }
            (kinds::POSE_REVISED, Some(id)) => {
                self.put_reliable(self.keys.pose(id), frame).await;
            }
            (kinds::SCAN_WITHDRAWN, Some(id)) => {
                self.put_reliable(self.keys.withdrawn(id), frame).await;
            }
            (kinds::STATUS, None) => self.put_reliable(self.keys.status(), frame).await,
            (kinds::GOODBYE, None) => return false,
            _ => {}
        }
        true
    }

    /// Listings, revisions, withdrawals, statuses: Zenoh holds them until the link
    /// takes them.
    async fn put_reliable(&self, key: String, payload: Bytes) {
        self.put(key, payload, CongestionControl::Block, Priority::Data)
            .await;
    }

    /// Scans' data: dropped first on a congested link (subscribers ask again by id).
    async fn put_droppable(&self, key: String, payload: Bytes) {
        self.put(key, payload, CongestionControl::Drop, Priority::DataLow)
            .await;
    }

    /// One put, on a blocking thread: Zenoh's put runs to completion in the calling
    /// thread (its `Block` waits there for the link), which on a tokio worker would
    /// stall every other task of the daemon, the camera's pipeline included. Awaiting
    /// the blocking thread keeps the puts in order and lets this publisher's bounded
    /// queue at the hub fill instead.
    async fn put(
        &self,
        key: String,
        payload: Bytes,
        congestion: CongestionControl,
        priority: Priority,
    ) {
        let session = self.session.clone();
        let put = tokio::task::spawn_blocking(move || {
            session
                .put(&key, payload.to_vec())
                .congestion_control(congestion)
                .priority(priority)
                .wait()
                .map_err(|e| format!("put {key}: {e}"))
        })
        .await;
        match put {
            Ok(Ok(())) => {}
            Ok(Err(e)) => tracing::warn!("zenoh: {e}"),
            Err(e) => tracing::warn!("zenoh: a put's thread failed: {e}"),
        }
    }

    /// Reads scan `id`'s frame off the async threads and puts it, droppable; skipped
    /// when enough reads are under way (subscribers then ask for it).
    fn put_data(&self, id: texel::model::ScanId) {
        let Ok(permit) = Arc::clone(&self.data_puts).try_acquire_owned() else {
            return;
        };
        let hub = Arc::clone(&self.hub);
        let session = self.session.clone();
        let key = self.keys.scan(id);
        tokio::task::spawn_blocking(move || {
            let _permit = permit;
            let Ok(frame) = hub.fetch_scan(id) else {
                return;
            };
            let Ok(frames) = hub.finish_fetch(id, frame) else {
                return;
            };
            let put = session
                .put(&key, frames.concat())
                .congestion_control(CongestionControl::Drop)
                .priority(Priority::DataLow)
                .wait();
            if let Err(e) = put {
                tracing::debug!("zenoh: put {key}: {e}");
            }
        });
    }
}
