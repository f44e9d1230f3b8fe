//! The simulated sources' settings (`[[source.sim]]`, `[[source.sim_serial]]`) and
//! their checks; built only with the cargo feature `sim`, which brings in `sims`.

use std::path::PathBuf;

use serde::Deserialize;

use super::{ConfigError, SerialConfig, SourcesSection, validate_line};

/// What a simulator renders: a scene and overrides of its settings.
#[derive(Debug, Clone, PartialEq)]
pub struct SimSetup {
    pub scene: PathBuf,
    pub seed: u64,
    pub effects: Option<Vec<String>>,
    pub frames: Option<usize>,
    pub lidar_size: Option<[u32; 2]>,
    pub eo_size: Option<[u32; 2]>,
}

/// When a simulated frame is not rendered by the time it is due.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LatePolicy {
    /// A frame still unrendered when the next one is due is skipped (counted
    /// `late_skipped`), and rendering moves on to the frame due now: the source keeps
    /// the trajectory's clock, like a camera that drops frames.
    Skip,
    /// Every frame is sent, late if need be (`late_frames` counts those sent more than
    /// one frame period after they were due).
    Wait,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimConfig {
    pub name: String,
    /// A scene file (`configs/scenes/*.toml`).
    pub scene: PathBuf,
    /// Seed of the simulator's random numbers.
    pub seed: u64,
    /// Replaces the scene's effect list (names; `[]` = none).
    pub effects: Option<Vec<String>>,
    /// Number of frames (default: the trajectory's).
    pub frames: Option<usize>,
    /// Lidar and EO resolution `[width, height]` (intrinsics scale with them).
    pub lidar_size: Option<[u32; 2]>,
    pub eo_size: Option<[u32; 2]>,
    /// Times the trajectory's frame rate; ignored when `fast`.
    pub speed: f64,
    /// As fast as frames render and the pipeline takes them.
    pub fast: bool,
    /// Render every frame before the first is sent, then send them at the pace (the
    /// daemon's latency without the simulator's rendering time in it).
    pub prerender: bool,
    /// Threads rendering frames ahead of their time (0 = one per core).
    pub render_threads: usize,
    pub late: LatePolicy,
    /// Send each frame's `/truth/pose` (recorded, and the world anchor).
    pub truth: bool,
    /// Times the trajectory is walked; later walks resend the first walk's renders
    /// with later timestamps (long sessions at the cost of one walk's rendering).
    pub loops: u32,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            name: "sim".into(),
            scene: PathBuf::new(),
            seed: 1,
            effects: None,
            frames: None,
            lidar_size: None,
            eo_size: None,
            speed: 1.0,
            fast: false,
            prerender: false,
            render_threads: 0,
            late: LatePolicy::Skip,
            truth: true,
            loops: 1,
        }
    }
}

impl SimConfig {
    pub fn setup(&self) -> SimSetup {
        SimSetup {
            scene: self.scene.clone(),
            seed: self.seed,
            effects: self.effects.clone(),
            frames: self.frames,
            lidar_size: self.lidar_size,
            eo_size: self.eo_size,
        }
    }
}

/// The serial path end to end: the simulator's virtual TXL1 device
/// (`sims::serial::VirtualLidar`) on a pseudo-terminal pair, read by the `serial`
/// source's own code, each lidar frame paired with the simulator's EO frame.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimSerialConfig {
    pub name: String,
    /// A scene file (`configs/scenes/*.toml`).
    pub scene: PathBuf,
    /// Seed of the simulator's random numbers.
    pub seed: u64,
    /// Replaces the scene's effect list (names; `[]` = none).
    pub effects: Option<Vec<String>>,
    /// Number of frames of the trajectory (default: the scene's).
    pub frames: Option<usize>,
    /// Lidar and EO resolution `[width, height]` (intrinsics scale with them).
    pub lidar_size: Option<[u32; 2]>,
    pub eo_size: Option<[u32; 2]>,
    /// Send each frame's `/truth/pose` (recorded, and the world anchor).
    pub truth: bool,
    /// When EO rendering falls behind the line: `skip` the frame's EO frame (counted
    /// `eo_skipped`; the lidar frame is recorded unpaired) or `wait` (the serial
    /// source waits, the pseudo-terminal buffers the line, the device waits).
    pub late: LatePolicy,
    /// The serial source's settings, as in `[[source.serial]]`.
    pub baud: u32,
    pub stall_timeout_ms: u64,
    pub reopen_backoff_min_ms: u64,
    pub reopen_backoff_max_ms: u64,
    /// A symbolic link kept pointing at the device's current pseudo-terminal, which the
    /// serial source opens (default: one in a private directory under the system's
    /// temporary directory).
    pub link: Option<PathBuf>,
    /// Write the device's injection log (`sims::serial::InjectionLog`, JSON) here when
    /// the source ends.
    pub injection_log: Option<PathBuf>,
    /// The virtual device: `rate_hz`, `range_unit_um`, `loop_trajectory`,
    /// `max_frames` and the `[faults]` table (`sims::serial::VirtualLidarConfig`).
    pub device: sims::serial::VirtualLidarConfig,
}

