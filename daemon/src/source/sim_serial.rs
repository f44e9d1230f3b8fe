//! The `sim-serial` source: the serial path end to end. The simulator's virtual TXL1
//! lidar (`sims::serial`) runs on a pseudo-terminal pair with the session's faults
//! injected; the `serial` source's own code ([`SerialSource`]: resynchronisation,
//! counters, stall detection, reopening with backoff) reads it through a symbolic
//! link that follows the device when it reappears under a new name. Each lidar frame
//! the serial source delivers is passed on with its true pose and the simulator's EO
//! frame of the same seq and timestamp (`sims::serial::sim_frame_for_seq`), so the
//! pipeline pairs, fuses, registers, records and serves it like any texel frame.
//!
//! The device's injection log is published as `injected_*` counters beside the serial
//! counters (and written as JSON when asked), so the status shows what was done to
//! the line next to what the reader saw. When the device has sent its last frame, the
//! source ends at the serial source's next stall: the line was read to its end.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use sims::Simulator;
use sims::serial::{
    DeviceEvent, InjectionLog, PtyDevice, VirtualLidar, VirtualLidarConfig, frame_of_seq,
    sim_frame_for_seq, spawn_pty,
};
use texel::capture::PoseTopic;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use super::serial::SerialSource;
use super::sim::build_simulator;
use super::{
    FrameSink, Source, SourceError, SourceEvent, SourceFuture, SourceMetrics, SourceState,
};
use crate::config::{LatePolicy, SimSerialConfig, SimSetup};

/// Lidar frames read from the line waiting to be passed on. The serial source waits
/// when it is full (the pseudo-terminal buffers the line meanwhile).
const LINE_QUEUE: usize = 4;
/// EO frames waiting to be rendered: fewer than `sync.max_pending` (8 by default),
/// so a lidar frame is still waiting for its partner when the EO frame comes.
const EO_QUEUE: usize = 4;
/// How often the device's events and injection log are looked at.
const DEVICE_POLL: Duration = Duration::from_millis(20);
/// The link's name in the private directory made when none is configured.
const LINK_NAME: &str = "ttyTXL1";

/// Private link directories made by this process (names stay unique).
static LINK_DIRS: AtomicU64 = AtomicU64::new(0);

/// The virtual lidar on a pseudo-terminal, read by the serial source, with the
/// simulator's EO frames.
#[derive(Debug, Clone)]
pub struct SimSerialSource {
    pub name: String,
    pub setup: SimSetup,
    /// Send each frame's `/truth/pose`.
    pub truth: bool,
    /// When EO rendering is behind the line: skip the frame's EO (the lidar frame is
    /// recorded unpaired), or make the line wait.
    pub late: LatePolicy,
    pub device: VirtualLidarConfig,
    pub baud: u32,
    pub stall_timeout: Duration,
    pub backoff_min: Duration,
    pub backoff_max: Duration,
    /// The symbolic link the serial source opens; `None`: a private one.
    pub link: Option<PathBuf>,
    /// Where the injection log is written (JSON) when the source ends.
    pub injection_log: Option<PathBuf>,
}

impl SimSerialSource {
    pub fn from_config(c: &SimSerialConfig) -> Self {
        Self {
            name: c.name.clone(),
            setup: c.setup(),
            truth: c.truth,
            late: c.late,
            device: c.device.clone(),
            baud: c.baud,
            stall_timeout: Duration::from_millis(c.stall_timeout_ms),
            backoff_min: Duration::from_millis(c.reopen_backoff_min_ms),
            backoff_max: Duration::from_millis(c.reopen_backoff_max_ms),
            link: c.link.clone(),
            injection_log: c.injection_log.clone(),
        }
    }
}

impl Source for SimSerialSource {
    fn name(&self) -> &str {
        &self.name
    }

    fn kind(&self) -> &'static str {
        "sim-serial"
    }

    fn run(self: Box<Self>, sink: FrameSink, shutdown: CancellationToken) -> SourceFuture {
        Box::pin(async move { self.run_loop(sink, shutdown).await })
    }
}

/// Why the reading loop stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Outcome {
    /// The device sent its last frame and the line was read to its end.
    Finished,
    Shutdown,
    PipelineClosed,
    /// The device's thread ended on its own (an error it returns).
    DeviceEnded,
}

/// The symbolic link the serial source opens, and the directory made for it.
struct Link {
    path: PathBuf,
    made_dir: Option<PathBuf>,
}

