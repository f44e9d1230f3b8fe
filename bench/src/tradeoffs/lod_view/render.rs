//! The two ways of drawing the street that `lod-view` compares, driven headless:
//! the level-of-detail tiles (`TileRenderer` over a `MemorySource`, loading what
//! each view selects until nothing is wanted) and the registered scans as the viewer
//! holds them (the residency planner choosing scans for the view within the viewer's
//! default GPU budget, drawn by the scan `Renderer` with view-dependent blending);
//! plus the cameras (close view, overview, the fly-through between them, held-out
//! poses) and the truth mask.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use nalgebra::{Point3, Vector3};
use texel::model::{ModelScan, ScanId, ScanListing};
use texel::{Pose, TexelScan};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{GpuContext, RenderSettings, Renderer, scan_gpu_bytes};
use texel_viewer::residency::{DataState, Plan, PlanOptions, PlanScan, plan};
use texel_viewer::tiles::source::MemorySource;
use texel_viewer::tiles::{TileFrameStats, TileRenderer, TileSettings, look_at};

use crate::tradeoffs::rendering::Config;

/// Image size of every render (as the rendering section).
pub const WIDTH: u32 = 320;
pub const HEIGHT: u32 = 240;
/// One frame at 30 Hz, seconds.
pub const FRAME_S: f64 = 1.0 / 30.0;
/// Where nothing is drawn (no scene colour is pure magenta).
pub const BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];
pub const BACKGROUND_RGB: [u8; 3] = [255, 0, 255];

/// The tile renderer's settings: the viewer's defaults, with `fade_s`, `budget_bytes`
/// and the magenta background.
pub fn tile_settings(fade_s: f64, budget_bytes: u64) -> TileSettings {
    TileSettings {
        fade_s,
        budget_bytes,
        background: BACKGROUND,
        ..TileSettings::default()
    }
}

/// The scan renderer's settings: `blended` at the rendering section's defaults.
pub fn scan_settings() -> RenderSettings {
    Config::base(Mode::Blended).settings()
}

