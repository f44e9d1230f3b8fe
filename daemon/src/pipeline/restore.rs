//! A resumed session's first step: the scans its recording holds go through the
//! encode stage into the hub under their original ids and poses, and seed the
//! registration stage, before any source starts (`crate::resume` reads them).

use std::path::PathBuf;
use std::sync::Arc;

use texel::Pose;
use texel::model::ScanId;
use tokio::sync::mpsc;

use super::SessionError;
use super::encode::{Encoder, Publish};
use super::placement::{Registration, ScanInput};
use crate::config::SessionConfig;
use crate::hub::Hub;
use crate::resume;
use crate::status::Metrics;

/// What a restore leaves for the live session.
#[derive(Debug, Default)]
pub struct Restored {
    /// Frame timestamps of the restored scans by id (the worker records revisions
    /// by them).
    pub timestamps: Vec<u64>,
    /// The latest frame in the recording: simulators go on after it.
    pub last_timestamp_ns: Option<u64>,
    /// Every restored scan's id and pose, retired ones too: the level-of-detail
    /// tree fuses them all, as the live session's tree had.
    pub poses: Vec<(ScanId, Pose)>,
}

/// Rebuilds the model from `segments` into `hub` and seeds `registration`; returns
/// the stage back with what the live session needs.
pub async fn restore_session(
    segments: Vec<PathBuf>,
    config: &SessionConfig,
    mut registration: Box<dyn Registration>,
    hub: Arc<Hub>,
    metrics: Arc<Metrics>,
) -> Result<(Box<dyn Registration>, Restored), SessionError> {
    let (tx, rx) = mpsc::channel(config.pipeline.encode_queue.max(1));
    let encoder = Encoder {
        rx,
        hub,
        metrics,
        texture: config.serve.texture,
        jpeg_quality: config.serve.jpeg_quality,
        coverage: config.model.retirement,
        // The session's tree fuses the restored scans once it starts (from the store).
        lod: None,
    };
    let fuse = config.pipeline.fuse;
    let encode_thread = std::thread::Builder::new()
        .name("texel-restore-encode".into())
        .spawn(move || encoder.run())
        .map_err(|e| SessionError::Thread(e.to_string()))?;
    let work = tokio::task::spawn_blocking(move || {
        let mut placed = Vec::new();
        // 1. Which scans the recording placed, under which ids, where now.
        let poses = resume::read_poses(&segments)?;
        tracing::info!(
            segments = segments.len(),
            scans = poses.len(),
            "resuming: rebuilding the model from the recording"
        );
        // 2. Each scan again, into the hub (through the encoder) and the stage.
        let summary = resume::restore(&segments, &poses, &fuse, |r| {
            registration.restore(
                &r.scan,
                ScanInput {
                    timestamp_ns: r.timestamp_ns,
                    sensor: &r.sensor,
                    truth: None,
                },
                r.id,
                r.world_from_scan,
            );
            placed.push((r.id, r.world_from_scan));
            tx.blocking_send(Publish::Scan {
                id: r.id,
                scan: r.scan,
                world_from_scan: r.world_from_scan,
                received: None,
            })
            .is_ok()
        })?;
        drop(tx);
        Ok::<_, SessionError>((registration, poses.timestamps().to_vec(), summary, placed))
    });
    let result = work
        .await
        .map_err(|e| SessionError::Thread(e.to_string()))?;
    encode_thread
        .join()
        .map_err(|_| SessionError::Thread("the restore's encode thread panicked".into()))?;
    let (registration, timestamps, summary, placed) = result?;
    for problem in &summary.problems {
        tracing::warn!("resume: {problem}");
    }
    tracing::info!(
        restored = summary.restored,
        of = summary.scans,
        unposed_frames = summary.unposed_frames,
        "resumed"
    );
    Ok((
        registration,
        Restored {
            timestamps,
            last_timestamp_ns: summary.last_timestamp_ns,
            poses: placed,
        },
    ))
}
