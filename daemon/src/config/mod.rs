//! Session configuration: defaults live here in code; a TOML session file
//! (`configs/sessions/*.toml`) only overrides them, unknown keys are errors naming
//! their key path, and [`SessionConfig::validate`] checks what types cannot.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use texel::FuseConfig;

use texel::wire::TextureFormat;
use texel_register::RegistrationConfig;
use thiserror::Error;

mod foxglove_section;
mod model;
#[cfg(feature = "sim")]
mod sim;
mod zenoh_section;
pub use foxglove_section::{FoxgloveSection, MAX_FOXGLOVE_CLIENT_QUEUE};
pub use model::{LodSection, ModelSection};
#[cfg(feature = "sim")]
pub use sim::{LatePolicy, SimConfig, SimSerialConfig, SimSetup};
pub use zenoh_section::{ZenohAuth, ZenohMode, ZenohSection, endpoint_is_loopback};

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read config {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("config {path}: {message}")]
    Parse { path: String, message: String },
    #[error("config {path}: {key}: {message}")]
    Invalid {
        path: String,
        key: String,
        message: String,
    },
}

/// The whole session.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionConfig {
    pub session: SessionSection,
    pub source: SourcesSection,
    pub sync: SyncSection,
    pub pipeline: PipelineSection,
    /// Overrides of the registration defaults (`texel_register::RegistrationConfig`,
    /// the same keys as `texeld register --config`).
    pub registration: RegistrationConfig,
    pub record: RecordSection,
    pub serve: ServeSection,
    pub status: StatusSection,
    /// The model over a long session: memory budget, on-disk store, retirement.
    pub model: ModelSection,
    /// Publishing the model on Zenoh.
    pub zenoh: ZenohSection,
    /// The live session offered to the Foxglove app (`foxglove_live`).
    pub foxglove: FoxgloveSection,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionSection {
    pub name: String,
    /// The sensor file (`configs/sensors/*.toml`) of a live texel camera; a replayed
    /// capture carries its own sensor model.
    pub sensor: Option<PathBuf>,
    /// Stop the daemon once every source has ended (a replay at its end); otherwise
    /// it keeps serving the model until SIGINT/SIGTERM.
    pub exit_when_sources_end: bool,
}

impl Default for SessionSection {
    fn default() -> Self {
        Self {
            name: "texel".into(),
            sensor: None,
            exit_when_sources_end: false,
        }
    }
}

/// Sources by kind; each kind is a list, so a session may have several.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SourcesSection {
    pub serial: Vec<SerialConfig>,
    pub v4l: Vec<V4lConfig>,
    pub replay: Vec<ReplayConfig>,
    /// The simulator in-process (`sims`).
    #[cfg(feature = "sim")]
    pub sim: Vec<SimConfig>,
    /// Without the `sim` feature the tables are read only to refuse them by name.
    #[cfg(not(feature = "sim"))]
    pub sim: Vec<toml::Table>,
    /// The simulator's virtual TXL1 lidar on a pseudo-terminal, read through the
    /// serial source, with the simulator's EO frames (`source::sim_serial`).
    #[cfg(feature = "sim")]
    pub sim_serial: Vec<SimSerialConfig>,
    #[cfg(not(feature = "sim"))]
    pub sim_serial: Vec<toml::Table>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SerialConfig {
    pub name: String,
    /// A device path or a glob (`/dev/ttyACM*`): the first match is opened, and on
    /// reconnection the device may come back under another matching name.
    pub path: String,
    pub baud: u32,
    pub stall_timeout_ms: u64,
    pub reopen_backoff_min_ms: u64,
    pub reopen_backoff_max_ms: u64,
}

