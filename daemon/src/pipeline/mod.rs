//! A daemon session: sources -> ingest (record, sync) -> worker (fuse, register) ->
//! encode stage -> hub -> server, with a recorder thread, a status task and an
//! orderly shutdown. Every channel is bounded:
//!
//! | channel | capacity | when full |
//! |---|---|---|
//! | sources -> ingest | `pipeline.ingest_queue` | sources wait (ingest only records and pairs) |
//! | ingest -> recorder | `record.queue` | ingest waits: nothing received is dropped |
//! | ingest -> worker | `pipeline.pair_queue` | `keep-newest`: one newest pair waits, older waiting ones are skipped and counted; `backpressure`: ingest waits |
//! | worker -> encode | `pipeline.encode_queue` | the worker waits (encoding is faster than registration) |
//! | hub -> each client | `serve.client_queue` | the client is resynchronised or disconnected |
//!
//! Shutdown: the sources stop, ingest drains and passes on what waits, the worker
//! finishes its queue, the recorder finalises the capture, then the hub closes and
//! every client is told why.

pub mod encode;
pub mod ingest;
pub mod lod;
mod restore;
pub mod tap;
/// The registration stage lives with registration; the pipeline drives it.
pub use texel_register::placement;
pub mod worker;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use texel::SensorModel;
use texel::paged::{PAGE_RECORDS, Record};
use texel::sync::SharedFrameSync;
use texel::wire::Message;
use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use self::lod::{LodInbox, LodStage};
use crate::config::{RegistrationMode, SessionConfig};
use crate::hub::{Hub, ModelOptions};
use crate::pages::FilePages;
use crate::record::{RecordItem, RecordSummary, Recorder};
use crate::resume::{self, ResumeError};
use crate::server::{self, ServeOptions};
use crate::shelf::{DiskShelf, ShelfFiles};
use crate::source::replay::{Pace, ReplaySource};
use crate::source::serial::SerialSource;
#[cfg(feature = "sim")]
use crate::source::sim::SimSource;
#[cfg(feature = "sim")]
use crate::source::sim_serial::SimSerialSource;
use crate::source::v4l::V4lSource;
use crate::source::v4l_convert::PixelFormat;
use crate::source::{FrameSink, Source, SourceMetrics};
use crate::status::{Metrics, QueueProbe, status_line};
use crate::store::Store;
use crate::zenoh_publish::ZenohPublisher;
use encode::Encoder;
use ingest::Ingest;
use placement::{CapturePoses, RegistrarStage, Registration};
use restore::{Restored, restore_session};
use texel_register::scan_table::ScanRecord;
use worker::Worker;

