//! The viewer on a running daemon's model: the served model fetched over loopback
//! as `texel-viewer render --connect` fetches it, then, under a GPU budget, residency
//! and blended frames from an overview of the whole model and from the newest scan's
//! pose: the frame time (a residency step and a render, median), the GPU memory
//! against the budget, and the scans resident, needed and left out.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use texel::model::Model;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{GpuContext, RenderSettings, Renderer};
use texel_viewer::live::fetch::fetch_model;
use texel_viewer::live::snapshots::orbit_pose;
use texel_viewer::residency::Residency;

use crate::viewer_bench::measure;

/// The image the figures are for (the residency benchmark's).
pub const WIDTH: u32 = 640;
pub const HEIGHT: u32 = 480;
const FOV_Y_DEG: f64 = 50.0;
/// Residency steps before timing: uploads within the budget until the plan is done.
const MAX_SETTLE_STEPS: usize = 64;

/// One view's figures.
#[derive(Debug, Clone)]
pub struct ViewFigures {
    pub view: &'static str,
    pub known: usize,
    pub needed: usize,
    pub resident: usize,
    pub left_out: usize,
    pub used_mib: f64,
    pub budget_mib: f64,
    pub drawn: usize,
    pub frame_ms: f64,
}

/// Fetches the daemon's served model and measures `frames` frames per view under a
/// `budget_mb` GPU budget.
pub fn measure_on_daemon(
    addr: SocketAddr,
    budget_mb: u64,
    frames: u32,
) -> Result<Vec<ViewFigures>> {
    // 1. The served model, every listed scan's data here (the CPU holds it, as a
    //    capture's scans are held; only the GPU is budgeted).
    let fetched = Instant::now();
    let mut model = fetch_model(&addr.to_string(), "", 0, Duration::from_secs(900))
        .context("fetching the served model")?;
    eprintln!(
        "viewer: {} scans fetched in {:.1} s",
        model.len(),
        fetched.elapsed().as_secs_f64()
    );
    // 2. The views: the whole model from outside it, and where the camera is now.
    let overview = orbit_pose(&model, 0).context("the model has no scans to view")?;
    let newest = model
        .scans()
        .last()
        .map(|s| s.world_from_scan)
        .context("the model has no scans")?;
    // One viewer moving from one view to the other (its residency owns the scans'
    // data from here on, as a capture's viewer's does).
    let gpu = GpuContext::headless()?;
    let settings = RenderSettings::with_mode(Mode::Blended);
    let mut residency = Residency::over_model(Residency::budget_bytes_of_mb(budget_mb), &mut model);
    let mut renderer = Renderer::new(&gpu);
    let mut figures = Vec::new();
    for (view, pose) in [("overview", overview), ("newest scan", newest)] {
        let camera = VirtualCamera::new(pose, FOV_Y_DEG, WIDTH, HEIGHT)?;
        let mut viewer = Viewer {
            gpu: &gpu,
            model: &mut model,
            residency: &mut residency,
            renderer: &mut renderer,
        };
        figures.push(viewer.figures(view, &camera, &settings, frames)?);
    }
    Ok(figures)
}

/// A viewer's parts, as the window holds them.
struct Viewer<'a> {
    gpu: &'a GpuContext,
    model: &'a mut Model,
    residency: &'a mut Residency,
    renderer: &'a mut Renderer,
}

impl Viewer<'_> {
    /// 3. Residency settles on the view, then each timed frame is a residency step
    ///    and a render (as in the window).
    fn figures(
        &mut self,
        view: &'static str,
        camera: &VirtualCamera,
        settings: &RenderSettings,
        frames: u32,
    ) -> Result<ViewFigures> {
        for _ in 0..MAX_SETTLE_STEPS {
            let stats = self.residency.step(self.model, self.renderer, camera);
            if stats.pending == 0 && stats.in_flight == 0 {
                break;
            }
        }
        let mut times = Vec::new();
        let mut last = None;
        for _ in 0..frames.max(1) {
            let start = Instant::now();
            let stats = self.residency.step(self.model, self.renderer, camera);
            let step_ms = start.elapsed().as_secs_f64() * 1000.0;
            // The render after two warm-up renders of the same frame.
            let (render_ms, drawn, _) = measure(self.gpu, self.renderer, camera, settings, 1)?;
            times.push(step_ms + render_ms);
            last = Some((stats, drawn));
        }
        times.sort_by(f64::total_cmp);
        let (stats, drawn) = last.context("no frame was measured")?;
        let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
        Ok(ViewFigures {
            view,
            known: stats.known,
            needed: stats.needed,
            resident: stats.resident,
            left_out: stats.left_out,
            used_mib: mib(stats.used_bytes),
            budget_mib: mib(stats.budget_bytes),
            drawn,
            frame_ms: times.get(times.len() / 2).copied().unwrap_or(f64::NAN),
        })
    }
}