impl Default for SerialConfig {
    fn default() -> Self {
        Self {
            name: "lidar".into(),
            path: "/dev/ttyACM*".into(),
            baud: 921_600,
            stall_timeout_ms: 1000,
            reopen_backoff_min_ms: 100,
            reopen_backoff_max_ms: 2000,
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct V4lConfig {
    pub name: String,
    pub device: PathBuf,
    /// `YUYV`, `MJPEG`, `RGB3` or `GREY`.
    pub format: String,
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    pub dequeue_timeout_ms: u64,
    pub buffers: u32,
}

impl Default for V4lConfig {
    fn default() -> Self {
        Self {
            name: "eo".into(),
            device: PathBuf::from("/dev/video0"),
            format: "YUYV".into(),
            width: 640,
            height: 480,
            fps: 30,
            dequeue_timeout_ms: 2000,
            buffers: 4,
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReplayConfig {
    pub name: String,
    pub capture: PathBuf,
    /// Times real time; ignored when `fast`.
    pub speed: f64,
    /// As fast as the pipeline takes frames.
    pub fast: bool,
}

impl Default for ReplayConfig {
    fn default() -> Self {
        Self {
            name: "replay".into(),
            capture: PathBuf::new(),
            speed: 1.0,
            fast: false,
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SyncSection {
    /// The largest timestamp difference of a lidar/EO pair, milliseconds.
    pub tolerance_ms: f64,
    /// Unpaired frames of each kind that wait for a partner.
    pub max_pending: usize,
}

impl Default for SyncSection {
    fn default() -> Self {
        Self {
            tolerance_ms: 5.0,
            max_pending: 8,
        }
    }
}

/// How scans are placed in the world.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RegistrationMode {
    /// `capture-poses` when `pipeline.pose_capture` is set; else `register` for live
    /// and simulated sessions, and for a replay `capture-poses` when the capture
    /// carries `/texel/pose` (it was registered already), else `register`.
    Auto,
    /// Register every scan against the model so far (`texel_register`).
    Register,
    /// Each scan at its capture's `/texel/pose` (else `/truth/pose`): for replaying
    /// captures that were registered already, or placing simulated ones at the truth.
    CapturePoses,
}

/// What happens when registration falls behind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OverloadPolicy {
    /// Register the newest pair when registration is free again; older pairs still
    /// waiting are skipped and counted (live use; they are recorded all the same).
    KeepNewest,
    /// Make the sources wait: every frame is registered (replays; a live serial line
    /// would overflow its kernel buffer instead).
    Backpressure,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PipelineSection {
    pub registration: RegistrationMode,
    /// Where `capture-poses` takes poses from; defaults to the first replay source's
    /// capture.
    pub pose_capture: Option<PathBuf>,
    pub overload: OverloadPolicy,
    /// Texel frames waiting for fusion and registration.
    pub pair_queue: usize,
    /// Model changes waiting for the encode stage (the worker waits when it is full).
    pub encode_queue: usize,
    /// Source events waiting for the ingest stage.
    pub ingest_queue: usize,
    pub fuse: FuseConfig,
}

impl Default for PipelineSection {
    fn default() -> Self {
        Self {
            registration: RegistrationMode::Auto,
            pose_capture: None,
            overload: OverloadPolicy::KeepNewest,
            pair_queue: 2,
            encode_queue: 8,
            ingest_queue: 64,
            fuse: FuseConfig::default(),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Compression {
    Zstd,
    Lz4,
    None,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecordSection {
    /// The capture to write; none records nothing.
    pub path: Option<PathBuf>,
    pub compression: Compression,
    /// The longest a crash can lose; the recorder checks four times as often.
    pub flush_interval_ms: u64,
    /// `fdatasync` at each flush, so power loss loses no more than a crash.
    pub sync_to_disk: bool,
    /// Records waiting for the disk.
    pub queue: usize,
    /// Resume the session this recording holds (`texeld run --resume`): rebuild the
    /// model from it and record what follows to its next segment.
    pub resume: bool,
}

impl Default for RecordSection {
    fn default() -> Self {
        Self {
            path: None,
            compression: Compression::Zstd,
            flush_interval_ms: 800,
            sync_to_disk: true,
            queue: 256,
            resume: false,
        }
    }
}

/// A slow client's fate when its queue overflows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SlowClientPolicy {
    /// Drop its queue and send it a fresh snapshot (up to `max_resyncs` in a row,
    /// then disconnect).
    Resync,
    /// Disconnect it with a message.
    Disconnect,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServeSection {
    pub enabled: bool,
    pub bind: SocketAddr,
    /// Required unless `bind` is a loopback address.
    pub token: Option<String>,
    pub max_clients: usize,
    /// Messages queued per client before it counts as slow.
    pub client_queue: usize,
    pub slow_client: SlowClientPolicy,
    pub max_resyncs: u32,
    pub texture: TextureFormat,
    pub jpeg_quality: u8,
    /// How long a connection has to deliver its hello; it holds no viewer slot
    /// meanwhile, only a pending place (below).
    pub handshake_timeout_ms: u64,
    /// Connections waiting for their hello, in all.
    pub max_pending_handshakes: usize,
    /// Connections waiting for their hello from one address (one IPv6 /64), so a
    /// flood from one address cannot take every pending place.
    pub max_pending_handshakes_per_address: usize,
    /// How long a write to a viewer may go without the socket taking a byte before
    /// the viewer is dropped as stalled.
    pub write_timeout_ms: u64,
    /// Scan requests (`RequestScan`) a viewer may have outstanding; one more and it
    /// is told so and disconnected.
    pub max_requests_in_flight: usize,
    /// Serve the browser viewer on the same port: its page over HTTP and the stream
    /// over WebSocket (`/ws`), with the same hello, token and limits as a native
    /// viewer. Off: an HTTP request is refused like any other invalid hello.
    pub web: bool,
    /// The directory of the browser viewer's files (`index.html`, its script and
    /// wasm). Unset: `$TEXEL_WEB_DIR`, else `web` in the target directory the daemon
    /// runs from (`target/web` for `target/release/texeld`), which is where
    /// `scripts/build-web.sh` puts it.
    pub web_dir: Option<PathBuf>,
}

impl Default for ServeSection {
    fn default() -> Self {
        Self {
            enabled: true,
            bind: SocketAddr::from(([127, 0, 0, 1], 7878)),
            token: None,
            max_clients: 16,
            client_queue: 256,
            slow_client: SlowClientPolicy::Resync,
            max_resyncs: 3,
            texture: TextureFormat::Jpeg,
            jpeg_quality: 90,
            // A hello is one small frame sent right after connecting: a couple of
            // round trips even on a slow link. Short, so silent connections free
            // their pending places quickly.
            handshake_timeout_ms: 2000,
            max_pending_handshakes: 64,
            max_pending_handshakes_per_address: 8,
            // Long enough for a viewer that pauses (a busy UI thread) and for a
            // frame on a slow link, which still takes bytes as it goes.
            write_timeout_ms: 10_000,
            // Four times what a client keeps outstanding by default: room for the
            // requests still in transit when a resync makes it start over.
            max_requests_in_flight: 64,
            web: true,
            web_dir: None,
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StatusSection {
    pub interval_ms: u64,
    /// Log a status line each interval.
    pub log: bool,
}

impl Default for StatusSection {
    fn default() -> Self {
        Self {
            interval_ms: 1000,
            log: true,
        }
    }
}

impl SessionConfig {
    /// Reads, parses and validates a session file. Relative paths inside it are taken
    /// relative to the directory the daemon runs in.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    /// Parses a session file's text (`origin` names it in errors). Validation is
    /// separate, so CLI overrides can be applied first.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let parse_error = |message: String| ConfigError::Parse {
            path: origin.to_string(),
            message,
        };
        let deserializer =
            toml::Deserializer::parse(text).map_err(|e| parse_error(e.to_string()))?;
        serde_path_to_error::deserialize(deserializer).map_err(|e| {
            let key = e.path().to_string();
            let inner = e.into_inner();
            // toml's message carries the line and column; the path names the key.
            let message = inner.to_string();
            if key.is_empty() || key == "." {
                parse_error(message.trim().to_string())
            } else {
                parse_error(format!("{key}: {}", message.trim()))
            }
        })
    }

    /// Checks what the types cannot.
    /// Checks the files the session names, before anything starts: replay captures,
    /// simulator scenes, the sensor file and the pose capture must be readable files,
    /// and the recording's folder must exist. The error names the key and the file.
    pub fn check_files(&self, origin: &str) -> Result<(), ConfigError> {
        let invalid = |key: String, message: String| ConfigError::Invalid {
            path: origin.to_string(),
            key,
            message,
        };
        let must_be_file = |key: String, path: &Path| -> Result<(), ConfigError> {
            match std::fs::metadata(path) {
                Ok(m) if m.is_file() => Ok(()),
                Ok(_) => Err(invalid(key, format!("{} is not a file", path.display()))),
                Err(e) => Err(invalid(key, format!("cannot read {}: {e}", path.display()))),
            }
        };
        for (i, r) in self.source.replay.iter().enumerate() {
            must_be_file(format!("source.replay[{i}].capture"), &r.capture)?;
        }
        #[cfg(feature = "sim")]
        {
            for (i, c) in self.source.sim.iter().enumerate() {
                must_be_file(format!("source.sim[{i}].scene"), &c.setup().scene)?;
            }
            for (i, c) in self.source.sim_serial.iter().enumerate() {
                must_be_file(format!("source.sim_serial[{i}].scene"), &c.setup().scene)?;
            }
        }
        if let Some(sensor) = &self.session.sensor {
            must_be_file("session.sensor".into(), sensor)?;
        }
        if let Some(poses) = &self.pipeline.pose_capture {
            must_be_file("pipeline.pose_capture".into(), poses)?;
        }
        if let Some(record) = &self.record.path {
            if record.is_dir() {
                return Err(invalid(
                    "record.path".into(),
                    format!("{} is a folder, not a capture file", record.display()),
                ));
            }
            let folder = record.parent().filter(|p| !p.as_os_str().is_empty());
            if let Some(folder) = folder
                && !folder.is_dir()
            {
                return Err(invalid(
                    "record.path".into(),
                    format!("the folder {} does not exist", folder.display()),
                ));
            }
            if self.record.resume && !record.is_file() {
                return Err(invalid(
                    "record.resume".into(),
                    format!(
                        "nothing to resume: the recording {} does not exist",
                        record.display()
                    ),
                ));
            }
        } else if self.record.resume {
            return Err(invalid(
                "record.resume".into(),
                "resuming needs the recording to resume from (record.path, or --record)".into(),
            ));
        }
        Ok(())
    }

    pub fn validate(&self, origin: &str) -> Result<(), ConfigError> {
        let invalid = |key: &str, message: String| ConfigError::Invalid {
            path: origin.to_string(),
            key: key.to_string(),
            message,
        };
        let s = &self.source;
        let live = !s.serial.is_empty() || !s.v4l.is_empty();
        let sims = s.sim.len() + s.sim_serial.len();
        if !live && s.replay.is_empty() && sims == 0 {
            return Err(invalid(
                "source",
                "no source: add [[source.serial]], [[source.v4l]], [[source.replay]], \
                 [[source.sim]] or [[source.sim_serial]]"
                    .into(),
            ));
        }
        if [live, !s.replay.is_empty(), sims > 0]
            .iter()
            .filter(|&&k| k)
            .count()
            > 1
        {
            return Err(invalid(
                "source",
                "live sources, replays and simulators cannot be mixed (their clocks differ)".into(),
            ));
        }
        #[cfg(not(feature = "sim"))]
        if sims > 0 {
            return Err(invalid(
                if s.sim.is_empty() {
                    "source.sim_serial"
                } else {
                    "source.sim"
                },
                "this texeld was built without simulated sources (the cargo feature `sim`)".into(),
            ));
        }
        if sims > 1 {
            return Err(invalid(
                "source",
                "at most one simulator per session (each has its own sensor model)".into(),
            ));
        }
        if live && self.session.sensor.is_none() {
            return Err(invalid(
                "session.sensor",
                "live sources need the texel camera's sensor file".into(),
            ));
        }
        for (i, r) in s.replay.iter().enumerate() {
            if r.capture.as_os_str().is_empty() {
                return Err(invalid(
                    &format!("source.replay[{i}].capture"),
                    "missing".into(),
                ));
            }
            if !(r.speed.is_finite() && r.speed > 0.0) {
                return Err(invalid(
                    &format!("source.replay[{i}].speed"),
                    format!("must be a positive number, got {}", r.speed),
                ));
            }
        }
        for (i, c) in s.serial.iter().enumerate() {
            if c.path.is_empty() {
                return Err(invalid(&format!("source.serial[{i}].path"), "empty".into()));
            }
            validate_line(
                &format!("source.serial[{i}]"),
                c.stall_timeout_ms,
                c.reopen_backoff_min_ms,
                c.reopen_backoff_max_ms,
            )
            .map_err(|(k, m)| invalid(&k, m))?;
        }
        #[cfg(feature = "sim")]
        sim::validate_sources(s, &invalid)?;
        for (i, c) in s.v4l.iter().enumerate() {
            if crate::source::v4l_convert::PixelFormat::from_name(&c.format).is_none() {
                return Err(invalid(
                    &format!("source.v4l[{i}].format"),
                    format!("{:?} is not one of YUYV, MJPEG, RGB3, GREY", c.format),
                ));
            }
            if c.width == 0 || c.height == 0 || c.dequeue_timeout_ms == 0 {
                return Err(invalid(
                    &format!("source.v4l[{i}]"),
                    "width, height and dequeue_timeout_ms must be positive".into(),
                ));
            }
        }
        let mut names: Vec<&str> = s
            .serial
            .iter()
            .map(|c| c.name.as_str())
            .chain(s.v4l.iter().map(|c| c.name.as_str()))
            .chain(s.replay.iter().map(|c| c.name.as_str()))
            .collect();
        // Without the feature a session naming a simulator was refused above.
        #[cfg(feature = "sim")]
        names.extend(
            s.sim
                .iter()
                .map(|c| c.name.as_str())
                .chain(s.sim_serial.iter().map(|c| c.name.as_str())),
        );
        names.sort_unstable();
        if let Some(w) = names.windows(2).find(|w| w[0] == w[1]) {
            return Err(invalid(
                "source",
                format!("two sources are named {:?}", w[0]),
            ));
        }
        if !(self.sync.tolerance_ms.is_finite() && self.sync.tolerance_ms >= 0.0) {
            return Err(invalid(
                "sync.tolerance_ms",
                format!("must be >= 0, got {}", self.sync.tolerance_ms),
            ));
        }
        self.registration
            .validate(origin)
            .map_err(|e| invalid("registration", e.to_string()))?;
        if self.pipeline.registration == RegistrationMode::CapturePoses
            && self.pipeline.pose_capture.is_none()
            && s.replay.is_empty()
        {
            return Err(invalid(
                "pipeline.registration",
                "capture-poses needs pipeline.pose_capture or a replay source".into(),
            ));
        }
        for (key, v) in [
            ("pipeline.pair_queue", self.pipeline.pair_queue),
            ("pipeline.encode_queue", self.pipeline.encode_queue),
            ("pipeline.ingest_queue", self.pipeline.ingest_queue),
            ("record.queue", self.record.queue),
            ("serve.max_clients", self.serve.max_clients),
            ("serve.client_queue", self.serve.client_queue),
            (
                "serve.max_pending_handshakes",
                self.serve.max_pending_handshakes,
            ),
            (
                "serve.max_pending_handshakes_per_address",
                self.serve.max_pending_handshakes_per_address,
            ),
        ] {
            if v == 0 {
                return Err(invalid(key, "must be at least 1".into()));
            }
        }
        if self.record.flush_interval_ms == 0 || self.record.flush_interval_ms > 1000 {
            return Err(invalid(
                "record.flush_interval_ms",
                format!(
                    "must be in 1..=1000 (a crash may lose at most a second), got {}",
                    self.record.flush_interval_ms
                ),
            ));
        }
        if self.status.interval_ms == 0 {
            return Err(invalid("status.interval_ms", "must be positive".into()));
        }
        validate_serve_limits(&self.serve).map_err(|(k, m)| invalid(k, m))?;
        self.model.validate().map_err(|(k, m)| invalid(k, m))?;
        self.foxglove.validate().map_err(|(k, m)| invalid(k, m))?;
        self.zenoh
            .validate(&self.session.name)
            .map_err(|(k, m)| invalid(k, m))?;
        if !(1..=100).contains(&self.serve.jpeg_quality) {
            return Err(invalid(
                "serve.jpeg_quality",
                format!("must be in 1..=100, got {}", self.serve.jpeg_quality),
            ));
        }
        if self.serve.enabled && !self.serve.bind.ip().is_loopback() {
            match &self.serve.token {
                None => {
                    return Err(invalid(
                        "serve.token",
                        format!(
                            "binding {} (not loopback) requires a token",
                            self.serve.bind
                        ),
                    ));
                }
                Some(t) if t.len() < 16 || t.len() > texel::wire::MAX_NAME_LEN => {
                    return Err(invalid(
                        "serve.token",
                        format!("must be 16..={} bytes long", texel::wire::MAX_NAME_LEN),
                    ));
                }
                Some(_) => {}
            }
        }
        Ok(())
    }
}

/// The longest handshake timeout: a silent connection holds its pending place this
/// long, so a larger value mostly helps a flood.
const MAX_HANDSHAKE_TIMEOUT_MS: u64 = 60_000;
/// The longest write timeout: ten minutes of a viewer reading nothing is a dead one.
const MAX_WRITE_TIMEOUT_MS: u64 = 600_000;

/// The most scan requests a viewer may keep outstanding: each costs a queue entry,
/// and a few dozen already keep a connection busy.
const MAX_REQUESTS_IN_FLIGHT: usize = 4096;

/// Checks the server's connection limits (counts of zero are refused with the other
/// queue sizes); the error names the key.
fn validate_serve_limits(serve: &ServeSection) -> Result<(), (&'static str, String)> {
    if !(1..=MAX_HANDSHAKE_TIMEOUT_MS).contains(&serve.handshake_timeout_ms) {
        return Err((
            "serve.handshake_timeout_ms",
            format!(
                "must be in 1..={MAX_HANDSHAKE_TIMEOUT_MS}, got {}",
                serve.handshake_timeout_ms
            ),
        ));
    }
    if !(1..=MAX_WRITE_TIMEOUT_MS).contains(&serve.write_timeout_ms) {
        return Err((
            "serve.write_timeout_ms",
            format!(
                "must be in 1..={MAX_WRITE_TIMEOUT_MS}, got {}",
                serve.write_timeout_ms
            ),
        ));
    }
    if !(1..=MAX_REQUESTS_IN_FLIGHT).contains(&serve.max_requests_in_flight) {
        return Err((
            "serve.max_requests_in_flight",
            format!(
                "must be in 1..={MAX_REQUESTS_IN_FLIGHT}, got {}",
                serve.max_requests_in_flight
            ),
        ));
    }
    if serve.max_pending_handshakes_per_address > serve.max_pending_handshakes {
        return Err((
            "serve.max_pending_handshakes_per_address",
            format!(
                "must not exceed serve.max_pending_handshakes ({}), got {}",
                serve.max_pending_handshakes, serve.max_pending_handshakes_per_address
            ),
        ));
    }
    Ok(())
}

/// Checks a serial line's timing settings; the error names the key.
fn validate_line(
    key: &str,
    stall_timeout_ms: u64,
    backoff_min_ms: u64,
    backoff_max_ms: u64,
) -> Result<(), (String, String)> {
    if stall_timeout_ms == 0 || backoff_min_ms == 0 {
        return Err((
            key.to_string(),
            "stall_timeout_ms and reopen_backoff_min_ms must be positive".into(),
        ));
    }
    if backoff_max_ms < backoff_min_ms {
        return Err((
            format!("{key}.reopen_backoff_max_ms"),
            "must not be below reopen_backoff_min_ms".into(),
        ));
    }
    Ok(())
}
