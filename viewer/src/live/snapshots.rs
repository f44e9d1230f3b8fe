//! Snapshots of a live model without a display: the viewer events are applied to a
//! model, and every `every` seconds (when the model changed) or every `every_scans`
//! new scans, a view is rendered headless to a numbered PNG in a folder, from the
//! newest scan's acquisition pose or from an orbit around the model. Each view holds
//! what it needs within the GPU budget; a live source is asked for what is missing
//! and the snapshot waits (a bounded time) for it.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender};
use std::time::{Duration, Instant};

use anyhow::Context;
use nalgebra::{Point3, Vector3};
use texel::Pose;
use texel::model::Model;

use super::{SourceCommand, ViewerEvent, fov_y_deg_of_scan};
use crate::camera::VirtualCamera;
use crate::gpu::{GpuContext, RenderSettings, Renderer};
use crate::residency::{Fetcher, Residency};

/// A snapshot waits at most this long for the scans its view asked for.
const FETCH_WAIT: Duration = Duration::from_secs(10);

/// Where snapshots are seen from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SnapshotView {
    /// The newest scan's acquisition pose (follow the sensor).
    Newest,
    /// Around the model's centre, 30 degrees further at each snapshot.
    Orbit,
}

#[derive(Debug, Clone)]
pub struct SnapshotOptions {
    pub dir: PathBuf,
    pub every: Duration,
    pub every_scans: usize,
    pub view: SnapshotView,
    pub width: u32,
    pub height: u32,
    /// Vertical field of view; default: estimated from the first scan.
    pub fov_deg: Option<f64>,
    pub settings: RenderSettings,
    /// Stop after this many snapshots.
    pub max_snapshots: Option<usize>,
    /// The GPU bytes scans may hold.
    pub budget_bytes: u64,
    /// Where missing scans are asked for (a live source); `None`: every scan's data
    /// arrives as an event and is kept on the CPU.
    pub commands: Option<SyncSender<SourceCommand>>,
    /// Draw by view-dependent texture mapping (Debevec 1998) instead of the scans:
    /// the merged surface is prepared anew from the scans held whenever the model
    /// has moved on by the time of a snapshot.
    pub vdtm: Option<crate::vdtm::VdtmChoice>,
}

/// What a snapshot run did.
#[derive(Debug, Clone, Default)]
pub struct SnapshotSummary {
    pub written: Vec<PathBuf>,
    pub scans: usize,
}

/// Applies events and writes snapshots until `stop` is set, the source ends, or
/// `max_snapshots` are written. Progress goes to stderr, each snapshot's path to
/// stdout.
pub fn run(
    events: &Receiver<ViewerEvent>,
    options: &SnapshotOptions,
    stop: &AtomicBool,
) -> anyhow::Result<SnapshotSummary> {
    std::fs::create_dir_all(&options.dir)
        .with_context(|| format!("creating {}", options.dir.display()))?;
    let gpu = GpuContext::headless()?;
    let mut renderer = Renderer::new(&gpu);
    let mut vdtm = options
        .vdtm
        .clone()
        .map(|choice| crate::vdtm::LiveVdtm::new(&gpu, choice));
    let mut model = Model::new();
    let fetcher = match &options.commands {
        Some(commands) => Fetcher::Remote {
            commands: commands.clone(),
        },
        None => Fetcher::Local {
            store: Default::default(),
        },
    };
    let mut residency = Residency::new(options.budget_bytes, fetcher);
    residency.options.hidden = options.settings.hidden.clone();
    let mut summary = SnapshotSummary::default();
    let mut last_shot = Instant::now();
    let mut changed_since_shot = false;
    let mut scans_at_shot = 0usize;
    let mut ended = false;
    // Until the first snapshot of the source is complete, the model is partial.
    let mut complete = false;
    let mut eo_response: Option<texel::radiance::EoResponse> = None;
    // When the due snapshot started waiting for its scans.
    let mut waiting_since: Option<Instant> = None;
    while !stop.load(Ordering::Acquire) && !ended {
        match events.recv_timeout(Duration::from_millis(100)) {
            Ok(event) => match event {
                ViewerEvent::Connection(state) => {
                    eprintln!("texel-viewer: {}", state.describe());
                    ended = matches!(state, super::ConnectionState::Ended { .. });
                }
                ViewerEvent::Reset => {
                    model = Model::new();
                    residency.reset(&mut renderer);
                    scans_at_shot = 0;
                    complete = false;
                    changed_since_shot = true;
                }
                ViewerEvent::SnapshotComplete { .. } => complete = true,
                ViewerEvent::ScanUnavailable { id, reason } => residency.unavailable(id, reason),
                ViewerEvent::EoResponse(response) => eo_response = Some(*response),
                ViewerEvent::Model { event, .. } => {
                    // Scans fetched for a view do not make a new snapshot due.
                    let fetched = matches!(event, texel::model::ModelEvent::ScanAdded { id, .. }
                        if residency.in_flight().contains(&id));
                    if model.apply(event.clone()).is_ok() {
                        residency.observe(&event, &model, &mut renderer);
                        changed_since_shot |= !fetched;
                    }
                }
                ViewerEvent::Status { .. } => {}
            },
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => ended = true,
        }
        let new_scans = model.len().saturating_sub(scans_at_shot);
        let due = (options.every_scans > 0 && new_scans >= options.every_scans)
            || (last_shot.elapsed() >= options.every && changed_since_shot)
            || (ended && changed_since_shot);
        if !due || model.is_empty() || !(complete || ended) {
            continue;
        }
        let Some(camera) = snapshot_camera(&model, options, summary.written.len())? else {
            continue;
        };
        let resident = residency.step(&mut model, &mut renderer, &camera);
        if options.settings.points {
            // The daemon's response curve (protocol version 4), else sRGB.
            let response = eo_response.get_or_insert_with(texel::radiance::EoResponse::srgb);
            let radiance = options.settings.tone_map.is_some().then_some(&*response);
            renderer.prepare_points(&model, radiance);
        }
        let since = *waiting_since.get_or_insert_with(Instant::now);
        if (resident.in_flight > 0 || resident.pending > 0)
            && since.elapsed() < FETCH_WAIT
            && !ended
        {
            continue;
        }
        waiting_since = None;
        let path = options
            .dir
            .join(format!("snapshot-{:04}.png", summary.written.len() + 1));
        match vdtm.as_mut() {
            Some(vdtm) => shoot_vdtm(&gpu, vdtm, &model, &camera, options, &path)?,
            None => shoot(&mut renderer, &camera, options, &path)?,
        }
        println!(
            "{} ({} scans), {}",
            path.display(),
            model.len(),
            resident.describe()
        );
        summary.written.push(path);
        summary.scans = model.len();
        last_shot = Instant::now();
        changed_since_shot = false;
        scans_at_shot = model.len();
        if options
            .max_snapshots
            .is_some_and(|m| summary.written.len() >= m)
        {
            break;
        }
    }
    Ok(summary)
}

