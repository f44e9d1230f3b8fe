//! Resuming a session from its recording (`texeld run --resume`): the recording's
//! segments are read back, every scan that had a `/texel/pose` is fused again and
//! placed at its last recorded pose under its original id (the order of first
//! `/texel/pose` messages is the order registration gave ids), the hub gets them as
//! it got them live, and the registration stage is seeded with them without
//! registering anything again. Live frames then go on, recorded to a new segment.
//!
//! Segments: a session recording to `NAME.mcap` that is resumed records to
//! `NAME.resume-1.mcap`, then `NAME.resume-2.mcap`, ...; a resume reads them all in
//! that order. A segment cut short by a kill is read up to its last whole chunk
//! (what the recorder's flush interval promised).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use texel::capture::{CaptureError, RegisteredPoses, SensorCache, TexelItem, open_texel_frames};
use texel::model::ScanId;
use texel::{FuseConfig, Pose, SensorModel, TexelScan};

/// Why a session cannot be resumed.
#[derive(Debug, thiserror::Error)]
pub enum ResumeError {
    #[error("--resume needs the session to record (record.path): the recording is what resumes")]
    NotRecording,
    #[error("nothing to resume: {0} does not exist")]
    NoRecording(String),
    #[error("resume: {0}")]
    Capture(#[from] CaptureError),
}

/// The segments of a session's recording.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Segments {
    /// Those that exist, in recording order.
    pub existing: Vec<PathBuf>,
    /// Where the resumed session records.
    pub next: PathBuf,
}

/// The `k`-th resume segment of `base` (`NAME.mcap` -> `NAME.resume-K.mcap`).
pub fn segment_path(base: &Path, k: u32) -> PathBuf {
    let stem = base
        .file_stem()
        .map_or_else(String::new, |s| s.to_string_lossy().into_owned());
    let ext = base
        .extension()
        .map_or_else(|| "mcap".to_string(), |e| e.to_string_lossy().into_owned());
    base.with_file_name(format!("{stem}.resume-{k}.{ext}"))
}

/// Finds the segments of the recording `base`.
pub fn segments(base: &Path) -> Result<Segments, ResumeError> {
    if !base.exists() {
        return Err(ResumeError::NoRecording(base.display().to_string()));
    }
    let mut existing = vec![base.to_path_buf()];
    let mut k = 1;
    while segment_path(base, k).exists() {
        existing.push(segment_path(base, k));
        k += 1;
    }
    Ok(Segments {
        existing,
        next: segment_path(base, k),
    })
}

/// The poses a recording holds: ids by first `/texel/pose`, the registered pose of
/// each (its last `/texel/pose`, or its keyframe's composed with its `/texel/anchor`).
#[derive(Debug, Clone, Default)]
pub struct RecordedPoses {
    registered: RegisteredPoses,
    ids: HashMap<u64, ScanId>,
}

impl RecordedPoses {
    pub fn new(registered: RegisteredPoses) -> Self {
        let ids = registered
            .timestamps()
            .iter()
            .enumerate()
            .map(|(id, &t)| (t, id as ScanId))
            .collect();
        Self { registered, ids }
    }

    /// Frame timestamps in id order.
    pub fn timestamps(&self) -> &[u64] {
        self.registered.timestamps()
    }

    /// The id and current pose of the scan of frame `timestamp_ns`.
    pub fn get(&self, timestamp_ns: u64) -> Option<(ScanId, Pose)> {
        Some((
            *self.ids.get(&timestamp_ns)?,
            self.registered.get(timestamp_ns)?,
        ))
    }

    pub fn len(&self) -> usize {
        self.registered.len()
    }

    pub fn is_empty(&self) -> bool {
        self.registered.is_empty()
    }
}

/// One scan rebuilt from the recording.
pub struct RestoredScan {
    pub id: ScanId,
    pub timestamp_ns: u64,
    pub scan: Arc<TexelScan>,
    pub world_from_scan: Pose,
    pub sensor: Arc<SensorModel>,
}