/// Median of `v` (NaN when empty).
pub fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s.get(s.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Updates (loading what is wanted, waiting for it) until the selection wants
/// nothing and no fade is under way, at most `max_frames` updates. Returns the
/// updates it took, the time after them and whether it settled.
pub fn settle(
    r: &mut TileRenderer<MemorySource>,
    camera: &VirtualCamera,
    mut now_s: f64,
    max_frames: usize,
) -> (usize, f64, bool) {
    for i in 0..max_frames {
        let stats = r.update(camera, now_s);
        now_s += FRAME_S;
        r.finish_loads(Duration::from_secs(60));
        if stats.tiles_wanted == 0 && stats.loads_in_flight == 0 && !stats.fading {
            return (i + 1, now_s, true);
        }
    }
    (max_frames, now_s, false)
}

/// One view drawn one way: the median frame time and what the frame held and drew.
#[derive(Debug, Clone, Copy, Default)]
pub struct ViewFigures {
    /// Median wall time of one frame rendered into an image and read back, ms.
    pub frame_ms: f64,
    /// GPU bytes of the resident data (tiles, or scans' buffers and textures).
    pub data_bytes: u64,
    /// GPU bytes of the frame's size-dependent targets (k-buffer, depth), scans only.
    pub target_bytes: u64,
    /// Tiles or scans resident.
    pub resident: usize,
    /// Tiles or scans drawn.
    pub drawn: usize,
    pub triangles: u64,
    /// Tiles: updates until nothing was wanted. Scans: scans the view needed.
    pub needed: usize,
    /// Scans only: needed scans the budget left out.
    pub left_out: usize,
    /// Whether the selection settled (tiles) or every needed scan fit (scans).
    pub complete: bool,
    /// Tiles with scans below: finest tiles showing their scans, and scans drawn.
    pub tiles_with_scans: usize,
    pub scans_drawn: usize,
}

/// The view with level of detail, from an empty cache: tiles loaded until the
/// selection wants nothing, then `timed` frames after two warm-up frames.
pub fn lod_view(
    gpu: &GpuContext,
    source: &MemorySource,
    camera: &VirtualCamera,
    settings: TileSettings,
    timed: usize,
) -> Result<(ViewFigures, image::RgbaImage)> {
    let mut r = TileRenderer::new(gpu, source.clone(), settings)?;
    let (updates, mut now_s, settled) = settle(&mut r, camera, 0.0, 400);
    let mut image = image::RgbaImage::new(camera.width, camera.height);
    let mut stats = TileFrameStats::default();
    for _ in 0..2 {
        (image, stats) = r.render_to_image(camera, now_s)?;
        now_s += FRAME_S;
    }
    let mut times = Vec::with_capacity(timed);
    for _ in 0..timed.max(1) {
        let started = Instant::now();
        (image, stats) = r.render_to_image(camera, now_s)?;
        times.push(started.elapsed().as_secs_f64() * 1e3);
        now_s += FRAME_S;
    }
    let errors = r.take_errors();
    anyhow::ensure!(errors.is_empty(), "tile loads failed: {errors:?}");
    Ok((
        ViewFigures {
            frame_ms: median(&times),
            data_bytes: stats.resident_bytes,
            target_bytes: 0,
            resident: stats.resident_tiles,
            drawn: stats.tiles_drawn,
            triangles: stats.triangles_drawn,
            needed: updates,
            left_out: 0,
            complete: settled,
            tiles_with_scans: 0,
            scans_drawn: 0,
        },
        image,
    ))
}

/// The view with level of detail and the scans below the finest tiles the view
/// still finds too coarse: tiles loaded until the selection wants nothing, the
/// scans those tiles want made resident (the planner, restricted to them, within
/// the holder's budget), the cross-fade to them run out, then `timed` frames, each
/// updating, choosing the scans and drawing both.
pub fn hybrid_view(
    gpu: &GpuContext,
    source: &MemorySource,
    holder: &mut ScanHolder<'_>,
    camera: &VirtualCamera,
    settings: TileSettings,
    timed: usize,
) -> Result<(ViewFigures, image::RgbaImage)> {
    let scan_settings = scan_settings();
    let mut r = TileRenderer::new(gpu, source.clone(), settings)?;
    let (updates, mut now_s, settled) = settle(&mut r, camera, 0.0, 400);
    // Warm-up, the scans' fade (0.25 s by default) run out, then the coverage
    // feedback's rounds: before each frame the wanted scans are made resident, as
    // the window does.
    let warm_up = 2
        + (settings.fade_s.max(0.0) / FRAME_S).ceil() as usize
        + settings.hybrid.feedback_rounds_to_read_every_pixel();
    let mut frame = None;
    let mut plan = None;
    let mut times = Vec::with_capacity(timed);
    for i in 0..warm_up + timed.max(1) {
        // Timed frames draw what the warm-up made resident, as a steady view does.
        let is_timed = i >= warm_up;
        if !is_timed {
            plan = Some(hold_wanted(&r, holder, camera)?);
        }
        let started = Instant::now();
        frame = Some(r.render_over_scans_to_image(
            &mut holder.renderer,
            &scan_settings,
            &holder.model_scans,
            camera,
            now_s,
        )?);
        if is_timed {
            times.push(started.elapsed().as_secs_f64() * 1e3);
        }
        now_s += FRAME_S;
    }
    let plan = plan.context("no warm-up frame")?;
    let errors = r.take_errors();
    anyhow::ensure!(errors.is_empty(), "tile loads failed: {errors:?}");
    let (image, stats, hybrid) = frame.context("no frame drawn")?;
    let scans = hybrid.scans.unwrap_or_default();
    let scan_triangles = if hybrid.scans.is_some() {
        let mut only = scan_settings.clone();
        only.only = Some(r.scans_wanted(&holder.model_scans, camera));
        holder.triangles_drawn(camera, &only)
    } else {
        0
    };
    Ok((
        ViewFigures {
            frame_ms: median(&times),
            data_bytes: stats.resident_bytes + scans.scan_bytes,
            target_bytes: scans.target_memory.total(),
            resident: stats.resident_tiles + scans.scans,
            drawn: stats.tiles_drawn + scans.drawn,
            triangles: stats.triangles_drawn + scan_triangles,
            needed: updates,
            left_out: plan.left_out.len(),
            complete: settled && plan.left_out.is_empty(),
            tiles_with_scans: stats.tiles_with_scans,
            scans_drawn: scans.drawn,
        },
        image,
    ))
}

/// Makes the scans the tiles want resident (the planner restricted to them).
fn hold_wanted(
    r: &TileRenderer<MemorySource>,
    holder: &mut ScanHolder<'_>,
    camera: &VirtualCamera,
) -> Result<Plan> {
    let wanted = r.scans_wanted(&holder.model_scans, camera);
    holder.set_only(Some(wanted));
    let hold = holder.hold_for(camera);
    holder.set_only(None);
    let (plan, _) = hold?;
    holder.renderer.release_targets();
    Ok(plan)
}

/// The placed scans as the viewer holds them: a scan renderer with the scans the
/// residency planner chooses for the current view within a byte budget.
pub struct ScanHolder<'a> {
    pub renderer: Renderer,
    /// The scans as a model lists them (no data), for choosing the scans below tiles.
    pub model_scans: Vec<ModelScan>,
    scans: &'a [(Arc<TexelScan>, Pose)],
    plan_scans: Vec<PlanScan>,
    options: PlanOptions,
}

