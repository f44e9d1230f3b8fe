//! VDTM over a model that keeps changing (a live session, a replay, the window):
//! the preprocessing runs on a worker thread over a snapshot of the model, the frame
//! keeps drawing the last prepared model meanwhile, and a new build starts once the
//! model has moved on (scans added, withdrawn or re-posed) and the last build is done.
//! View maps are not updated in place: a revised pose can change what every view
//! sees, so each build starts over, and its cost is the preprocessing's.

use std::sync::Arc;
use std::sync::mpsc::{Receiver, TryRecvError, sync_channel};
// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::{Duration, Instant};

use texel::camera::PinholeCamera;
use texel::model::Model;

use super::gpu::GpuVdtm;
use super::pass::{VdtmPass, VdtmSettings};
use super::prepare::{PreparedVdtm, VdtmViewConfig, prepare};
use crate::camera::VirtualCamera;
use crate::gpu::GpuContext;
use crate::tiles::pass::PassTarget;

/// A pose change smaller than this (metres) does not call for a new build.
const POSE_TOLERANCE_M: f64 = 0.01;

/// What the last build made and cost, for the panel and the logs.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct VdtmStatus {
    /// Scans, views and polygons of the model drawn.
    pub scans: usize,
    pub views: usize,
    pub polygons: usize,
    pub holes: usize,
    /// Seconds the last build took (surface and preprocessing) and the upload after.
    pub build_s: f64,
    pub upload_s: f64,
    pub builds: u32,
    /// A build is running.
    pub building: bool,
    /// The last build's error, if it failed.
    pub error: Option<String>,
}

impl VdtmStatus {
    pub fn describe(&self) -> String {
        let mut s = format!(
            "VDTM: {} scans, {} views, {} polygons ({} holes); build {:.1} s, upload {:.2} s",
            self.scans, self.views, self.polygons, self.holes, self.build_s, self.upload_s
        );
        if self.building {
            s.push_str("; rebuilding");
        }
        if let Some(e) = &self.error {
            s.push_str(&format!("; last build failed: {e}"));
        }
        s
    }
}

/// The VDTM mode as chosen (command line, panel): what to build and how to draw it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct VdtmChoice {
    pub settings: VdtmSettings,
    pub config: VdtmViewConfig,
    /// The calibrated EO camera, when known (a capture holds it).
    pub camera: Option<PinholeCamera>,
}

type BuildResult = (Result<PreparedVdtm, String>, f64);

/// The VDTM mode's state across frames.
pub struct LiveVdtm {
    pub settings: VdtmSettings,
    pub config: VdtmViewConfig,
    /// The calibrated EO camera, when known (a capture holds it); otherwise fitted
    /// from the first scan (`crate::live::eo_fit`).
    camera: Option<PinholeCamera>,
    pass: VdtmPass,
    current: Option<(Arc<PreparedVdtm>, GpuVdtm)>,
    pending: Option<Receiver<BuildResult>>,
    /// Builds wait this long after the last one started (a burst of scans is one build).
    pub min_interval: Duration,
    last_start: Option<Instant>,
    pub status: VdtmStatus,
}

impl LiveVdtm {
    pub fn new(gpu: &GpuContext, choice: VdtmChoice) -> Self {
        Self {
            settings: choice.settings,
            config: choice.config,
            camera: choice.camera,
            pass: VdtmPass::new(gpu),
            current: None,
            pending: None,
            min_interval: Duration::from_secs(2),
            last_start: None,
            status: VdtmStatus::default(),
        }
    }

    /// The EO camera the views are textured through.
    fn eo_camera(&mut self, model: &Model) -> Option<PinholeCamera> {
        if self.camera.is_none() {
            self.camera = model
                .resident()
                .find_map(|(_, scan)| crate::live::eo_fit::eo_camera_of_scan(scan))
                .map(|fit| fit.camera);
        }
        self.camera.clone()
    }

