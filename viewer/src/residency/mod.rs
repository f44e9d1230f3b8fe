//! Residency: what of the model the viewer holds within a GPU byte budget. The pure
//! planner ([`plan`]) chooses; [`Residency`] carries its choice out on a model and a
//! renderer: it evicts (GPU data dropped, `ScanEvicted` applied so the CPU copy goes
//! too), uploads what is here, and fetches what is missing, from a local store (a
//! capture, a replay) or by asking a live source (`RequestScan`).

pub mod plan;

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use std::sync::mpsc::{SyncSender, TrySendError};
// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::{Duration, Instant};

use texel::TexelScan;
use texel::model::{Model, ModelEvent, ScanId, ScanListing};

pub use plan::{DataState, Plan, PlanOptions, PlanScan, plan};

use crate::camera::VirtualCamera;
use crate::gpu::{GpuError, Renderer, scan_gpu_bytes};
use crate::live::SourceCommand;

/// The default budget (`--gpu-budget-mb`).
pub const DEFAULT_BUDGET_MB: u64 = 512;

/// GPU bytes per wire byte assumed until a fetched scan gives the real ratio: the
/// wire carries the texture compressed and 25 bytes per vertex, the GPU holds the
/// texture as RGBA8 and 28 bytes per vertex plus two index lists.
pub const DEFAULT_GPU_PER_WIRE_BYTE: f64 = 4.0;

/// The size assumed for a scan whose listing gives no encoded size, until a scan's
/// data was seen: a 640x480 texture and a 160x120 mesh.
pub const DEFAULT_SCAN_BYTES: u64 = 2 << 20;

/// A request without an answer after this long may be made again.
const REQUEST_EXPIRY: Duration = Duration::from_secs(15);

/// Where missing scan data comes from.
pub enum Fetcher {
    /// Every scan's data stays in a CPU store (a loaded capture, a replay): a fetch
    /// is an upload from it. Only the GPU is budgeted.
    Local {
        store: BTreeMap<ScanId, Arc<TexelScan>>,
    },
    /// A live source: fetches are requests on the connection's command channel; the
    /// data comes back as a `ScanAdded` event.
    Remote { commands: SyncSender<SourceCommand> },
}

/// Estimates a scan's GPU bytes from its listing before its data is here: its wire
/// size times the ratio of GPU bytes to wire bytes over the scans seen so far
/// (`DEFAULT_GPU_PER_WIRE_BYTE` before any); without a wire size, the mean GPU size
/// of the scans seen (`DEFAULT_SCAN_BYTES` before any).
#[derive(Debug, Clone, Default)]
pub struct SizeEstimator {
    gpu_bytes_with_wire: u64,
    wire_bytes: u64,
    gpu_bytes_seen: u64,
    scans_seen: u64,
}

impl SizeEstimator {
    pub fn learn(&mut self, gpu_bytes: u64, encoded_bytes: u64) {
        self.gpu_bytes_seen = self.gpu_bytes_seen.saturating_add(gpu_bytes);
        self.scans_seen += 1;
        if encoded_bytes > 0 {
            self.gpu_bytes_with_wire = self.gpu_bytes_with_wire.saturating_add(gpu_bytes);
            self.wire_bytes = self.wire_bytes.saturating_add(encoded_bytes);
        }
    }

    pub fn estimate(&self, listing: &ScanListing) -> u64 {
        if listing.encoded_bytes > 0 {
            let ratio = if self.wire_bytes > 0 {
                self.gpu_bytes_with_wire as f64 / self.wire_bytes as f64
            } else {
                DEFAULT_GPU_PER_WIRE_BYTE
            };
            return (listing.encoded_bytes as f64 * ratio)
                .ceil()
                .min(u64::MAX as f64) as u64;
        }
        match self.scans_seen {
            0 => DEFAULT_SCAN_BYTES,
            n => self.gpu_bytes_seen / n,
        }
    }
}

