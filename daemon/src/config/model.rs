//! The `[model]` section: how the daemon keeps its model over a session of any
//! length (a memory budget, the on-disk store beyond it, retirement of redundant
//! scans). Defaults suit a small laptop.

use std::path::{Path, PathBuf};
use std::time::Duration;

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
    /// A tile above the finest level is rebuilt at most once in this many seconds,
    /// doubled per level above the first: scans keep changing the coarse tiles, which
    /// far views need seldom anew, and their atlases make them the dearest to build.
    pub coarse_rebuild_interval_s: f64,
    /// New scans the stage keeps in memory while it lags; beyond that it reads them
    /// back from the store when their turn comes (so lagging costs no memory).
    pub held_scans: usize,
    /// Tile data held in memory; beyond it tiles are read back from the tile store.
    pub tile_memory_budget_mb: u64,
    /// The fields the tiles are cut from, held in memory; beyond it their blocks
    /// used longest ago wait in an unlinked file beside the store (0 holds only
    /// what one fusion or rebuild needs at once).
    pub field_memory_budget_mb: u64,
}

impl Default for LodSection {
    fn default() -> Self {
        Self {
            enabled: true,
            tree: LodConfig::default(),
            revise_threshold_m: 0.05,
            scans_per_round: 4,
            tiles_per_round: 2,
            coarse_rebuild_interval_s: 1.0,
            held_scans: 8,
            tile_memory_budget_mb: 256,
            field_memory_budget_mb: 256,
        }
    }
}

impl LodSection {
    /// The least time between two rebuilds of a tile of level `lod`.
    pub fn coarse_interval(&self, lod: u8) -> Duration {
        if lod == 0 {
            return Duration::ZERO;
        }
        let seconds = self.coarse_rebuild_interval_s * 2f64.powi(i32::from(lod) - 1);
        // A very coarse level waits at most an hour (and a bad value no time at all:
        // the config is validated, this only keeps the conversion from panicking).
        if seconds.is_finite() {
            Duration::from_secs_f64(seconds.clamp(0.0, 3600.0))
        } else {
            Duration::ZERO
        }
    }

    /// The tile budget in bytes.
    pub fn tile_memory_budget_bytes(&self) -> u64 {
        self.tile_memory_budget_mb.saturating_mul(1024 * 1024)
    }

    /// The field budget in bytes.
    pub fn field_memory_budget_bytes(&self) -> usize {
        usize::try_from(self.field_memory_budget_mb.saturating_mul(1024 * 1024))
            .unwrap_or(usize::MAX)
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
        if !(0.0..=3600.0).contains(&self.coarse_rebuild_interval_s) {
            return Err((
                "model.lod.coarse_rebuild_interval_s",
                format!(
                    "must be in 0..=3600 seconds, got {}",
                    self.coarse_rebuild_interval_s
                ),
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
        if self.field_memory_budget_mb > MAX_BUDGET_MB {
            return Err((
                "model.lod.field_memory_budget_mb",
                format!(
                    "must be in 0..={MAX_BUDGET_MB}, got {}",
                    self.field_memory_budget_mb
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coarse_tiles_wait_longer_the_coarser_they_are() {
        let lod = LodSection::default();
        assert_eq!(lod.coarse_interval(0), Duration::ZERO);
        assert_eq!(lod.coarse_interval(1), Duration::from_secs(1));
        assert_eq!(lod.coarse_interval(3), Duration::from_secs(4));
        // However coarse, at most an hour.
        assert_eq!(lod.coarse_interval(30), Duration::from_secs(3600));
        for bad in [-1.0, f64::NAN, f64::INFINITY, 4000.0] {
            let section = LodSection {
                coarse_rebuild_interval_s: bad,
                ..LodSection::default()
            };
            let err = section.validate().err();
            assert_eq!(
                err.map(|e| e.0),
                Some("model.lod.coarse_rebuild_interval_s"),
                "{bad}"
            );
        }
    }
}