    /// Takes a finished build (uploading it) and starts a new one when the model has
    /// moved on. `wait`: block until the build started or running is done (headless).
    pub fn update(&mut self, gpu: &GpuContext, model: &Model, wait: bool) {
        self.collect(gpu, wait);
        let stale = self
            .current
            .as_ref()
            .is_none_or(|(p, _)| !p.matches(model, POSE_TOLERANCE_M));
        let due = self
            .last_start
            .is_none_or(|t| t.elapsed() >= self.min_interval);
        if self.pending.is_none() && stale && (due || wait) && model.resident().next().is_some() {
            self.start(model);
            self.collect(gpu, wait);
        }
    }

    fn start(&mut self, model: &Model) {
        let Some(camera) = self.eo_camera(model) else {
            self.status.error = Some("no EO camera: none given and none fits the scans".into());
            return;
        };
        let snapshot = model.clone();
        let config = self.config.clone();
        let (tx, rx) = sync_channel(1);
        self.last_start = Some(Instant::now());
        self.status.building = true;
        let spawned = std::thread::Builder::new()
            .name("vdtm-build".into())
            .spawn(move || {
                let t = Instant::now();
                let result = prepare(&snapshot, &camera, &config).map_err(|e| e.to_string());
                let _ = tx.send((result, t.elapsed().as_secs_f64()));
            });
        match spawned {
            Ok(_) => self.pending = Some(rx),
            Err(e) => {
                self.status.building = false;
                self.status.error = Some(format!("cannot start the build thread: {e}"));
            }
        }
    }

    fn collect(&mut self, gpu: &GpuContext, wait: bool) {
        let Some(rx) = &self.pending else {
            return;
        };
        let received = if wait {
            rx.recv().map_err(|_| TryRecvError::Disconnected)
        } else {
            rx.try_recv()
        };
        let (result, build_s) = match received {
            Ok(r) => r,
            Err(TryRecvError::Empty) => return,
            Err(TryRecvError::Disconnected) => (Err("the build thread stopped".into()), 0.0),
        };
        self.pending = None;
        self.status.building = false;
        match result.and_then(|prepared| {
            let t = Instant::now();
            let uploaded =
                GpuVdtm::upload(&gpu.device, &gpu.queue, &prepared).map_err(|e| e.to_string())?;
            Ok((prepared, uploaded, t.elapsed().as_secs_f64()))
        }) {
            Ok((prepared, uploaded, upload_s)) => {
                self.status = VdtmStatus {
                    scans: prepared.fused.len(),
                    views: prepared.views.len(),
                    polygons: uploaded.polygons(),
                    holes: prepared.model.stats.holes,
                    build_s,
                    upload_s,
                    builds: self.status.builds + 1,
                    building: false,
                    error: None,
                };
                self.current = Some((Arc::new(prepared), uploaded));
            }
            Err(e) => self.status.error = Some(e),
        }
    }

    /// The model being drawn, once a build has finished.
    pub fn prepared(&self) -> Option<&PreparedVdtm> {
        self.current.as_ref().map(|(p, _)| p.as_ref())
    }

    /// Records the pass into `target`; false (nothing recorded) before the first
    /// build has finished.
    pub fn encode(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        target: &PassTarget<'_>,
        camera: &VirtualCamera,
    ) -> bool {
        let Some((prepared, model)) = self.current.as_mut() else {
            return false;
        };
        self.pass
            .encode(encoder, target, camera, &self.settings, prepared, model);
        true
    }

    /// Renders into a new image (headless); `None` before the first build finished.
    pub fn render_to_image(
        &mut self,
        gpu: &GpuContext,
        camera: &VirtualCamera,
        background: [f32; 3],
    ) -> Result<Option<image::RgbaImage>, crate::gpu::GpuError> {
        let Some((prepared, model)) = self.current.as_mut() else {
            return Ok(None);
        };
        super::pass::render_vdtm_to_image(
            gpu,
            &mut self.pass,
            prepared,
            model,
            camera,
            &self.settings,
            background,
        )
        .map(Some)
    }
}
