//! What the window shows, independent of the window: the model as the events built
//! it, the settings, the camera, the residency of the model's scans on the GPU and the
//! statistics the overlay shows.

use std::sync::mpsc::{Receiver, SyncSender};
// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::Instant;

use texel::model::{Model, ModelEvent};
use texel::wire::Status;

use super::controls::CameraControls;
use crate::camera::VirtualCamera;
use crate::gpu::{FrameStats, RenderSettings, Renderer};
use crate::live::{ConnectionState, LatencyMeter, SourceCommand, ViewerEvent, fov_y_deg_of_scan};
use crate::residency::{Fetcher, Residency, ResidencyStats};

/// What the viewer shows, independent of the window.
pub struct ViewerState {
    pub model: Model,
    pub settings: RenderSettings,
    pub controls: CameraControls,
    pub fov_deg: f64,
    pub follow_newest: bool,
    pub stats: FrameStats,
    pub fps: f64,
    /// A request from the UI to jump to a scan's acquisition view.
    pub jump_to: Option<u64>,
    /// The source's connection, if it reports one.
    pub connection: Option<ConnectionState>,
    /// The daemon's latest status and when it came.
    pub status: Option<(Status, Instant)>,
    /// Whether the first snapshot is complete.
    pub snapshot_complete: bool,
    pub latency: LatencyMeter,
    /// What of the model is on the GPU, within the budget.
    pub residency: Residency,
    pub residency_stats: ResidencyStats,
    /// The camera and model state of the last residency step: with neither changed
    /// and nothing on its way, planning again would change nothing.
    planned: Option<(VirtualCamera, u64)>,
    /// Draw the daemon's level-of-detail tiles instead of its scans (when it serves
    /// them); `L` switches.
    pub show_tiles: bool,
    /// With the tiles, draw the scans below the finest tiles the view finds too
    /// coarse (Liu's leaves).
    pub scans_below_tiles: bool,
    /// The last frame's tile figures, when tiles were drawn.
    pub tile_stats: Option<crate::tiles::TileFrameStats>,
    /// The VDTM mode's last build, when that mode is on.
    pub vdtm_status: Option<crate::vdtm::VdtmStatus>,
    /// The VDTM switches the panel edits.
    pub vdtm_settings: Option<crate::vdtm::VdtmSettings>,
    /// The response curve the source sent (a daemon of protocol version 4).
    pub eo_response: Option<texel::radiance::EoResponse>,
    /// The picture on screen (its quality) and the last drawn frame's time, ms,
    /// when the scans are drawn through adaptive quality.
    pub quality: Option<(crate::adaptive::Shown, f64)>,
    /// The full-quality frame under way: steps submitted and in all.
    pub refining: Option<(usize, usize)>,
    camera_placed: bool,
    fov_known: bool,
}

impl ViewerState {
    pub fn new(settings: RenderSettings, fov_deg: Option<f64>, residency: Residency) -> Self {
        Self {
            model: Model::new(),
            settings,
            controls: CameraControls::new(texel::Pose::identity(), 3.0),
            fov_deg: fov_deg.unwrap_or(50.0),
            follow_newest: false,
            stats: FrameStats::default(),
            fps: 0.0,
            jump_to: None,
            connection: None,
            show_tiles: false,
            scans_below_tiles: true,
            tile_stats: None,
            vdtm_status: None,
            vdtm_settings: None,
            eo_response: None,
            status: None,
            snapshot_complete: false,
            latency: LatencyMeter::default(),
            residency_stats: residency.stats(),
            residency,
            planned: None,
            quality: None,
            refining: None,
            camera_placed: false,
            fov_known: fov_deg.is_some(),
        }
    }

