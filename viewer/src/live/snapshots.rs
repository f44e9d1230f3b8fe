//! Snapshots of a live model without a display: the viewer events are applied to a
//! model, and every `every` seconds (when the model changed) or every `every_scans`
//! new scans, a view is rendered headless to a numbered PNG in a folder, from the
//! newest scan's acquisition pose or from an orbit around the model.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use anyhow::Context;
use nalgebra::{Point3, Vector3};
use texel::Pose;
use texel::model::Model;

use super::{ViewerEvent, apply_to_model, fov_y_deg_of_scan};
use crate::camera::VirtualCamera;
use crate::gpu::{GpuContext, RenderSettings, Renderer};

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
    let mut model = Model::new();
    let mut summary = SnapshotSummary::default();
    let mut last_shot = Instant::now();
    let mut changed_since_shot = false;
    let mut scans_at_shot = 0usize;
    let mut ended = false;
    // Until the first snapshot of the source is complete, the model is partial.
    let mut complete = false;
    while !stop.load(Ordering::Acquire) && !ended {
        match events.recv_timeout(Duration::from_millis(100)) {
            Ok(event) => {
                if let ViewerEvent::Connection(state) = &event {
                    eprintln!("texel-viewer: {}", state.describe());
                    ended = matches!(state, super::ConnectionState::Ended { .. });
                }
                match event {
                    ViewerEvent::Reset => {
                        renderer.clear_scans();
                        scans_at_shot = 0;
                        complete = false;
                    }
                    ViewerEvent::SnapshotComplete { .. } => complete = true,
                    _ => {}
                }
                changed_since_shot |= apply_to_model(&mut model, &event);
            }
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
        let path = options
            .dir
            .join(format!("snapshot-{:04}.png", summary.written.len() + 1));
        renderer.sync_model(&model)?;
        shoot(&mut renderer, &model, options, summary.written.len(), &path)?;
        println!("{} ({} scans)", path.display(), model.len());
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

fn shoot(
    renderer: &mut Renderer,
    model: &Model,
    options: &SnapshotOptions,
    index: usize,
    path: &Path,
) -> anyhow::Result<()> {
    let Some(newest) = model.scans().last() else {
        return Ok(());
    };
    let fov = options
        .fov_deg
        .or_else(|| newest.scan.as_deref().and_then(fov_y_deg_of_scan))
        .unwrap_or(50.0);
    let pose = match options.view {
        SnapshotView::Newest => newest.world_from_scan,
        SnapshotView::Orbit => orbit_pose(model, index).unwrap_or(newest.world_from_scan),
    };
    let camera = VirtualCamera::new(pose, fov, options.width, options.height)?;
    let (image, _) = renderer.render_to_image(&camera, &options.settings)?;
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
        let Some((a, b)) = s.scan.as_deref().and_then(texel::TexelScan::bounds) else {
            continue;
        };
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