/// What residency looks like after a step (the window's overlay and the headless
/// paths print it).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ResidencyStats {
    /// Scans known (listed).
    pub known: usize,
    /// Scans uploaded.
    pub resident: usize,
    /// Their GPU bytes.
    pub used_bytes: u64,
    pub budget_bytes: u64,
    /// Requests sent and not answered.
    pub in_flight: usize,
    /// Scans the view needs (in the widened view or near the camera).
    pub needed: usize,
    /// Needed scans that did not fit the budget.
    pub left_out: usize,
    /// Selected scans not uploaded yet (on their way or waiting for a request slot).
    pub pending: usize,
    /// Evictions and uploads since the start.
    pub evictions: u64,
    pub uploads: u64,
}

impl ResidencyStats {
    pub fn describe(&self) -> String {
        let mib = |b: u64| b as f64 / 1048576.0;
        let mut s = format!(
            "resident {}/{} scans, GPU {:.1}/{:.0} MiB, fetching {}",
            self.resident,
            self.known,
            mib(self.used_bytes),
            mib(self.budget_bytes),
            self.in_flight
        );
        if self.left_out > 0 {
            s.push_str(&format!(
                "; the view needs {} scans, {} left out (over budget)",
                self.needed, self.left_out
            ));
        }
        s
    }
}

/// Carries out residency plans for one model and one renderer.
pub struct Residency {
    pub options: PlanOptions,
    fetcher: Fetcher,
    in_flight: BTreeMap<ScanId, Instant>,
    /// Scans the source could not give or the GPU could not take, and why.
    unavailable: BTreeMap<ScanId, String>,
    exact_bytes: BTreeMap<ScanId, u64>,
    estimator: SizeEstimator,
    /// Uploads per step (the window paces them over frames; headless takes all).
    pub max_uploads_per_step: usize,
    stats: ResidencyStats,
    /// Resets seen: requests carry it so that the source drops stale ones.
    generation: u64,
}

impl Residency {
    pub fn new(budget_bytes: u64, fetcher: Fetcher) -> Self {
        let mut options = PlanOptions::new(budget_bytes);
        if matches!(fetcher, Fetcher::Local { .. }) {
            // A local fetch is an upload: the per-step upload limit paces it.
            options.max_in_flight = usize::MAX;
        }
        Self {
            options,
            fetcher,
            in_flight: BTreeMap::new(),
            unavailable: BTreeMap::new(),
            exact_bytes: BTreeMap::new(),
            estimator: SizeEstimator::default(),
            max_uploads_per_step: usize::MAX,
            stats: ResidencyStats {
                budget_bytes,
                ..Default::default()
            },
            generation: 0,
        }
    }

    /// Budget from megabytes (MiB) as `--gpu-budget-mb` gives it.
    pub fn budget_bytes_of_mb(mb: u64) -> u64 {
        mb.saturating_mul(1 << 20)
    }

    /// A local residency over a whole model: its data moves to the store (the
    /// model keeps the listings), to be uploaded as views need it.
    pub fn over_model(budget_bytes: u64, model: &mut Model) -> Self {
        let mut r = Self::new(
            budget_bytes,
            Fetcher::Local {
                store: BTreeMap::new(),
            },
        );
        let ids: Vec<ScanId> = model.resident().map(|(s, _)| s.id).collect();
        for id in ids {
            if let Some(s) = model.get(id)
                && let Some(scan) = s.scan.clone()
            {
                r.record(id, &scan, s.listing.encoded_bytes);
                let _ = model.apply(ModelEvent::ScanEvicted { id });
            }
        }
        r
    }

    pub fn stats(&self) -> ResidencyStats {
        self.stats
    }

    fn record(&mut self, id: ScanId, scan: &Arc<TexelScan>, encoded_bytes: u64) {
        let bytes = scan_gpu_bytes(scan);
        self.estimator.learn(bytes, encoded_bytes);
        self.exact_bytes.insert(id, bytes);
        if let Fetcher::Local { store } = &mut self.fetcher {
            store.insert(id, Arc::clone(scan));
        }
    }