impl Link {
    fn prepare(configured: Option<&Path>, name: &str) -> Result<Self, String> {
        if let Some(path) = configured {
            // The device replaces the link atomically; never replace anything else.
            if let Ok(meta) = std::fs::symlink_metadata(path)
                && !meta.file_type().is_symlink()
            {
                return Err(format!(
                    "link {} exists and is not a symbolic link",
                    path.display()
                ));
            }
            return Ok(Self {
                path: path.to_path_buf(),
                made_dir: None,
            });
        }
        let tag: String = name
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
            .collect();
        let dir = std::env::temp_dir().join(format!(
            "texeld-{tag}-{}-{}",
            std::process::id(),
            LINK_DIRS.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).map_err(|e| format!("cannot make {}: {e}", dir.display()))?;
        Ok(Self {
            path: dir.join(LINK_NAME),
            made_dir: Some(dir),
        })
    }

    /// Removes the link if it still points at `target` (an unplugged device's name
    /// disappears; a reappeared one's link is left alone).
    fn remove_if_pointing_at(&self, target: &str) {
        if std::fs::read_link(&self.path).is_ok_and(|t| t == Path::new(target)) {
            let _ = std::fs::remove_file(&self.path);
        }
    }

    fn clean_up(&self) {
        let _ = std::fs::remove_file(&self.path);
        if let Some(dir) = &self.made_dir {
            let _ = std::fs::remove_dir(dir);
        }
    }
}

/// Follows the device's events: logs them, removes the link of an unplugged device,
/// and notes when the last frame has been sent.
struct DeviceWatch {
    /// The pseudo-terminal the device is on now.
    current: Option<String>,
    /// The serial source's stall count when the device finished.
    stalls_at_finish: Option<u64>,
}

impl DeviceWatch {
    fn poll(&mut self, device: &PtyDevice, link: &Link, metrics: &SourceMetrics, name: &str) {
        while let Ok(event) = device.events().try_recv() {
            match event {
                DeviceEvent::Ready { path } => {
                    tracing::info!(source = %name, device = %path, link = %link.path.display(), "virtual lidar ready");
                    self.current = Some(path);
                }
                DeviceEvent::ReaderConnected => {
                    tracing::debug!(source = %name, "virtual lidar streaming");
                }
                DeviceEvent::ReaderGone => {
                    tracing::info!(source = %name, "the reader closed the virtual lidar");
                }
                DeviceEvent::Stalling { seq, seconds } => {
                    tracing::info!(source = %name, "injected: the line stalls {seconds} s before frame {seq}");
                }
                DeviceEvent::Disconnected { seq } => {
                    tracing::info!(source = %name, "injected: the device is unplugged before frame {seq}");
                    if let Some(path) = self.current.take() {
                        link.remove_if_pointing_at(&path);
                    }
                }
                DeviceEvent::Reappeared { path } => {
                    tracing::info!(source = %name, device = %path, "injected: the device is back");
                    self.current = Some(path);
                }
                DeviceEvent::Finished => {
                    tracing::info!(source = %name, "the virtual lidar sent its last frame");
                    self.stalls_at_finish = Some(metrics.counter("stalls"));
                }
            }
        }
    }

    /// The device is done and the serial source has since found the line silent for
    /// its stall timeout: every byte sent has been read.
    fn line_drained(&self, metrics: &SourceMetrics) -> bool {
        self.stalls_at_finish
            .is_some_and(|at| metrics.counter("stalls") > at)
    }
}

/// Renders the EO frame of each seq it is given and sends it on.
struct EoRenderer {
    name: String,
    sim: Arc<Simulator>,
    /// EO frames render on their own threads: on rayon's global pool their long
    /// parallel loops would hold up the device's own range rendering, and a device
    /// held up is a line gone silent.
    pool: Arc<rayon::ThreadPool>,
    sink: FrameSink,
    shutdown: CancellationToken,
}

impl EoRenderer {
    async fn run(self, mut jobs: mpsc::Receiver<u32>) {
        let metrics = Arc::clone(self.sink.metrics());
        while let Some(seq) = jobs.recv().await {
            if self.shutdown.is_cancelled() {
                // Stopping: the lidar frames are passed on, their EO frames are not
                // worth a render each.
                metrics.add_counter("eo_skipped", 1);
                continue;
            }
            let (sim, pool) = (Arc::clone(&self.sim), Arc::clone(&self.pool));
            let rendered =
                tokio::task::spawn_blocking(move || pool.install(|| sim_frame_for_seq(&sim, seq)))
                    .await;
            let message = match rendered {
                Ok(Ok(frame)) => {
                    if self
                        .sink
                        .send(SourceEvent::Eo(Arc::new(frame.pair.eo)))
                        .await
                        .is_err()
                    {
                        return;
                    }
                    continue;
                }
                Ok(Err(e)) => format!("EO frame for seq {seq}: {e}"),
                Err(e) => format!("EO frame for seq {seq}: render thread failed: {e}"),
            };
            metrics.add_counter("eo_render_failures", 1);
            tracing::warn!(source = %self.name, "{message}");
            metrics.report_error(message);
        }
    }
}

/// Publishes what the device did as `injected_*` counters.
fn publish_injection(metrics: &SourceMetrics, log: &Mutex<InjectionLog>) {
    let Ok(log) = log.lock() else {
        return;
    };
    for (name, value) in [
        ("injected_frames_written", log.frames_written),
        ("injected_bytes_written", log.bytes_written),
        ("injected_garbage_bytes", log.garbage_bytes),
        ("injected_crc_errors", log.crc_errors),
        ("injected_dropped", log.dropped),
        ("injected_stalls", log.stalls.len() as u64),
        ("injected_disconnects", log.disconnects.len() as u64),
        ("injected_reader_disconnects", log.reader_disconnects),
    ] {
        metrics.set_counter(name, value);
    }
}

impl SimSerialSource {
    fn fatal(&self, metrics: &SourceMetrics, message: String) -> SourceError {
        metrics.set_state(SourceState::Failed);
        metrics.report_error(message.clone());
        SourceError::Fatal {
            source_name: self.name.clone(),
            message,
        }
    }