/// Where snapshot `index` is seen from; `None` for an empty model.
fn snapshot_camera(
    model: &Model,
    options: &SnapshotOptions,
    index: usize,
) -> anyhow::Result<Option<VirtualCamera>> {
    let Some(newest) = model.scans().last() else {
        return Ok(None);
    };
    let fov = options
        .fov_deg
        .or_else(|| {
            model
                .resident()
                .find_map(|(_, scan)| fov_y_deg_of_scan(scan))
        })
        .unwrap_or(50.0);
    let pose = match options.view {
        SnapshotView::Newest => newest.world_from_scan,
        SnapshotView::Orbit => orbit_pose(model, index).unwrap_or(newest.world_from_scan),
    };
    Ok(Some(VirtualCamera::new(
        pose,
        fov,
        options.width,
        options.height,
    )?))
}

fn shoot(
    renderer: &mut Renderer,
    camera: &VirtualCamera,
    options: &SnapshotOptions,
    path: &Path,
) -> anyhow::Result<()> {
    let (image, _) = renderer.render_to_image(camera, &options.settings)?;
    save_whole(&image, path)
}

/// A VDTM snapshot: the preparation brought up to the model first (waited for).
fn shoot_vdtm(
    gpu: &GpuContext,
    vdtm: &mut crate::vdtm::LiveVdtm,
    model: &Model,
    camera: &VirtualCamera,
    options: &SnapshotOptions,
    path: &Path,
) -> anyhow::Result<()> {
    vdtm.update(gpu, model, true);
    eprintln!("{}", vdtm.status.describe());
    let image = vdtm
        .render_to_image(gpu, camera, options.settings.composite.background)?
        .with_context(|| {
            format!(
                "VDTM has nothing to draw: {}",
                vdtm.status.error.as_deref().unwrap_or("no build finished")
            )
        })?;
    save_whole(&image, path)
}

fn save_whole(image: &image::RgbaImage, path: &Path) -> anyhow::Result<()> {
    // Written whole under a temporary name, then renamed: a reader never sees half
    // a PNG.
    let partial = path.with_extension("partial.png");
    image
        .save(&partial)
        .with_context(|| format!("writing {}", partial.display()))?;
    std::fs::rename(&partial, path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// A pose on a circle around the model (world +z up): centred on the middle of the
/// scans' acquisition centres and the surfaces they saw, at a radius that keeps it
/// in view, `30 * index` degrees around.
pub fn orbit_pose(model: &Model, index: usize) -> Option<Pose> {
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for s in model.scans() {
        // The listing's box: known whether or not the data is here.
        let (a, b) = (s.listing.bounds_min_m, s.listing.bounds_max_m);
        for corner in 0..8 {
            let p = Vector3::new(
                f64::from(if corner & 1 == 0 { a[0] } else { b[0] }),
                f64::from(if corner & 2 == 0 { a[1] } else { b[1] }),
                f64::from(if corner & 4 == 0 { a[2] } else { b[2] }),
            );
            let w = s.world_from_scan.transform_point(&Point3::from(p)).coords;
            lo = lo.inf(&w);
            hi = hi.sup(&w);
        }
    }
    if !(lo.iter().all(|v| v.is_finite()) && hi.iter().all(|v| v.is_finite())) {
        return None;
    }
    let centre = (lo + hi) * 0.5;
    let radius = ((hi - lo).norm() * 0.6).max(0.5);
    let angle = (index as f64 * 30.0).to_radians();
    let eye = centre + Vector3::new(radius * angle.cos(), radius * angle.sin(), radius * 0.5);
    Some(texel::pose::look_at(
        Point3::from(eye),
        Point3::from(centre),
        Vector3::z(),
    ))
}