    /// Follows an event the caller has applied to `model`: records arriving data,
    /// moves uploaded scans, drops withdrawn or evicted ones from the GPU.
    pub fn observe(&mut self, event: &ModelEvent, model: &Model, renderer: &mut Renderer) {
        match event {
            ModelEvent::ScanAdded {
                id,
                scan,
                world_from_scan,
            } => {
                self.in_flight.remove(id);
                self.unavailable.remove(id);
                let encoded = model.get(*id).map_or(0, |s| s.listing.encoded_bytes);
                self.record(*id, scan, encoded);
                renderer.set_pose(*id, *world_from_scan);
            }
            ModelEvent::PoseRevised {
                id,
                world_from_scan,
            }
            | ModelEvent::ScanListed {
                id,
                world_from_scan,
                ..
            } => {
                renderer.set_pose(*id, *world_from_scan);
                if matches!(event, ModelEvent::ScanListed { .. }) {
                    // Listed again: worth asking for again.
                    self.unavailable.remove(id);
                }
            }
            ModelEvent::ScanWithdrawn { id } => {
                renderer.remove_scan(*id);
                self.in_flight.remove(id);
                self.unavailable.remove(id);
                self.exact_bytes.remove(id);
                if let Fetcher::Local { store } = &mut self.fetcher {
                    store.remove(id);
                }
            }
            ModelEvent::ScanEvicted { id } => {
                renderer.remove_scan(*id);
            }
        }
    }

    /// The source could not give a scan: do not ask again until it is listed again.
    pub fn unavailable(&mut self, id: ScanId, reason: String) {
        self.in_flight.remove(&id);
        self.unavailable.insert(id, reason);
    }

    /// The source reset its model (a reconnect, a resynchronisation): requests are
    /// forgotten (and the source drops those not sent yet), ids will be reused.
    pub fn reset(&mut self, renderer: &mut Renderer) {
        self.generation += 1;
        renderer.clear_scans();
        self.in_flight.clear();
        self.unavailable.clear();
        self.exact_bytes.clear();
        if let Fetcher::Local { store } = &mut self.fetcher {
            store.clear();
        }
    }

    /// Scans that cannot be had, with the reason.
    pub fn unavailable_scans(&self) -> &BTreeMap<ScanId, String> {
        &self.unavailable
    }

    fn state(&self, id: ScanId, has_data: bool, renderer: &Renderer) -> DataState {
        if renderer.has_scan(id) {
            DataState::OnGpu
        } else if has_data {
            DataState::Held
        } else if self.in_flight.contains_key(&id) {
            DataState::InFlight
        } else {
            DataState::Absent
        }
    }

