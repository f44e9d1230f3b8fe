//! The encode stage: a thread that turns the worker's model changes into wire frames
//! (the texture compressed once per scan) and applies them to the hub, in the order
//! the worker decided them, so scan ids reach viewers in order and a revision never
//! precedes its scan. It runs beside registration: a JPEG of a 640x480 texture costs
//! about as much as registering a scan, and the two now overlap instead of adding up.
//!
//! A frame is written straight from the shared scan (`texel::wire::WireScanRef`): the
//! mesh arrays are read in place, not copied, and not checked again (the worker
//! checked them once with `texel::wire::check_sendable`). A texture that cannot be
//! compressed is sent as raw RGB instead (which cannot fail for a scan the worker let
//! through), so one bad texture never breaks the ids of later scans.

use std::sync::Arc;
use std::time::Instant;

use bytes::Bytes;
use texel::coverage::{CoverageConfig, ScanCoverage};
use texel::model::{ScanId, ScanListing};
use texel::wire::{TextureFormat, TextureRef, WireScanRef};
use texel::{Pose, TexelScan};
use tokio::sync::mpsc;

use crate::hub::Hub;
use crate::pipeline::lod::LodInbox;
use crate::status::{Counter, Metrics, Stage};

/// One change to publish.
#[derive(Debug)]
pub enum Publish {
    Scan {
        id: ScanId,
        scan: Arc<TexelScan>,
        world_from_scan: Pose,
        /// When its range frame reached ingest (for the end-to-end latency); `None`
        /// for a scan a retry placed later.
        received: Option<Instant>,
    },
    Revision {
        id: ScanId,
        world_from_scan: Pose,
    },
}

pub struct Encoder {
    pub rx: mpsc::Receiver<Publish>,
    pub hub: Arc<Hub>,
    pub metrics: Arc<Metrics>,
    pub texture: TextureFormat,
    pub jpeg_quality: u8,
    /// How a scan's coverage is measured (its priority, and retirement's input).
    pub coverage: CoverageConfig,
    /// The level-of-detail stage's inbox, when the tree is built.
    pub lod: Option<Arc<LodInbox>>,
}

impl Encoder {
    /// Publishes until the worker closes the queue.
    pub fn run(mut self) {
        while let Some(item) = self.rx.blocking_recv() {
            match item {
                Publish::Scan {
                    id,
                    scan,
                    world_from_scan,
                    received,
                } => self.scan(id, scan, world_from_scan, received),
                Publish::Revision {
                    id,
                    world_from_scan,
                } => match self.hub.revise_pose(id, world_from_scan) {
                    Ok(()) => {
                        self.metrics.add(Counter::PoseRevisions, 1);
                        if let Some(lod) = &self.lod {
                            lod.revision(id, world_from_scan);
                        }
                    }
                    Err(e) => tracing::warn!("pose revision of scan {id} refused: {e}"),
                },
            }
        }
    }

    fn scan(
        &self,
        id: ScanId,
        scan: Arc<TexelScan>,
        world_from_scan: Pose,
        received: Option<Instant>,
    ) {
        let started = Instant::now();
        let frame = match encode_scan(id, &scan, world_from_scan, self.texture, self.jpeg_quality) {
            Ok(frame) => frame,
            Err(first) => {
                self.metrics.add(Counter::EncodeFallbacks, 1);
                tracing::warn!("scan {id}: {first}; sent with a raw RGB texture instead");
                match encode_scan(id, &scan, world_from_scan, TextureFormat::Rgb8, 0) {
                    Ok(frame) => frame,
                    Err(e) => {
                        // Only a non-finite pose gets here (the worker checked the rest);
                        // the model keeps the id so later scans keep theirs.
                        self.metrics.add(Counter::EncodeFailures, 1);
                        tracing::error!("scan {id} cannot be streamed: {e}");
                        Bytes::new()
                    }
                }
            }
        };
        // What the scan shows, reliability-weighted: its priority for newcomers, and
        // what retirement tests it by.
        let coverage = ScanCoverage::of(&scan, &self.coverage);
        let listing = ScanListing::of_scan(&scan, frame.len() as u64, coverage.score() as f32);
        // Into the store first, so the hub may drop it from memory at any time.
        let stored = match self.hub.store() {
            Some(store) => match store.append(id, &frame) {
                Ok(()) => true,
                Err(e) => {
                    self.metrics.add(Counter::StoreErrors, 1);
                    tracing::error!("scan {id} kept in memory only: {e}");
                    false
                }
            },
            None => false,
        };
        // The tree fuses every scan, retired ones too: a redundant scan still
        // averages the surface down, and it costs the tree nothing to keep. Handed
        // over once stored: a scan the tree does not hold is read back from there.
        if let Some(lod) = &self.lod {
            lod.scan(id, &scan, world_from_scan);
        }
        // Version 4 clients are told how the frame was exposed, before its data.
        if let Some(exposure) = scan.texture.exposure
            && let Err(e) = self.hub.note_exposure(id, &exposure)
        {
            tracing::error!("scan {id}: its exposure cannot be served: {e}");
        }
        drop(scan);
        self.metrics
            .record_latency(Stage::Encode, started.elapsed());
        let coverage = self.hub.retires().then_some(coverage);
        if let Err(e) = self
            .hub
            .add_scan(id, listing, world_from_scan, frame, stored, coverage)
        {
            tracing::debug!("scan {id} not added: {e}");
            return;
        }
        self.metrics.add(Counter::Scans, 1);
        if let Some(received) = received {
            self.metrics
                .record_latency(Stage::EndToEnd, received.elapsed());
        }
    }
}

/// The `ScanAdded` frame of a scan that passed `texel::wire::check_sendable`, its
/// texture in `format`. Raw RGB is read from the scan's own pixels; a compressed
/// texture is made once and borrowed.
pub fn encode_scan(
    id: ScanId,
    scan: &TexelScan,
    world_from_scan: Pose,
    format: TextureFormat,
    jpeg_quality: u8,
) -> Result<Bytes, String> {
    let compressed;
    let texture = match format {
        TextureFormat::Rgb8 => TextureRef::rgb8(&scan.texture).map_err(|e| e.to_string())?,
        TextureFormat::Png | TextureFormat::Jpeg => {
            compressed = crate::texture::encode(&scan.texture, format, jpeg_quality)
                .map_err(|e| e.to_string())?;
            compressed.view()
        }
    };
    let frame = WireScanRef::new(id, scan, world_from_scan, texture)
        .and_then(|view| view.encode())
        .map_err(|e| e.to_string())?;
    // Sized exactly, so the shared bytes hold no spare capacity.
    Ok(Bytes::from(frame))
}
