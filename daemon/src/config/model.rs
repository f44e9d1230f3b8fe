//! The `[model]` section: how the daemon keeps its model over a session of any
//! length (a memory budget, the on-disk store beyond it, retirement of redundant
//! scans). Defaults suit a small laptop.

use std::path::{Path, PathBuf};

use serde::Deserialize;
use texel::coverage::CoverageConfig;
use texel_lod::LodConfig;

/// The largest budget accepted (1 TiB): a typo, not a machine.
const MAX_BUDGET_MB: u64 = 1 << 20;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelSection {
    /// Encoded scans held in memory beyond this are dropped to the on-disk store,
    /// least recently requested first, and read back when asked for.
    pub memory_budget_mb: u64,
    /// Where the on-disk store is written. Default: beside the recording
    /// (`NAME.scans` for `NAME.mcap`), or a temporary file removed at exit when the
    /// session records nothing.
    pub store_path: Option<PathBuf>,
    /// Retirement of redundant scans (`docs/model.md`).
    pub retirement: CoverageConfig,
    /// The level-of-detail tree built in the background (`docs/lod.md`).
    pub lod: LodSection,
}

/// The `[model.lod]` section.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LodSection {
    /// Build the tree and serve its tiles (protocol version 3).
    pub enabled: bool,
    /// The tree's own knobs (`[model.lod.tree]`, the keys of `texeld export
    /// --lod-config`).
    pub tree: LodConfig,
    /// A pose revision moves a scan's tiles only when some point of the scan moves
    /// at least this far (metres); smaller ones would not change a tile.
    pub revise_threshold_m: f64,
    /// Scans fused between two rounds of rebuilding.
    pub scans_per_round: usize,
    /// Tiles rebuilt per round (coarsest first).
    pub tiles_per_round: usize,
    /// New scans the stage keeps in memory while it lags; beyond that it reads them
    /// back from the store when their turn comes (so lagging costs no memory).
    pub held_scans: usize,
    /// Tile data held in memory; beyond it tiles are read back from the tile store.
    pub tile_memory_budget_mb: u64,
}

impl Default for LodSection {
    fn default() -> Self {
        Self {
            enabled: true,
            tree: LodConfig::default(),
            revise_threshold_m: 0.05,
            scans_per_round: 4,
            tiles_per_round: 2,
            held_scans: 8,
            tile_memory_budget_mb: 256,
        }
    }
}

impl LodSection {
    /// The tile budget in bytes.
    pub fn tile_memory_budget_bytes(&self) -> u64 {
        self.tile_memory_budget_mb.saturating_mul(1024 * 1024)
    }

    fn validate(&self) -> Result<(), (&'static str, String)> {
        self.tree
            .validate()
            .map_err(|e| ("model.lod.tree", e.to_string()))?;
        if self.revise_threshold_m.is_nan()
            || self.revise_threshold_m < 0.0
            || !self.revise_threshold_m.is_finite()
        {
            return Err((
                "model.lod.revise_threshold_m",
                format!("must be finite and >= 0, got {}", self.revise_threshold_m),
            ));
        }
        for (key, v) in [
            ("model.lod.scans_per_round", self.scans_per_round),
            ("model.lod.tiles_per_round", self.tiles_per_round),
        ] {
            if !(1..=1024).contains(&v) {
                return Err((key, format!("must be in 1..=1024, got {v}")));
            }
        }
        if self.held_scans > 1024 {
            return Err((
                "model.lod.held_scans",
                format!("must be at most 1024, got {}", self.held_scans),
            ));
        }
        if !(1..=MAX_BUDGET_MB).contains(&self.tile_memory_budget_mb) {
            return Err((
                "model.lod.tile_memory_budget_mb",
                format!(
                    "must be in 1..={MAX_BUDGET_MB}, got {}",
                    self.tile_memory_budget_mb
                ),
            ));
        }
        Ok(())
    }
}

impl Default for ModelSection {
    fn default() -> Self {
        Self {
            memory_budget_mb: 1024,
            store_path: None,
            retirement: CoverageConfig::default(),
            lod: LodSection::default(),
        }
    }
}

impl ModelSection {
    /// The budget in bytes.
    pub fn memory_budget_bytes(&self) -> u64 {
        self.memory_budget_mb.saturating_mul(1024 * 1024)
    }

    /// The store's path for a session recording to `recording` (if it records), or
    /// `None` for a temporary store.
    pub fn store_path_for(&self, recording: Option<&Path>) -> Option<PathBuf> {
        self.store_path
            .clone()
            .or_else(|| recording.map(|r| r.with_extension("scans")))
    }

    /// Checks what types cannot; the error names the key.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if !(1..=MAX_BUDGET_MB).contains(&self.memory_budget_mb) {
            return Err((
                "model.memory_budget_mb",
                format!(
                    "must be in 1..={MAX_BUDGET_MB}, got {}",
                    self.memory_budget_mb
                ),
            ));
        }
        self.lod.validate()
    }
}