    /// Plans for `camera` and carries the plan out: evicts, uploads what is here (at
    /// most `max_uploads_per_step`, never past the budget) and fetches what is
    /// missing. An upload that fails marks the scan unavailable.
    pub fn step(
        &mut self,
        model: &mut Model,
        renderer: &mut Renderer,
        camera: &VirtualCamera,
    ) -> ResidencyStats {
        let now = Instant::now();
        self.in_flight
            .retain(|_, asked| now.saturating_duration_since(*asked) < REQUEST_EXPIRY);
        let scans: Vec<PlanScan> = model
            .scans()
            .iter()
            .filter(|s| !self.unavailable.contains_key(&s.id))
            .map(|s| PlanScan {
                id: s.id,
                listing: s.listing,
                world_from_scan: s.world_from_scan,
                bytes: renderer
                    .scan_bytes(s.id)
                    .or_else(|| self.exact_bytes.get(&s.id).copied())
                    .unwrap_or_else(|| self.estimator.estimate(&s.listing)),
                state: self.state(s.id, s.is_resident(), renderer),
            })
            .collect();
        let plan = plan(&scans, camera, &self.options);
        for &id in &plan.evict {
            renderer.remove_scan(id);
            if model.get(id).is_some_and(|s| s.is_resident()) {
                let _ = model.apply(ModelEvent::ScanEvicted { id });
            }
            self.stats.evictions += 1;
        }
        let mut uploads = 0usize;
        let mut pending = 0usize;
        for &id in &plan.selected {
            if renderer.has_scan(id) {
                continue;
            }
            if uploads >= self.max_uploads_per_step {
                pending += 1;
                continue;
            }
            match self.upload(id, model, renderer) {
                Ok(true) => uploads += 1,
                Ok(false) => pending += 1,
                Err(e) => {
                    eprintln!("warning: scan {id} left out: {e}");
                    self.unavailable.insert(id, e.to_string());
                    let _ = model.apply(ModelEvent::ScanEvicted { id });
                }
            }
        }
        self.stats.uploads += uploads as u64;
        if let Fetcher::Remote { commands } = &self.fetcher {
            for &id in &plan.fetch {
                let request = SourceCommand::RequestScan {
                    id,
                    generation: self.generation,
                };
                match commands.try_send(request) {
                    Ok(()) => {
                        self.in_flight.insert(id, now);
                    }
                    Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => break,
                }
            }
        }
        self.stats = ResidencyStats {
            known: model.len(),
            resident: renderer.scan_count(),
            used_bytes: renderer.scans_bytes(),
            budget_bytes: self.options.budget_bytes,
            in_flight: self.in_flight.len(),
            needed: plan.needed,
            left_out: plan.left_out.len(),
            pending,
            ..self.stats
        };
        self.stats
    }

    /// Uploads a selected scan whose data is here (in the model, or in the local
    /// store); `Ok(false)` when it is not here or does not fit beside what is
    /// uploaded (its size was estimated low: the next plan knows it exactly).
    fn upload(
        &mut self,
        id: ScanId,
        model: &mut Model,
        renderer: &mut Renderer,
    ) -> Result<bool, GpuError> {
        let Some(entry) = model.get(id) else {
            return Ok(false);
        };
        let pose = entry.world_from_scan;
        let was_resident = entry.is_resident();
        let data = match (&entry.scan, &self.fetcher) {
            (Some(scan), _) => Arc::clone(scan),
            (None, Fetcher::Local { store }) => match store.get(&id) {
                Some(scan) => Arc::clone(scan),
                None => return Ok(false),
            },
            (None, Fetcher::Remote { .. }) => return Ok(false),
        };
        let bytes = *self
            .exact_bytes
            .entry(id)
            .or_insert_with(|| scan_gpu_bytes(&data));
        if renderer.scans_bytes().saturating_add(bytes) > self.options.budget_bytes {
            return Ok(false);
        }
        renderer.add_scan(id, &data, pose)?;
        if !was_resident {
            let _ = model.apply(ModelEvent::ScanAdded {
                id,
                scan: data,
                world_from_scan: pose,
            });
        }
        Ok(true)
    }

    /// The scans asked for and not answered yet.
    pub fn in_flight(&self) -> BTreeSet<ScanId> {
        self.in_flight.keys().copied().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn listing(encoded_bytes: u64) -> ScanListing {
        ScanListing {
            timestamp_ns: 0,
            bounds_min_m: [0.0; 3],
            bounds_max_m: [1.0; 3],
            cop_m: [0.0; 3],
            priority: 0.0,
            encoded_bytes,
        }
    }

    #[test]
    fn sizes_are_estimated_from_what_was_seen() {
        let mut e = SizeEstimator::default();
        assert_eq!(e.estimate(&listing(100)), 400);
        assert_eq!(e.estimate(&listing(0)), DEFAULT_SCAN_BYTES);
        e.learn(3000, 1000);
        e.learn(1000, 0);
        // 3 GPU bytes per wire byte; the mean of the two sizes seen.
        assert_eq!(e.estimate(&listing(100)), 300);
        assert_eq!(e.estimate(&listing(0)), 2000);
        // Huge wire sizes saturate instead of wrapping.
        assert_eq!(e.estimate(&listing(u64::MAX)), u64::MAX);
    }
}
