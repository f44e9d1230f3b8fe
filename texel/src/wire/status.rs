//! The daemon's status as it travels in a `Status` message (JSON inside the frame, so
//! fields can be added without a protocol version change; unknown fields are
//! ignored, missing ones default).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// One source's health.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SourceStatus {
    pub name: String,
    /// `serial`, `v4l`, `replay`, ...
    pub kind: String,
    /// `starting`, `running`, `reopening`, `ended`, `failed`.
    pub state: String,
    /// Frames per second over the last status interval.
    pub range_fps: f64,
    pub eo_fps: f64,
    /// Source-specific counters (`bytes_skipped`, `crc_errors`, `lost_frames`, ...).
    pub counters: BTreeMap<String, u64>,
    pub last_error: Option<String>,
}

/// Latency of one pipeline stage over a recent window.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct StageLatency {
    pub stage: String,
    pub samples: u64,
    pub p50_ms: f64,
    pub p99_ms: f64,
}

/// A bounded queue's fill.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct QueueStatus {
    pub name: String,
    pub depth: u64,
    pub capacity: u64,
}

/// The recording's progress.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RecordingStatus {
    pub path: String,
    pub bytes: u64,
    pub messages: u64,
    /// Writes that failed (a full disk, say); the first is logged.
    pub errors: u64,
}

/// The served model: how many scans it has, where they live, what they cost.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ModelStatus {
    /// Every scan registered this session (ids `0..scans`).
    pub scans: u64,
    /// Scans in the served model (not retired).
    pub served: u64,
    /// Scans retired as redundant (kept in the recording and the store).
    pub retired: u64,
    /// Served scans whose encoded frames are in memory.
    pub in_memory: u64,
    /// Scans whose encoded frames live only in the on-disk store.
    pub on_disk: u64,
    /// Bytes the model holds in memory (encoded frames, coverage signatures, index).
    pub memory_bytes: u64,
    /// `model.memory_budget_mb` in bytes.
    pub memory_budget_bytes: u64,
    /// Bytes written to the on-disk store.
    pub store_bytes: u64,
    /// Scans read back from the store (viewer requests, late joiners).
    pub store_reads: u64,
    /// Store reads that failed (a damaged entry); the first is logged.
    pub store_errors: u64,
}

/// Everything the periodic status reports.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Status {
    pub uptime_s: f64,
    pub sources: Vec<SourceStatus>,
    pub stages: Vec<StageLatency>,
    pub queues: Vec<QueueStatus>,
    /// Pipeline counters: `paired`, `unpaired_range`, `unpaired_eo`, `late_range`,
    /// `late_eo`, `fuse_failures`, `registration_failures`,
    /// `registration_degenerate`, `skipped_by_overload`, `scans`, `pose_revisions`.
    pub counters: BTreeMap<String, u64>,
    pub recording: Option<RecordingStatus>,
    pub clients: u64,
    /// The served model (absent from daemons that predate it).
    pub model: Option<ModelStatus>,
    /// The level-of-detail tree (absent when the daemon builds none).
    pub lod: Option<LodStatus>,
}

/// The level-of-detail tree the daemon builds in the background: its size, how far
/// it lags behind the scans, what its tiles cost on the wire.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LodStatus {
    /// Tiles served (holding surface, up to the top of the tree).
    pub tiles: u64,
    /// The top level of the tree (0: the finest).
    pub top_lod: u64,
    /// Scans waiting to be fused (new ones, and pose revisions past the threshold).
    pub pending_scans: u64,
    /// Tiles waiting to be rebuilt.
    pub pending_tiles: u64,
    /// Seconds since the oldest scan not yet reflected in the served tiles arrived
    /// (0 when the tree is up to date).
    pub lag_s: f64,
    /// Scans fused so far, revisions applied (a scan moved out and in again), and
    /// revisions under the threshold (too small to change a tile).
    pub scans_fused: u64,
    pub revisions_applied: u64,
    pub revisions_skipped: u64,
    /// Tiles rebuilt so far.
    pub rebuilds: u64,
    /// Bytes of a tile's data on the wire (`TileData` frame): the mean over the
    /// served tiles, and the largest.
    pub mean_tile_bytes: f64,
    pub largest_tile_bytes: u64,
    /// Tile data held in memory, and the fields the tree is merged from.
    pub tile_memory_bytes: u64,
    pub field_bytes: u64,
    /// The fields' blocks beyond their memory budget, in the daemon's page file, and
    /// page writes or reads that failed (a block that could not be written stays in
    /// memory; one that could not be read back is observed anew by later scans).
    pub field_paged_bytes: u64,
    pub field_page_errors: u64,
    /// Tile data frames sent to viewers, and their bytes.
    pub tiles_sent: u64,
    pub tile_bytes_sent: u64,
    /// Scans the stage could not read back (a damaged store entry); the first is
    /// logged.
    pub read_errors: u64,
}