#[derive(Debug, Error)]
pub enum SessionError {
    #[error("sensor file: {0}")]
    Sensor(#[from] texel::sensor::SensorError),
    /// `message` names the file.
    #[error("pose capture: {message}")]
    PoseCapture { path: String, message: String },
    #[error("recording: {0}")]
    Record(#[from] texel::capture::CaptureError),
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        source: std::io::Error,
    },
    #[error("config: {0}")]
    Config(String),
    #[error("{0}")]
    Store(String),
    #[error(transparent)]
    Resume(#[from] ResumeError),
    #[error("a pipeline thread failed: {0}")]
    Thread(String),
    #[error(transparent)]
    Zenoh(#[from] crate::zenoh_publish::ZenohError),
    #[cfg(feature = "foxglove-live")]
    #[error(transparent)]
    Foxglove(#[from] crate::foxglove_live::FoxgloveLiveError),
}

/// What a finished session did.
#[derive(Debug, Clone)]
pub struct SessionSummary {
    pub scans: usize,
    pub recording: Option<RecordSummary>,
    pub status: texel::wire::Status,
}

/// A running session.
pub struct Session {
    pub hub: Arc<Hub>,
    pub metrics: Arc<Metrics>,
    /// Where viewers connect (the bound address, so port 0 becomes a real port).
    pub local_addr: Option<SocketAddr>,
    /// Cancelled when every source has stopped.
    pub sources_done: CancellationToken,
    /// Where this daemon listens for Zenoh, when it publishes there (`[zenoh]`).
    pub zenoh_locators: Vec<String>,
    zenoh: Option<ZenohPublisher>,
    /// Where the Foxglove app connects, when the session offers itself there
    /// (`[foxglove]`; the bound address, so port 0 becomes a real port).
    pub foxglove_addr: Option<SocketAddr>,
    #[cfg(feature = "foxglove-live")]
    foxglove: Option<crate::foxglove_live::FoxgloveLive>,
    task: JoinHandle<Result<SessionSummary, SessionError>>,
}

impl Session {
    /// Starts a validated session; `shutdown` stops it.
    pub async fn start(
        config: SessionConfig,
        shutdown: CancellationToken,
    ) -> Result<Self, SessionError> {
        let registration = build_registration(&config)?;
        Self::start_with_registration(config, registration, shutdown).await
    }

    /// Starts a validated session with a given registration stage instead of the one
    /// `pipeline.registration` names.
    pub async fn start_with_registration(
        config: SessionConfig,
        registration: Box<dyn Registration>,
        shutdown: CancellationToken,
    ) -> Result<Self, SessionError> {
        // Library users get the same checks as the command line (a token off
        // loopback, bounded queues).
        config
            .validate(&format!("session {:?}", config.session.name))
            .map_err(|e| SessionError::Config(e.to_string()))?;
        let listener = if config.serve.enabled {
            let addr = config.serve.bind;
            Some(
                TcpListener::bind(addr)
                    .await
                    .map_err(|source| SessionError::Bind { addr, source })?,
            )
        } else {
            None
        };
        let local_addr = listener.as_ref().and_then(|l| l.local_addr().ok());
        let sensor = match &config.session.sensor {
            Some(path) if config.source.replay.is_empty() => {
                Some(Arc::new(SensorModel::load(path)?))
            }
            _ => None,
        };
        let mut config = config;
        let mut registration = registration;
        // A resumed session reads its recording's segments and records to the next.
        let segments = if config.record.resume {
            let base = config
                .record
                .path
                .clone()
                .ok_or(ResumeError::NotRecording)?;
            let segments = resume::segments(&base)?;
            config.record.path = Some(segments.next.clone());
            Some((base, segments))
        } else {
            None
        };
        let store_base = segments
            .as_ref()
            .map(|(base, _)| base.clone())
            .or_else(|| config.record.path.clone());
        let hub = Hub::with_model(
            config.serve.client_queue,
            model_options(&config, store_base.as_deref())?,
        );
        let metrics = Metrics::new();
        let mut restored = Restored::default();
        if let Some((_, segments)) = segments {
            let (stage, r) = restore_session(
                segments.existing,
                &config,
                registration,
                Arc::clone(&hub),
                Arc::clone(&metrics),
            )
            .await?;
            registration = stage;
            restored = r;
        }
        let recorder = match &config.record.path {
            Some(path) => Some(Recorder::start(path, &config.record)?),
            None => None,
        };
        // Sources are known to the status from the start.
        let sources: Vec<_> = build_sources_after(&config, restored.last_timestamp_ns)
            .into_iter()
            .map(|source| {
                let m = SourceMetrics::new(source.name(), source.kind());
                metrics.add_source(Arc::clone(&m));
                (source, m)
            })
            .collect();
        let zenoh = if config.zenoh.enabled {
            Some(ZenohPublisher::start(&config, Arc::clone(&hub), shutdown.clone()).await?)
        } else {
            None
        };
        // Last before the pipeline starts: nothing after it can fail.
        #[cfg(feature = "foxglove-live")]
        let foxglove = if config.foxglove.enabled {
            let live = crate::foxglove_live::FoxgloveLive::start(
                &config.foxglove,
                &config.session.name,
                Arc::clone(&hub),
                &metrics,
            )
            .await?;
            Some(live)
        } else {
            None
        };
        #[cfg(feature = "foxglove-live")]
        let (tap, foxglove_addr) = (
            foxglove.as_ref().and_then(|f| f.tap()),
            foxglove.as_ref().map(|f| f.local_addr()),
        );
        #[cfg(not(feature = "foxglove-live"))]
        let (tap, foxglove_addr) = (None, None);
        let sources_done = CancellationToken::new();
        let task = tokio::spawn(run(
            config,
            sources,
            sensor,
            registration,
            recorder,
            listener,
            Arc::clone(&hub),
            Arc::clone(&metrics),
            shutdown,
            sources_done.clone(),
            restored,
            tap,
        ));
        Ok(Self {
            hub,
            metrics,
            local_addr,
            sources_done,
            zenoh_locators: zenoh
                .as_ref()
                .map(|z| z.locators.clone())
                .unwrap_or_default(),
            zenoh,
            foxglove_addr,
            #[cfg(feature = "foxglove-live")]
            foxglove,
            task,
        })
    }

    /// Waits for the session to end (and its Zenoh publisher to leave, for at most
    /// two seconds).
    pub async fn wait(self) -> Result<SessionSummary, SessionError> {
        let summary = self
            .task
            .await
            .map_err(|e| SessionError::Thread(e.to_string()))?;
        if let Some(zenoh) = self.zenoh {
            let _ = tokio::time::timeout(Duration::from_secs(2), zenoh.wait()).await;
        }
        #[cfg(feature = "foxglove-live")]
        if let Some(foxglove) = self.foxglove {
            foxglove.wait(Duration::from_secs(2)).await;
        }
        summary
    }
}

/// How the hub keeps the model: the budget, the store (beside the recording, where
/// `model.store_path` says, or an anonymous temporary file), retirement.
fn model_options(
    config: &SessionConfig,
    recording: Option<&std::path::Path>,
) -> Result<ModelOptions, SessionError> {
    let store = match config.model.store_path_for(recording) {
        Some(path) => Store::create(&path),
        None => Store::create_anonymous(),
    }
    .map_err(|e| SessionError::Store(e.to_string()))?;
    // Retired scans' entries wait beside the store (an unlinked file).
    let shelf = if config.model.retirement.enabled {
        Some(
            ShelfFiles::create_in(&spill_dir(config, recording))
                .map_err(|e| SessionError::Store(e.to_string()))?,
        )
    } else {
        None
    };
    // Tile data beyond its budget waits in its own unlinked store beside the scans'.
    let tile_store = if config.model.lod.enabled {
        Some(Arc::new(
            Store::create_unlinked_in(&spill_dir(config, recording), "tiles")
                .map_err(|e| SessionError::Store(format!("tile store: {e}")))?,
        ))
    } else {
        None
    };
    Ok(ModelOptions {
        tile_memory_budget_bytes: config.model.lod.tile_memory_budget_bytes(),
        tile_store,
        memory_budget_bytes: config.model.memory_budget_bytes(),
        store: Some(Arc::new(store)),
        coverage: Some(config.model.retirement),
        shelf,
    })
}

/// Where a session's unlinked spill files go (retired scans' entries, the pages of
/// per-frame tables): beside the model's store, or in the system's temporary folder
/// when the store is anonymous.
fn spill_dir(config: &SessionConfig, recording: Option<&std::path::Path>) -> std::path::PathBuf {
    config
        .model
        .store_path_for(recording)
        .and_then(|p| p.parent().map(std::path::Path::to_path_buf))
        .map(|d| {
            if d.as_os_str().is_empty() {
                std::path::PathBuf::from(".")
            } else {
                d
            }
        })
        .unwrap_or_else(std::env::temp_dir)
}

/// A page store in an unlinked file beside the store, for pages of `page_bytes`
/// (`name` marks its file and its errors).
fn file_pages(
    config: &SessionConfig,
    name: &str,
    page_bytes: usize,
) -> Result<Box<dyn texel::paged::PageStore>, SessionError> {
    let pages = FilePages::create_in(
        &spill_dir(config, config.record.path.as_deref()),
        name,
        page_bytes,
    )
    .map_err(|e| SessionError::Store(format!("{name} pages: {e}")))?;
    Ok(Box::new(pages))
}

/// A page store for a worker's table of 8-byte words.
fn word_pages(
    config: &SessionConfig,
    name: &str,
) -> Result<Box<dyn texel::paged::PageStore>, SessionError> {
    file_pages(config, name, PAGE_RECORDS * u64::LEN)
}

/// The sources a session's config names.
pub fn build_sources(config: &SessionConfig) -> Vec<Box<dyn Source>> {
    build_sources_after(config, None)
}

/// The sources of a session that goes on after `resume_after_ns` (a resumed one:
/// simulators skip what the recording holds).
pub fn build_sources_after(
    config: &SessionConfig,
    resume_after_ns: Option<u64>,
) -> Vec<Box<dyn Source>> {
    // Only simulators replay a trajectory from its start; live sources and replays
    // need no resume point.
    #[cfg(not(feature = "sim"))]
    let _ = resume_after_ns;
    let mut sources: Vec<Box<dyn Source>> = Vec::new();
    for c in &config.source.serial {
        sources.push(Box::new(SerialSource {
            name: c.name.clone(),
            path: c.path.clone(),
            baud: c.baud,
            stall_timeout: Duration::from_millis(c.stall_timeout_ms),
            backoff_min: Duration::from_millis(c.reopen_backoff_min_ms),
            backoff_max: Duration::from_millis(c.reopen_backoff_max_ms),
        }));
    }
    for c in &config.source.v4l {
        sources.push(Box::new(V4lSource {
            name: c.name.clone(),
            device: c.device.clone(),
            format: PixelFormat::from_name(&c.format).unwrap_or(PixelFormat::Yuyv),
            width: c.width,
            height: c.height,
            fps: c.fps,
            dequeue_timeout: Duration::from_millis(c.dequeue_timeout_ms),
            buffers: c.buffers,
        }));
    }
    for c in &config.source.replay {
        sources.push(Box::new(ReplaySource {
            name: c.name.clone(),
            capture: c.capture.clone(),
            pace: if c.fast {
                Pace::Fast
            } else {
                Pace::Speed(c.speed)
            },
        }));
    }
    #[cfg(feature = "sim")]
    for c in &config.source.sim {
        sources.push(Box::new(SimSource {
            name: c.name.clone(),
            setup: c.setup(),
            pace: if c.fast {
                Pace::Fast
            } else {
                Pace::Speed(c.speed)
            },
            prerender: c.prerender,
            render_threads: c.render_threads,
            late: c.late,
            truth: c.truth,
            loops: c.loops,
            resume_after_ns,
        }));
    }
    #[cfg(feature = "sim")]
    for c in &config.source.sim_serial {
        sources.push(Box::new(SimSerialSource::from_config(c)));
    }
    sources
}

/// The registration stage `pipeline.registration` names.
pub fn build_registration(config: &SessionConfig) -> Result<Box<dyn Registration>, SessionError> {
    let replayed = config.source.replay.first().map(|r| r.capture.clone());
    let read_poses = |path: &std::path::Path| {
        CapturePoses::from_capture(path).map_err(|e| SessionError::PoseCapture {
            path: path.display().to_string(),
            message: e.to_string(),
        })
    };
    let register = |truth| -> Result<Box<dyn Registration>, SessionError> {
        // The registrar's per-scan records beyond a few pages, and its keyframes'
        // member lists, wait on disk.
        let dir = spill_dir(config, config.record.path.as_deref());
        let pages = FilePages::create_in(&dir, "registrar", PAGE_RECORDS * ScanRecord::LEN)
            .map_err(|e| SessionError::Store(format!("registrar's record pages: {e}")))?;
        let members = DiskShelf::create_in(&dir, "shelf-members")
            .map_err(|e| SessionError::Store(format!("registrar's member lists: {e}")))?;
        Ok(Box::new(
            RegistrarStage::new(config.registration.clone())
                .with_truth(truth)
                .with_record_pages(Box::new(pages))
                .with_member_shelf(Box::new(members)),
        ))
    };
    let mode = match config.pipeline.registration {
        // A pose capture named explicitly is the session's choice.
        RegistrationMode::Auto if config.pipeline.pose_capture.is_some() => {
            RegistrationMode::CapturePoses
        }
        mode => mode,
    };
    match mode {
        RegistrationMode::CapturePoses => {
            let path = config
                .pipeline
                .pose_capture
                .clone()
                .or(replayed)
                .ok_or_else(|| {
                    SessionError::Config(
                        "capture-poses needs pipeline.pose_capture or a replay source".into(),
                    )
                })?;
            let poses = read_poses(&path)?;
            if poses.is_empty() {
                tracing::warn!(
                    "{} has no /texel/pose or /truth/pose: no scan can be placed",
                    path.display()
                );
            }
            Ok(Box::new(poses))
        }
        RegistrationMode::Register => {
            // A replayed capture's truth anchors the world, as `texeld register` does.
            let truth = match &replayed {
                Some(path) => read_poses(path)?.into_truth(),
                None => Default::default(),
            };
            register(truth)
        }
        RegistrationMode::Auto => match &replayed {
            None => register(Default::default()),
            Some(path) => {
                let poses = read_poses(path)?;
                if poses.texel_count() > 0 {
                    tracing::info!(
                        "{} carries /texel/pose: scans are placed there (registration = \"register\" registers them again)",
                        path.display()
                    );
                } else {
                    tracing::info!("{} has no /texel/pose: registering", path.display());
                }
                Ok(placement::replay_stage(poses, &config.registration))
            }
        },
    }
}

/// The level-of-detail stage's last status.
fn lock_status(s: &std::sync::Mutex<texel::wire::LodStatus>) -> texel::wire::LodStatus {
    s.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .clone()
}

fn depth_probe<T: Send + 'static>(name: &'static str, tx: &mpsc::Sender<T>) -> QueueProbe {
    let weak = tx.downgrade();
    QueueProbe {
        name,
        capacity: tx.max_capacity(),
        depth: Box::new(move || weak.upgrade().map(|tx| tx.max_capacity() - tx.capacity())),
    }
}

#[allow(clippy::too_many_arguments)]
async fn run(
    config: SessionConfig,
    sources: Vec<(Box<dyn Source>, Arc<SourceMetrics>)>,
    sensor: Option<Arc<SensorModel>>,
    registration: Box<dyn Registration>,
    recorder: Option<Recorder>,
    listener: Option<TcpListener>,
    hub: Arc<Hub>,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
    sources_done: CancellationToken,
    restored: Restored,
    tap: Option<tap::Tap>,
) -> Result<SessionSummary, SessionError> {
    let record_tx = recorder.as_ref().map(|r| r.tx.clone());
    if let Some(r) = &recorder {
        *metrics
            .recording
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) =
            Some(crate::status::RecordingProbe {
                path: r.path.clone(),
                messages: Arc::clone(&r.messages),
                errors: Arc::clone(&r.errors),
            });
        metrics.add_queue(depth_probe("record", &r.tx));
    }

    // Sources.
    let (events_tx, events_rx) = mpsc::channel(config.pipeline.ingest_queue);
    metrics.add_queue(depth_probe("ingest", &events_tx));
    let mut source_tasks = tokio::task::JoinSet::new();
    for (i, (source, m)) in sources.into_iter().enumerate() {
        let sink = FrameSink::new(i, events_tx.clone(), m);
        let name = source.name().to_string();
        let stop = shutdown.clone();
        source_tasks.spawn(async move {
            if let Err(e) = source.run(sink, stop).await {
                tracing::error!(source = %name, "stopped: {e}");
            }
        });
    }
    drop(events_tx);

    // Ingest, worker.
    let (pairs_tx, pairs_rx) = mpsc::channel(config.pipeline.pair_queue);
    metrics.add_queue(depth_probe("pairs", &pairs_tx));
    let tolerance_ns = (config.sync.tolerance_ms * 1e6).round().max(0.0) as u64;
    let ingest = Ingest {
        events: events_rx,
        record: record_tx.clone(),
        pairs: pairs_tx,
        sync: SharedFrameSync::new(tolerance_ns, config.sync.max_pending),
        policy: config.pipeline.overload,
        sensor,
        metrics: Arc::clone(&metrics),
        hub: Arc::clone(&hub),
        tap: tap.clone(),
    };
    let ingest_task = tokio::spawn(ingest.run());
    let (publish_tx, publish_rx) = mpsc::channel(config.pipeline.encode_queue);
    metrics.add_queue(depth_probe("encode", &publish_tx));
    let worker = Worker {
        jobs: pairs_rx,
        registration,
        record: record_tx.clone(),
        publish: publish_tx,
        metrics: Arc::clone(&metrics),
        fuse: config.pipeline.fuse,
        timestamps: restored.timestamps,
        timestamp_pages: Some(word_pages(&config, "timestamps")?),
        hanging_pages: Some(word_pages(&config, "hanging")?),
        tap,
    };
    // The level-of-detail tree, off the ingest path.
    let lod_status = Arc::new(std::sync::Mutex::new(texel::wire::LodStatus::default()));
    let lod_stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let lod = if config.model.lod.enabled {
        let inbox = LodInbox::new(config.model.lod.held_scans);
        // Scans a resumed session restored are fused first (read back from the
        // store), retired ones too: the live session's tree had fused them.
        for (id, pose) in restored.poses {
            inbox.revision(id, pose);
        }
        let stage = LodStage {
            inbox: Arc::clone(&inbox),
            hub: Arc::clone(&hub),
            scans: hub.store().cloned(),
            tiles: hub.tile_store().cloned(),
            // The fields' blocks beyond their budget, one block a page.
            field_pages: Some(file_pages(
                &config,
                "lod-fields",
                texel_lod::fields::PAGE_BYTES,
            )?),
            config: config.model.lod,
            status: Arc::clone(&lod_status),
            stop: Arc::clone(&lod_stop),
        };
        let thread = std::thread::Builder::new()
            .name("texel-lod".into())
            .spawn(move || stage.run())
            .map_err(|e| SessionError::Thread(e.to_string()))?;
        Some((inbox, thread))
    } else {
        None
    };
    let encoder = Encoder {
        lod: lod.as_ref().map(|(inbox, _)| Arc::clone(inbox)),
        rx: publish_rx,
        hub: Arc::clone(&hub),
        metrics: Arc::clone(&metrics),
        texture: config.serve.texture,
        jpeg_quality: config.serve.jpeg_quality,
        coverage: config.model.retirement,
    };
    let encode_thread = std::thread::Builder::new()
        .name("texel-encode".into())
        .spawn(move || encoder.run())
        .map_err(|e| SessionError::Thread(e.to_string()))?;
    let worker_thread = std::thread::Builder::new()
        .name("texel-worker".into())
        .spawn(move || worker.run())
        .map_err(|e| SessionError::Thread(e.to_string()))?;

    // Recorder ticks, so an idle recorder still flushes on time.
    let ticks_stop = CancellationToken::new();
    if let Some(tx) = record_tx.clone() {
        let period = Duration::from_millis((config.record.flush_interval_ms / 4).max(10));
        let stop = ticks_stop.clone();
        tokio::spawn(async move {
            let mut interval = tokio::time::interval(period);
            loop {
                tokio::select! {
                    _ = interval.tick() => { let _ = tx.try_send(RecordItem::Tick); }
                    () = stop.cancelled() => break,
                }
            }
        });
    }
    drop(record_tx);

    // Status.
    let status_stop = CancellationToken::new();
    {
        let (metrics, hub, stop) = (Arc::clone(&metrics), Arc::clone(&hub), status_stop.clone());
        let lod_status = lod.is_some().then(|| Arc::clone(&lod_status));
        let period = Duration::from_millis(config.status.interval_ms);
        let log = config.status.log;
        tokio::spawn(async move {
            let mut interval = tokio::time::interval(period);
            interval.tick().await;
            loop {
                tokio::select! {
                    _ = interval.tick() => {}
                    () = stop.cancelled() => break,
                }
                let mut status = metrics.snapshot();
                status.model = Some(hub.status());
                status.lod = lod_status.as_ref().map(|s| lock_status(s));
                if log {
                    tracing::info!("status: {}", status_line(&status));
                }
                if let Ok(frame) = Message::Status(Box::new(status)).encode() {
                    hub.publish_status(&Bytes::from(frame));
                }
            }
        });
    }

    // Server.
    let server_stop = CancellationToken::new();
    let server_task = listener.map(|listener| {
        let options = ServeOptions::from_config(&config.serve, &config.session.name);
        if let Ok(addr) = listener.local_addr() {
            tracing::info!("serving viewers on {addr}");
            if options.web {
                tracing::info!("field display: {}", server::display_url(addr));
                let dir = options.web_dir.as_deref();
                if server::web_page_missing(dir) {
                    let dir =
                        dir.map_or_else(|| "no web directory".into(), |d| d.display().to_string());
                    tracing::warn!(
                        "the browser viewer is not built: {dir} has no index.html; build it \
                         with `{}` (or set serve.web_dir)",
                        server::WEB_BUILD_COMMAND
                    );
                }
            }
        }
        tokio::spawn(server::run(
            listener,
            Arc::clone(&hub),
            options,
            Arc::clone(&metrics),
            server_stop.clone(),
        ))
    });

    // Wait for the sources to end (a replay) or the shutdown.
    let sources_ended = async { while source_tasks.join_next().await.is_some() {} };
    tokio::select! {
        () = sources_ended => {
            tracing::info!("every source has stopped");
            sources_done.cancel();
            if !config.session.exit_when_sources_end {
                shutdown.cancelled().await;
            }
        }
        () = shutdown.cancelled() => {
            // Sources watch the same token; give them a moment to stop.
            let stop = async { while source_tasks.join_next().await.is_some() {} };
            if tokio::time::timeout(Duration::from_millis(700), stop).await.is_err() {
                tracing::warn!("a source did not stop in time");
                source_tasks.abort_all();
            }
            sources_done.cancel();
        }
    }
    tracing::info!("draining the pipeline");
    let _ = ingest_task.await;
    let worker_result = tokio::task::spawn_blocking(move || worker_thread.join())
        .await
        .map_err(|e| SessionError::Thread(e.to_string()))?;
    if worker_result.is_err() {
        tracing::error!("the worker thread panicked");
    }
    // The worker's end closed the encode queue: the encoder publishes what is left.
    let encode_result = tokio::task::spawn_blocking(move || encode_thread.join())
        .await
        .map_err(|e| SessionError::Thread(e.to_string()))?;
    if encode_result.is_err() {
        tracing::error!("the encode thread panicked");
    }
    ticks_stop.cancel();
    let recording = match recorder {
        Some(r) => Some(
            tokio::task::spawn_blocking(move || r.finish())
                .await
                .map_err(|e| SessionError::Thread(e.to_string()))?,
        ),
        None => None,
    };
    if let Some(r) = &recording {
        tracing::info!(
            "recording finalised: {} ({} messages, {} errors)",
            r.path.display(),
            r.messages,
            r.errors
        );
    }
    status_stop.cancel();
    if let Some((inbox, thread)) = lod {
        lod_stop.store(true, std::sync::atomic::Ordering::Release);
        inbox.close();
        let joined = tokio::task::spawn_blocking(move || thread.join())
            .await
            .map_err(|e| SessionError::Thread(e.to_string()))?;
        if joined.is_err() {
            tracing::error!("the level-of-detail thread panicked");
        }
    }
    let mut status = metrics.snapshot();
    status.model = Some(hub.status());
    status.lod = config.model.lod.enabled.then(|| lock_status(&lod_status));
    tracing::info!("final status: {}", status_line(&status));
    hub.close("the daemon is shutting down");
    server_stop.cancel();
    if let Some(t) = server_task {
        let _ = t.await;
    }
    Ok(SessionSummary {
        scans: hub.scan_count(),
        recording,
        status,
    })
}