    async fn run_loop(
        self: Box<Self>,
        sink: FrameSink,
        shutdown: CancellationToken,
    ) -> Result<(), SourceError> {
        let metrics = Arc::clone(sink.metrics());
        let setup = self.setup.clone();
        let sim = match tokio::task::spawn_blocking(move || build_simulator(&setup)).await {
            Ok(Ok(sim)) => Arc::new(sim),
            Ok(Err(message)) => return Err(self.fatal(&metrics, message)),
            Err(e) => return Err(self.fatal(&metrics, format!("simulator thread failed: {e}"))),
        };
        if sink
            .send(SourceEvent::Sensor(Arc::new(sim.sensor_model().clone())))
            .await
            .is_err()
        {
            return Ok(());
        }
        // Half the cores: the device, the reader and the pipeline need the rest.
        let threads = std::thread::available_parallelism().map_or(1, |n| (n.get() / 2).max(1));
        let eo_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("sim-serial-eo-{i}"))
            .build()
            .map(Arc::new)
            .map_err(|e| self.fatal(&metrics, format!("cannot start EO render threads: {e}")))?;
        let lidar = VirtualLidar::new(Arc::clone(&sim), self.device.clone())
            .map_err(|e| self.fatal(&metrics, e.to_string()))?;
        let log = lidar.log_handle();
        let link = Link::prepare(self.link.as_deref(), &self.name)
            .map_err(|message| self.fatal(&metrics, message))?;
        let device = match spawn_pty(lidar, Some(link.path.clone())) {
            Ok(device) => device,
            Err(e) => {
                link.clean_up();
                return Err(self.fatal(&metrics, e.to_string()));
            }
        };
        tracing::info!(
            source = %self.name,
            scene = %self.setup.scene.display(),
            frames = sim.frame_count(),
            rate_hz = self.device.rate_hz.unwrap_or_else(|| sim.frame_rate_hz()),
            "virtual serial lidar started"
        );

        // The serial source, unchanged, on the link; its frames come here first.
        let (line_tx, mut line_rx) = mpsc::channel(LINE_QUEUE);
        let line_sink = FrameSink::new(0, line_tx, Arc::clone(&metrics));
        let line_stop = shutdown.child_token();
        let serial = Box::new(SerialSource {
            name: self.name.clone(),
            path: link.path.to_string_lossy().into_owned(),
            baud: self.baud,
            stall_timeout: self.stall_timeout,
            backoff_min: self.backoff_min,
            backoff_max: self.backoff_max,
        });
        let line = tokio::spawn(serial.run(line_sink, line_stop.clone()));

        // EO frames render beside the line, so rendering never holds up reading.
        let (eo_tx, eo_rx) = mpsc::channel(EO_QUEUE);
        let renderer = EoRenderer {
            name: self.name.clone(),
            sim: Arc::clone(&sim),
            pool: eo_pool,
            sink: sink.clone(),
            shutdown: shutdown.clone(),
        };
        let eo_task = tokio::spawn(renderer.run(eo_rx));