impl Default for SimSerialConfig {
    fn default() -> Self {
        let serial = SerialConfig::default();
        Self {
            name: "sim-serial".into(),
            scene: PathBuf::new(),
            seed: 1,
            effects: None,
            frames: None,
            lidar_size: None,
            eo_size: None,
            truth: true,
            late: LatePolicy::Skip,
            baud: serial.baud,
            stall_timeout_ms: serial.stall_timeout_ms,
            reopen_backoff_min_ms: serial.reopen_backoff_min_ms,
            reopen_backoff_max_ms: serial.reopen_backoff_max_ms,
            link: None,
            injection_log: None,
            device: sims::serial::VirtualLidarConfig::default(),
        }
    }
}

impl SimSerialConfig {
    pub fn setup(&self) -> SimSetup {
        SimSetup {
            scene: self.scene.clone(),
            seed: self.seed,
            effects: self.effects.clone(),
            frames: self.frames,
            lidar_size: self.lidar_size,
            eo_size: self.eo_size,
        }
    }
}

/// Checks the simulated sources of `s`; `invalid` builds the error for a key.
pub(super) fn validate_sources(
    s: &SourcesSection,
    invalid: &dyn Fn(&str, String) -> ConfigError,
) -> Result<(), ConfigError> {
    for (i, c) in s.sim.iter().enumerate() {
        let key = format!("source.sim[{i}]");
        validate_sim(&c.setup(), &key).map_err(|(k, m)| invalid(&k, m))?;
        if !(c.speed.is_finite() && c.speed > 0.0) {
            return Err(invalid(
                &format!("{key}.speed"),
                format!("must be a positive number, got {}", c.speed),
            ));
        }
        if c.render_threads > 64 {
            return Err(invalid(
                &format!("{key}.render_threads"),
                format!("must be at most 64, got {}", c.render_threads),
            ));
        }
        if !(1..=1_000_000).contains(&c.loops) {
            return Err(invalid(
                &format!("{key}.loops"),
                format!("must be in 1..=1000000, got {}", c.loops),
            ));
        }
    }
    for (i, c) in s.sim_serial.iter().enumerate() {
        let key = format!("source.sim_serial[{i}]");
        validate_sim(&c.setup(), &key).map_err(|(k, m)| invalid(&k, m))?;
        validate_line(
            &key,
            c.stall_timeout_ms,
            c.reopen_backoff_min_ms,
            c.reopen_backoff_max_ms,
        )
        .map_err(|(k, m)| invalid(&k, m))?;
        c.device
            .validate()
            .map_err(|e| invalid(&format!("{key}.device"), e.to_string()))?;
        if let Some([w, h]) = c.lidar_size
            && (w > u32::from(texel::txl1::MAX_SIDE) || h > u32::from(texel::txl1::MAX_SIDE))
        {
            return Err(invalid(
                &format!("{key}.lidar_size"),
                format!(
                    "{w}x{h} does not fit a TXL1 frame (at most {} per side)",
                    texel::txl1::MAX_SIDE
                ),
            ));
        }
    }
    Ok(())
}

/// Checks a simulator's settings (without loading the scene); the error names the key.
fn validate_sim(setup: &SimSetup, key: &str) -> Result<(), (String, String)> {
    if setup.scene.as_os_str().is_empty() {
        return Err((format!("{key}.scene"), "missing".into()));
    }
    if let Some(names) = &setup.effects {
        for name in names {
            if let Err(e) = sims::Effect::from_name_and_params(name, toml::Table::new()) {
                return Err((format!("{key}.effects"), e));
            }
        }
    }
    if setup.frames == Some(0) {
        return Err((format!("{key}.frames"), "must be at least 1".into()));
    }
    for (name, size) in [("lidar_size", setup.lidar_size), ("eo_size", setup.eo_size)] {
        if let Some([w, h]) = size
            && (w == 0 || h == 0)
        {
            return Err((format!("{key}.{name}"), format!("{w}x{h} is empty")));
        }
    }
    Ok(())
}
