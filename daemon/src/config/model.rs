//! The `[model]` section: how the daemon keeps its model over a session of any
//! length (a memory budget, the on-disk store beyond it, retirement of redundant
//! scans). Defaults suit a small laptop.

use std::path::{Path, PathBuf};

use serde::Deserialize;
use texel::coverage::CoverageConfig;

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
}

impl Default for ModelSection {
    fn default() -> Self {
        Self {
            memory_budget_mb: 1024,
            store_path: None,
            retirement: CoverageConfig::default(),
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
        Ok(())
    }
}