impl<'a> ScanHolder<'a> {
    pub fn new(gpu: &GpuContext, scans: &'a [(Arc<TexelScan>, Pose)], budget_bytes: u64) -> Self {
        let plan_scans: Vec<PlanScan> = scans
            .iter()
            .enumerate()
            .map(|(i, (scan, pose))| PlanScan {
                id: i as ScanId,
                listing: ScanListing::of_scan(scan, 0, 0.0),
                world_from_scan: *pose,
                bytes: scan_gpu_bytes(scan),
                state: DataState::Held,
            })
            .collect();
        let model_scans = plan_scans
            .iter()
            .map(|s: &PlanScan| ModelScan {
                id: s.id,
                scan: None,
                listing: s.listing,
                world_from_scan: s.world_from_scan,
                revisions: 0,
            })
            .collect();
        Self {
            renderer: Renderer::new(gpu),
            model_scans,
            scans,
            plan_scans,
            options: PlanOptions::new(budget_bytes),
        }
    }

    /// Restricts the scans the planner may choose (`None`: any).
    pub fn set_only(&mut self, only: Option<BTreeSet<ScanId>>) {
        self.options.only = only;
    }

    /// GPU bytes of every scan, were they all uploaded.
    pub fn all_bytes(&self) -> u64 {
        self.plan_scans.iter().map(|s| s.bytes).sum()
    }

    /// Plans residency for `camera` and carries it out: scans not chosen are dropped
    /// from the GPU, chosen ones uploaded. Returns the plan and whether the resident
    /// set changed.
    pub fn hold_for(&mut self, camera: &VirtualCamera) -> Result<(Plan, bool)> {
        let p = plan(&self.plan_scans, camera, &self.options);
        let keep: BTreeSet<ScanId> = p.selected.iter().copied().collect();
        let mut changed = false;
        let resident: Vec<ScanId> = self.renderer.scan_ids().collect();
        for id in resident {
            if !keep.contains(&id) {
                self.renderer.remove_scan(id);
                changed = true;
                if let Some(s) = self.plan_scans.get_mut(id as usize) {
                    s.state = DataState::Held;
                }
            }
        }
        for &id in &p.selected {
            if self.renderer.has_scan(id) {
                continue;
            }
            let (scan, pose) = self
                .scans
                .get(id as usize)
                .with_context(|| format!("the planner chose scan {id}, which is not listed"))?;
            self.renderer.add_scan(id, scan, *pose)?;
            changed = true;
            if let Some(s) = self.plan_scans.get_mut(id as usize) {
                s.state = DataState::OnGpu;
            }
        }
        Ok((p, changed))
    }