    /// Applies the events waiting (at most a bounded batch per frame, so the window
    /// stays responsive while a large snapshot arrives) and uploads what they bring;
    /// a bad event is reported and skipped, never fatal. Returns the events taken
    /// (a window with none has nothing new to show).
    pub fn apply_events(
        &mut self,
        events: &Receiver<ViewerEvent>,
        renderer: &mut Renderer,
    ) -> usize {
        const MAX_PER_FRAME: usize = 64;
        let mut taken = 0;
        for _ in 0..MAX_PER_FRAME {
            let Ok(event) = events.try_recv() else {
                break;
            };
            taken += 1;
            let (event, received) = match event {
                ViewerEvent::Model { event, received } => (event, received),
                ViewerEvent::Reset => {
                    self.model = Model::new();
                    self.residency.reset(renderer);
                    self.planned = None;
                    self.snapshot_complete = false;
                    continue;
                }
                ViewerEvent::ScanUnavailable { id, reason } => {
                    self.residency.unavailable(id, reason);
                    self.planned = None;
                    continue;
                }
                ViewerEvent::EoResponse(response) => {
                    self.eo_response = Some(*response);
                    continue;
                }
                ViewerEvent::SnapshotComplete { .. } => {
                    self.snapshot_complete = true;
                    continue;
                }
                ViewerEvent::Status { status, received } => {
                    self.status = Some((*status, received));
                    continue;
                }
                ViewerEvent::Connection(state) => {
                    self.connection = Some(state);
                    continue;
                }
            };
            self.latency.received(received);
            if let Err(e) = self.model.apply(event.clone()) {
                eprintln!("warning: model event skipped: {e}");
                continue;
            }
            // Residency uploads what the view needs at the next step.
            self.residency.observe(&event, &self.model, renderer);
            match event {
                ModelEvent::ScanAdded {
                    id,
                    scan,
                    world_from_scan,
                } => {
                    if !self.fov_known
                        && let Some(fov) = fov_y_deg_of_scan(&scan)
                    {
                        self.fov_deg = fov;
                        self.fov_known = true;
                    }
                    let newest = self.model.scans().last().is_some_and(|s| s.id == id);
                    if (self.follow_newest && newest) || !self.camera_placed {
                        self.jump(world_from_scan, median_range_m(&scan));
                    }
                }
                ModelEvent::PoseRevised {
                    id,
                    world_from_scan,
                } => {
                    // Following the sensor: the newest scan's revised pose moves the
                    // camera with it.
                    if self.follow_newest
                        && self.model.scans().last().is_some_and(|s| s.id == id)
                        && let Some(scan) = self.model.get(id).and_then(|s| s.scan.clone())
                    {
                        self.jump(world_from_scan, median_range_m(&scan));
                    }
                }
                // A model that arrives as listings first: look from the first one.
                ModelEvent::ScanListed {
                    world_from_scan,
                    listing,
                    ..
                } if !self.camera_placed => {
                    self.jump(world_from_scan, listing_range_m(&listing));
                }
                ModelEvent::ScanListed { .. }
                | ModelEvent::ScanWithdrawn { .. }
                | ModelEvent::ScanEvicted { .. } => {}
            }
        }
        if let Some(id) = self.jump_to.take()
            && let Some(s) = self.model.get(id)
        {
            let pivot = s
                .scan
                .as_deref()
                .map_or_else(|| listing_range_m(&s.listing), median_range_m);
            let pose = s.world_from_scan;
            self.jump(pose, pivot);
        }
        taken
    }

    /// Carries out residency for `camera`: evicts, uploads, fetches.
    pub fn update_residency(&mut self, renderer: &mut Renderer, camera: &VirtualCamera) {
        if self.residency.options.hidden != self.settings.hidden
            || self.residency.options.only != self.settings.only
        {
            self.residency.options.hidden = self.settings.hidden.clone();
            self.residency.options.only = self.settings.only.clone();
            self.planned = None;
        }
        let state = (*camera, self.model.events_applied());
        let settled = self.residency_stats.in_flight == 0 && self.residency_stats.pending == 0;
        if settled && self.planned == Some(state) {
            return;
        }
        self.residency_stats = self.residency.step(&mut self.model, renderer, camera);
        // The step's own evictions and uploads are events: the state after it.
        self.planned = Some((*camera, self.model.events_applied()));
    }

    /// Puts the camera at `world_from_eo` (a deep link's fixed view), pivoting
    /// `pivot_m` ahead; scans arriving later no longer move it.
    pub fn place_camera(&mut self, world_from_eo: texel::Pose, pivot_m: f64) {
        self.jump(world_from_eo, pivot_m);
    }

    /// Puts the camera at a scan's acquisition pose, pivoting `pivot_m` ahead.
    fn jump(&mut self, world_from_scan: texel::Pose, pivot_m: f64) {
        self.controls = CameraControls::new(world_from_scan, pivot_m);
        self.camera_placed = true;
    }

    pub fn camera(&self, width: u32, height: u32) -> Option<VirtualCamera> {
        VirtualCamera::new(self.controls.world_from_eo, self.fov_deg, width, height).ok()
    }
}

/// The median range (z) of a scan's vertices: where the camera pivots; 3 m for a scan
/// without a finite vertex.
fn median_range_m(scan: &texel::TexelScan) -> f64 {
    let mut ranges: Vec<f32> = scan
        .vertices
        .iter()
        .map(|v| v[2])
        .filter(|z| z.is_finite())
        .collect();
    ranges.sort_by(f32::total_cmp);
    f64::from(ranges.get(ranges.len() / 2).copied().unwrap_or(3.0))
}

/// The middle of a listing's box along its optical axis (z): the pivot before the
/// data is here; 3 m when that is not a positive finite distance.
fn listing_range_m(listing: &texel::model::ScanListing) -> f64 {
    let z = 0.5 * (f64::from(listing.bounds_min_m[2]) + f64::from(listing.bounds_max_m[2]));
    if z.is_finite() && z > 0.0 { z } else { 3.0 }
}

/// The residency of a window: fetching through `commands` when there are any, else
/// from a store of every scan that arrived.
pub(crate) fn window_residency(
    budget_bytes: u64,
    commands: Option<SyncSender<SourceCommand>>,
) -> Residency {
    let fetcher = match commands {
        Some(commands) => Fetcher::Remote { commands },
        None => Fetcher::Local {
            store: Default::default(),
        },
    };
    let mut residency = Residency::new(budget_bytes, fetcher);
    // Uploads are paced so a frame stays short while a model streams in.
    residency.max_uploads_per_step = 8;
    residency
}