        let mut watch = DeviceWatch {
            current: None,
            stalls_at_finish: None,
        };
        let mut poll = tokio::time::interval(DEVICE_POLL);
        let outcome = loop {
            tokio::select! {
                event = line_rx.recv() => match event {
                    Some(tagged) => {
                        if !self.pass_on(tagged.event, &sim, &sink, &eo_tx).await {
                            break Outcome::PipelineClosed;
                        }
                    }
                    // The serial source stops only when told to.
                    None => break Outcome::Shutdown,
                },
                _ = poll.tick() => {
                    watch.poll(&device, &link, &metrics, &self.name);
                    publish_injection(&metrics, &log);
                    if watch.line_drained(&metrics) {
                        break Outcome::Finished;
                    }
                    if !device.is_running() {
                        break Outcome::DeviceEnded;
                    }
                }
                () = shutdown.cancelled() => break Outcome::Shutdown,
            }
        };

        // Stop reading, and pass on every frame already read (nothing received is
        // lost); at shutdown without its EO frame, which would take a render.
        line_stop.cancel();
        let mut pipeline_open = outcome != Outcome::PipelineClosed;
        while let Some(tagged) = line_rx.recv().await {
            if pipeline_open && !self.pass_on(tagged.event, &sim, &sink, &eo_tx).await {
                pipeline_open = false;
            }
        }
        if let Err(e) = line.await {
            tracing::warn!(source = %self.name, "serial reader task failed: {e}");
        }
        drop(eo_tx);
        if let Err(e) = eo_task.await {
            tracing::warn!(source = %self.name, "EO render task failed: {e}");
        }

        let stopped = tokio::task::spawn_blocking(move || device.stop()).await;
        link.clean_up();
        publish_injection(&metrics, &log);
        self.write_injection_log(&metrics, &log);
        match stopped {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => return Err(self.fatal(&metrics, e.to_string())),
            Err(e) => {
                return Err(self.fatal(&metrics, format!("virtual lidar thread failed: {e}")));
            }
        }
        if outcome == Outcome::DeviceEnded {
            return Err(self.fatal(&metrics, "the virtual lidar stopped on its own".into()));
        }
        metrics.set_state(SourceState::Ended);
        tracing::info!(source = %self.name, "sim-serial ended ({outcome:?})");
        Ok(())
    }

    /// Passes on one event of the serial source: a lidar frame with its true pose
    /// before it, and its seq to the EO renderer. False when the pipeline has stopped.
    async fn pass_on(
        &self,
        event: SourceEvent,
        sim: &Simulator,
        sink: &FrameSink,
        eo_jobs: &mpsc::Sender<u32>,
    ) -> bool {
        let SourceEvent::Range(frame) = event else {
            // The serial source yields lidar frames only.
            return sink.forward(event).await.is_ok();
        };
        let seq = frame.seq;
        let (index, timestamp_ns) = frame_of_seq(sim, seq);
        if timestamp_ns != frame.timestamp_ns {
            // Cannot happen with an intact frame of this device; the pair would not
            // form, so say why.
            sink.metrics().add_counter("timestamp_mismatches", 1);
            tracing::warn!(
                source = %self.name,
                "frame {seq} carries {} ns, the simulation says {timestamp_ns} ns",
                frame.timestamp_ns
            );
        }
        // The truth first, so the pipeline knows it when the pair forms.
        if self.truth
            && sink
                .send(SourceEvent::Pose {
                    topic: PoseTopic::Truth,
                    timestamp_ns,
                    world_from_eo: sim.true_pose(index),
                })
                .await
                .is_err()
        {
            return false;
        }
        // Counted as received by the serial source's sink already.
        if sink.forward(SourceEvent::Range(frame)).await.is_err() {
            return false;
        }
        let queued = match self.late {
            LatePolicy::Wait => eo_jobs.send(seq).await.is_ok(),
            LatePolicy::Skip => eo_jobs.try_send(seq).is_ok(),
        };
        if !queued {
            sink.metrics().add_counter("eo_skipped", 1);
        }
        true
    }

    fn write_injection_log(&self, metrics: &SourceMetrics, log: &Mutex<InjectionLog>) {
        let Some(path) = &self.injection_log else {
            return;
        };
        let copy = log.lock().map(|l| l.clone()).unwrap_or_default();
        let written = serde_json::to_vec_pretty(&copy)
            .map_err(|e| e.to_string())
            .and_then(|bytes| std::fs::write(path, bytes).map_err(|e| e.to_string()));
        if let Err(e) = written {
            let message = format!("cannot write the injection log {}: {e}", path.display());
            tracing::warn!(source = %self.name, "{message}");
            metrics.report_error(message);
        }
    }
}