    /// Triangles of the scans drawn from `camera` (before the stretched-triangle
    /// filter, so an upper bound on those rasterised).
    pub fn triangles_drawn(&self, camera: &VirtualCamera, settings: &RenderSettings) -> u64 {
        let (visible, _) = self.renderer.cull(camera, settings);
        visible
            .iter()
            .filter_map(|id| self.scans.get(*id as usize))
            .map(|(scan, _)| scan.triangles.len() as u64)
            .sum()
    }
}

/// The view with the scans only: the planner's scans for it uploaded, then `timed`
/// frames after two warm-up frames.
pub fn scans_view(
    holder: &mut ScanHolder<'_>,
    camera: &VirtualCamera,
    timed: usize,
) -> Result<(ViewFigures, image::RgbaImage)> {
    let settings = scan_settings();
    let (p, _) = holder.hold_for(camera)?;
    holder.renderer.release_targets();
    // Two warm-up frames, as with the tiles.
    holder.renderer.render_to_image(camera, &settings)?;
    let (mut image, mut stats) = holder.renderer.render_to_image(camera, &settings)?;
    let mut times = Vec::with_capacity(timed);
    for _ in 0..timed.max(1) {
        let started = Instant::now();
        (image, stats) = holder.renderer.render_to_image(camera, &settings)?;
        times.push(started.elapsed().as_secs_f64() * 1e3);
    }
    Ok((
        ViewFigures {
            frame_ms: median(&times),
            data_bytes: stats.scan_bytes,
            target_bytes: stats.target_memory.total(),
            resident: stats.scans,
            drawn: stats.drawn,
            triangles: holder.triangles_drawn(camera, &settings),
            needed: p.needed,
            left_out: p.left_out.len(),
            complete: p.left_out.is_empty(),
            tiles_with_scans: 0,
            scans_drawn: stats.drawn,
        },
        image,
    ))
}

/// A camera at the fixed size with the EO camera's field of view.
pub fn camera(pose: Pose, fov_deg: f64) -> Result<VirtualCamera> {
    Ok(VirtualCamera::new(pose, fov_deg, WIDTH, HEIGHT)?)
}

/// A pose at `eye` looking at `target`, z up.
pub fn looking(eye: Vector3<f64>, target: Vector3<f64>) -> Result<Pose> {
    look_at(eye.into(), target.into(), [0.0, 0.0, 1.0])
        .with_context(|| format!("no camera from {eye:?} looking at {target:?}"))
}

/// The views measured and the fly-through between them.
#[derive(Debug, Clone, Copy)]
pub struct Views {
    pub close_eye: Vector3<f64>,
    pub close_target: Vector3<f64>,
    /// Distance from the close eye to the surface it looks at, metres.
    pub close_hit_m: f64,
    pub overview_eye: Vector3<f64>,
    pub overview_target: Vector3<f64>,
    /// The walked street: x range of the true poses.
    pub walk_x: (f64, f64),
}

impl Views {
    /// The close view: at the middle frame of the walk, 1.7 m up, looking 40 degrees
    /// off the street's axis towards the nearer facade (what it hits, or 8 m out).
    /// The overview: above and to the side of the walk's middle, far enough that the
    /// whole walked length (at least 20 m, plus 10 m) is in view.
    pub fn of(sim: &sims::Simulator) -> Self {
        let n = sim.frame_count().max(1);
        let eyes: Vec<Vector3<f64>> = (0..n)
            .map(|i| sim.true_pose(i).translation.vector)
            .collect();
        let x0 = eyes.iter().map(|e| e.x).fold(f64::INFINITY, f64::min);
        let x1 = eyes.iter().map(|e| e.x).fold(f64::NEG_INFINITY, f64::max);
        let mid = eyes.get(n / 2).copied().unwrap_or_else(Vector3::zeros);
        let close_eye = Vector3::new(mid.x, mid.y, 1.7);
        let side = if mid.y >= 0.0 { 1.0 } else { -1.0 };
        let angle = 40f64.to_radians();
        let dir = Vector3::new(angle.cos(), side * angle.sin(), 0.0);
        let close_hit_m = sim
            .scene()
            .cast_ray(Point3::from(close_eye), dir)
            .map_or(f64::NAN, |h| h.distance_m);
        let reach = if close_hit_m.is_finite() {
            close_hit_m
        } else {
            8.0
        };
        let close_target = close_eye + dir * reach;
        let length = (x1 - x0).max(20.0) + 10.0;
        let overview_target = Vector3::new(0.5 * (x0 + x1), 0.0, 0.0);
        let overview_eye = overview_target + Vector3::new(-0.35, -0.75, 0.65) * length;
        Self {
            close_eye,
            close_target,
            close_hit_m,
            overview_eye,
            overview_target,
            walk_x: (x0, x1),
        }
    }