/// What a restore found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RestoreSummary {
    /// Scans with a recorded pose.
    pub scans: usize,
    /// Of those, rebuilt and handed on.
    pub restored: usize,
    /// Frames recorded after the last one registered (lost by the kill, or never
    /// registered): not in the model.
    pub unposed_frames: usize,
    /// The latest frame timestamp in the recording.
    pub last_timestamp_ns: Option<u64>,
    /// Damaged stretches read around, and scans that could not be fused.
    pub problems: Vec<String>,
}

/// Reads every `/texel/pose` and `/texel/anchor` of the segments, in recording
/// order (only those topics are decoded).
pub fn read_poses(segments: &[PathBuf]) -> Result<RecordedPoses, ResumeError> {
    let mut registered = RegisteredPoses::default();
    for path in segments {
        registered.read_capture(path)?;
    }
    Ok(RecordedPoses::new(registered))
}

/// Rebuilds every scan with a recorded pose, in recording order, handing each to
/// `each` (which may stop the restore by returning false).
pub fn restore(
    segments: &[PathBuf],
    poses: &RecordedPoses,
    fuse: &FuseConfig,
    mut each: impl FnMut(RestoredScan) -> bool,
) -> Result<RestoreSummary, ResumeError> {
    let mut summary = RestoreSummary {
        scans: poses.len(),
        ..RestoreSummary::default()
    };
    let mut cache = SensorCache::new();
    for path in segments {
        for item in open_texel_frames(path)? {
            let (pair, sensor) = match item {
                Ok(TexelItem::Pair { pair, sensor }) => (pair, sensor),
                Ok(TexelItem::Pose { .. } | TexelItem::Anchor(_)) => continue,
                Err(e) if e.is_fatal() => {
                    summary.problems.push(e.to_string());
                    break;
                }
                Err(e) => {
                    summary.problems.push(e.to_string());
                    continue;
                }
            };
            let timestamp_ns = pair.timestamp_ns();
            summary.last_timestamp_ns = summary.last_timestamp_ns.max(Some(timestamp_ns));
            // A live pair may be keyed by its EO timestamp instead.
            let Some((id, world_from_scan)) = poses
                .get(timestamp_ns)
                .or_else(|| poses.get(pair.eo.timestamp_ns))
            else {
                summary.unposed_frames += 1;
                continue;
            };
            let scan = match cache.fuse(pair, &sensor, fuse) {
                Ok(scan) => Arc::new(scan),
                Err(e) => {
                    summary
                        .problems
                        .push(format!("scan {id} at {timestamp_ns} ns not fused: {e}"));
                    continue;
                }
            };
            summary.restored += 1;
            let go_on = each(RestoredScan {
                id,
                timestamp_ns,
                scan,
                world_from_scan,
                sensor,
            });
            if !go_on {
                return Ok(summary);
            }
        }
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    #[test]
    fn segments_are_numbered_beside_the_recording() {
        let dir = tempfile::tempdir().unwrap();
        let base = dir.path().join("walk.mcap");
        assert!(matches!(segments(&base), Err(ResumeError::NoRecording(_))));
        std::fs::write(&base, b"").unwrap();
        let s = segments(&base).unwrap();
        assert_eq!(s.existing, vec![base.clone()]);
        assert_eq!(s.next, dir.path().join("walk.resume-1.mcap"));
        std::fs::write(&s.next, b"").unwrap();
        let s = segments(&base).unwrap();
        assert_eq!(s.existing.len(), 2);
        assert_eq!(s.next, dir.path().join("walk.resume-2.mcap"));
    }

    #[test]
    fn ids_follow_first_poses_and_revisions_win() {
        let mut r = RegisteredPoses::default();
        let x = |v: f64| Pose::translation(v, 0.0, 0.0);
        r.insert_pose(30, x(0.0));
        r.insert_pose(10, x(1.0)); // a recovered scan: registered after 30
        r.insert_pose(20, x(2.0));
        r.insert_pose(30, x(3.0)); // a revision
        let p = RecordedPoses::new(r);
        assert_eq!(p.timestamps(), &[30, 10, 20]);
        assert_eq!(p.get(30), Some((0, x(3.0))));
        assert_eq!(p.get(10), Some((1, x(1.0))));
        assert_eq!(p.get(40), None);
    }
}