    pub fn close(&self) -> Result<Pose> {
        looking(self.close_eye, self.close_target)
    }

    pub fn overview(&self) -> Result<Pose> {
        looking(self.overview_eye, self.overview_target)
    }

    /// The fly-through at `s` (0: the close view, 1: the overview): the target moves
    /// linearly, the direction from it turns linearly, the distance grows
    /// geometrically (the same relative motion every frame).
    pub fn fly(&self, s: f64) -> Result<Pose> {
        let s = s.clamp(0.0, 1.0);
        let target = self.close_target + (self.overview_target - self.close_target) * s;
        let d0 = (self.close_eye - self.close_target).norm().max(0.1);
        let d1 = (self.overview_eye - self.overview_target).norm().max(0.1);
        let u0 = (self.close_eye - self.close_target) / d0;
        let u1 = (self.overview_eye - self.overview_target) / d1;
        let dir = (u0 + (u1 - u0) * s)
            .try_normalize(1e-9)
            .context("the fly-through turns through zero")?;
        let dist = d0 * (d1 / d0).powf(s);
        looking(target + dir * dist, target)
    }
}

/// Held-out poses: `near`, halfway between neighbouring frames of the walk (the
/// rendering section's `between` poses); `far`, from the same frames raised 8 m and
/// pulled back 12 m along the walk, looking at what the frame looked at 8 m out.
pub fn held_out(sim: &sims::Simulator, count: usize) -> Vec<(&'static str, Pose)> {
    let mut out: Vec<(&'static str, Pose)> =
        crate::tradeoffs::rendering::held_out_poses(sim, 3 * count)
            .into_iter()
            .filter(|p| p.kind == "between")
            .map(|p| ("near", p.world_from_eo))
            .collect();
    let n = sim.frame_count();
    if n < 2 {
        return out;
    }
    for j in 0..count {
        let i = (j * (n - 1)) / count.max(1);
        let pose = sim.true_pose(i);
        let eye = pose.translation.vector;
        let ahead = sim.true_pose((i + 15).min(n - 1)).translation.vector;
        let behind = sim.true_pose(i.saturating_sub(15)).translation.vector;
        let mut walk = ahead - behind;
        walk.z = 0.0;
        let walk = walk.try_normalize(1e-9).unwrap_or_else(Vector3::x);
        let target = eye + pose.rotation * Vector3::z() * 8.0;
        let far_eye = eye - walk * 12.0 + Vector3::z() * 8.0;
        if let Ok(p) = looking(far_eye, target) {
            out.push(("far", p));
        }
    }
    out
}

/// Per pixel whether the simulator's scene has geometry along the camera's ray.
pub fn truth_geometry(scene: &sims::Scene, camera: &VirtualCamera) -> Vec<bool> {
    let origin = Point3::from(camera.world_from_eo.translation.vector);
    let mut mask = Vec::with_capacity((camera.width * camera.height) as usize);
    for y in 0..camera.height {
        for x in 0..camera.width {
            let dir = camera.world_from_eo.rotation * camera.pixel_ray_view(x, y);
            mask.push(scene.cast_ray(origin, dir).is_some());
        }
    }
    mask
}

/// RGB bytes of an RGBA image.
pub fn rgb(image: &image::RgbaImage) -> Vec<u8> {
    image.pixels().flat_map(|p| [p[0], p[1], p[2]]).collect()
}

/// Per pixel whether a render drew anything.
pub fn covered(image: &image::RgbaImage) -> Vec<bool> {
    image
        .pixels()
        .map(|p| [p[0], p[1], p[2]] != BACKGROUND_RGB)
        .collect()
}
