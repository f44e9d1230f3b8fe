//! `texel-viewer`: renders the texel model live from a daemon (`--connect`: a window,
//! or snapshots to a folder without a display), headless (`render`; `render --lod`
//! draws the level-of-detail tiles built from the scans instead), in a window on
//! a replayed capture (`open`), tone-maps radiance images (`tonemap`), and measures
//! the renderer (`bench`, `tradeoffs`).

mod tonemap_cli;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};
use texel::pose::parse_pose;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::capture_load::{LoadedCapture, load_capture};
use texel_viewer::composite::MAX_K;
use texel_viewer::display_mode::DisplayMode;
use texel_viewer::gpu::{GpuContext, RenderSettings, Renderer, Strategy};
use texel_viewer::headless::parse_views;
use texel_viewer::live;
use texel_viewer::live::snapshots::SnapshotView;
use texel_viewer::residency::Residency;
use texel_viewer::vdtm::{LiveVdtm, VdtmChoice, VdtmSettings, VdtmViewConfig};
use texel_viewer::zenoh_source::ZenohArgs;

#[derive(Parser)]
#[command(
    name = "texel-viewer",
    version,
    about = "Renders the texel model with view-dependent blending",
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    live: LiveArgs,
}

/// `texel-viewer --connect HOST:PORT`: the live model in a window, or, without a
/// display, snapshots of it in a folder.
#[derive(Args)]
struct LiveArgs {
    /// The daemon to follow.
    #[arg(long, value_name = "HOST:PORT", conflicts_with = "zenoh")]
    connect: Option<String>,
    /// Or the cameras on Zenoh.
    #[command(flatten)]
    zenoh: ZenohArgs,
    /// The daemon's token (needed when it listens beyond loopback).
    #[arg(long, default_value = "")]
    token: String,
    /// Draw the daemon's level-of-detail tiles (protocol version 3, over a second
    /// connection) and, below the finest tiles the view still finds too coarse, its
    /// scans; `L` in the window switches to the scans alone. Not over Zenoh (its
    /// cameras publish the scans alone).
    #[arg(long, conflicts_with = "zenoh")]
    lod: bool,
    /// With `--lod`: the tiles alone, no scans below the finest (a check box in the
    /// window's panel).
    #[arg(long, requires = "lod")]
    lod_tiles_only: bool,
    #[arg(long, default_value_t = 1280)]
    width: u32,
    #[arg(long, default_value_t = 800)]
    height: u32,
    /// Vertical field of view in degrees (default: estimated from the first scan).
    #[arg(long)]
    fov_deg: Option<f64>,
    #[command(flatten)]
    display: DisplayArgs,
    /// Write snapshots to this folder instead of opening a window (the default when
    /// there is no display: `texel-snapshots`).
    #[arg(long, value_name = "DIR")]
    snapshots: Option<PathBuf>,
    /// A snapshot at least this often while the model changes (seconds).
    #[arg(long, default_value_t = 5.0)]
    every_s: f64,
    /// And whenever this many new scans arrived (0: only by time).
    #[arg(long, default_value_t = 10)]
    every_scans: usize,
    /// Where snapshots are seen from.
    #[arg(long, value_enum, default_value = "newest")]
    snapshot_view: SnapshotView,
    /// Stop after this many snapshots.
    #[arg(long)]
    max_snapshots: Option<usize>,
    /// Window: write a read-back of the frame to this PNG, then exit.
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// Window: frames to draw before the screenshot.
    #[arg(long, default_value_t = 5)]
    frames: u32,
    /// Window: scans the model must hold before the screenshot (waits at most 60 s).
    #[arg(long, default_value_t = 1)]
    min_scans: usize,
    #[command(flatten)]
    pacing: PacingArgs,
}

/// How the window answers the hand: cheap frames within a budget while the view
/// moves, the full-quality frame once it is still.
#[derive(Args)]
struct PacingArgs {
    /// Budget of a frame while the view moves, ms: drawn at a reduced resolution
    /// (steered by the measured frame time) in a cheap mode; 0: every frame at full
    /// quality.
    #[arg(long, default_value_t = texel_viewer::adaptive::DEFAULT_INTERACTIVE_MS)]
    interactive_ms: f64,
    /// Once the full-quality frame is shown and nothing changes, stay this many
    /// seconds, print the GPU submissions made meanwhile (none when idle), and exit.
    #[arg(long, value_name = "SECONDS")]
    exit_when_idle: Option<f64>,
}

impl PacingArgs {
    /// The budget (`None`: adaptive quality off) and the idle exit.
    fn options(&self) -> anyhow::Result<(Option<f64>, Option<std::time::Duration>)> {
        if !(self.interactive_ms.is_finite() && self.interactive_ms >= 0.0) {
            bail!(
                "--interactive-ms {} must be finite and not negative",
                self.interactive_ms
            );
        }
        let idle = match self.exit_when_idle {
            Some(s) if s.is_finite() && (0.0..=86400.0).contains(&s) => {
                Some(std::time::Duration::from_secs_f64(s))
            }
            Some(s) => bail!("--exit-when-idle {s} must be within 0..=86400 seconds"),
            None => None,
        };
        Ok((
            (self.interactive_ms > 0.0).then_some(self.interactive_ms),
            idle,
        ))
    }
}

#[derive(Subcommand)]
enum Command {
    /// Render views of a capture's model to PNG files.
    Render(Box<RenderArgs>),
    /// Open a window on a capture's model.
    Open(OpenArgs),
    /// Tone-map a radiance image (OpenEXR) into a PNG.
    Tonemap(tonemap_cli::ToneMapArgs),
}

/// Where the model comes from: exactly one source.
#[derive(Args)]
struct SourceArgs {
    /// A capture (MCAP): every texel frame fused and placed by /texel/pose, else /truth/pose.
    #[arg(long, value_name = "RESULT.mcap", conflicts_with_all = ["connect", "zenoh"])]
    capture: Option<PathBuf>,
    /// A running daemon: its model once the snapshot is complete.
    #[arg(long, value_name = "HOST:PORT", conflicts_with = "zenoh")]
    connect: Option<String>,
    /// Or the cameras on Zenoh, merged.
    #[command(flatten)]
    zenoh: ZenohArgs,
}

/// Options of a `render --connect`.
#[derive(Args)]
struct FetchArgs {
    /// The daemon's token.
    #[arg(long, default_value = "", requires = "connect")]
    token: String,
    /// Wait until the model holds at least this many scans.
    #[arg(long, default_value_t = 1)]
    wait_scans: usize,
    /// Give up after this many seconds (connecting included).
    #[arg(long, default_value_t = 60.0)]
    timeout_s: f64,
}

/// A model to render, the field of view it suggests and its EO camera when known.
struct SourceModel {
    model: texel::model::Model,
    default_fov_deg: f64,
    eo_camera: Option<texel::PinholeCamera>,
    /// The EO camera's response curve, where the source's sensor model has one.
    eo_response: Option<texel::radiance::EoResponse>,
}

impl SourceArgs {
    fn load(&self, fetch: &FetchArgs) -> anyhow::Result<SourceModel> {
        // Held while the model is fetched through it.
        let gateway = if self.zenoh.zenoh {
            Some(self.zenoh.start()?)
        } else {
            None
        };
        let connect = gateway
            .as_ref()
            .map(|g| g.addr.clone())
            .or(self.connect.clone());
        match (&self.capture, &connect) {
            (Some(path), _) => {
                let loaded = load(path)?;
                Ok(SourceModel {
                    default_fov_deg: VirtualCamera::fov_y_deg_of(&loaded.eo_camera),
                    model: loaded.model,
                    eo_camera: Some(loaded.eo_camera),
                    eo_response: loaded.eo_response,
                })
            }
            (None, Some(addr)) => {
                let (model, eo_response) = texel_viewer::live::fetch::fetch_model_and_response(
                    addr,
                    &fetch.token,
                    fetch.wait_scans,
                    std::time::Duration::from_secs_f64(fetch.timeout_s.clamp(0.1, 86400.0)),
                )?;
                eprintln!("{addr}: {} scans", model.len());
                let default_fov_deg = model
                    .resident()
                    .next()
                    .and_then(|(_, scan)| texel_viewer::live::fov_y_deg_of_scan(scan))
                    .unwrap_or(50.0);
                Ok(SourceModel {
                    model,
                    default_fov_deg,
                    eo_camera: None,
                    eo_response,
                })
            }
            (None, None) => bail!("give a model source (--capture, --connect or --zenoh)"),
        }
    }
}

#[derive(Args, Clone)]
struct DisplayArgs {
    /// painter, best, blended, scan-colour or reliability (the scans composited per
    /// pixel), vdtm (the merged surface textured view-dependently, Debevec 1998), or
    /// points (the scans as splatted points with per-view depth maps, coloured from the
    /// acquisition views that see each pixel; Lechelek et al. 2019).
    #[arg(long, default_value = "blended")]
    mode: DisplayMode,
    /// vdtm: lower the weight of views that saw the surface coarser than the frame
    /// needs.
    #[arg(long)]
    vdtm_resolution_term: bool,
    /// vdtm: fade each view's weight to 0 over this many pixels at its image border
    /// (0: off).
    #[arg(long, default_value_t = 0.0)]
    vdtm_feather_px: f32,
    /// vdtm: texture from at most this many views, evenly spread over the scans.
    #[arg(long, default_value_t = VdtmViewConfig::default().max_views)]
    vdtm_max_views: usize,
    /// vdtm: the merged surface's finest voxel, metres.
    #[arg(long, default_value_t = VdtmViewConfig::default().voxel_m)]
    vdtm_voxel_m: f64,
    /// Fragments within this reliability of the best are blended.
    #[arg(long, default_value_t = 0.15)]
    blend_threshold: f32,
    /// At most this many fragments per pixel are ranked and blended (1..=8).
    #[arg(long, default_value_t = 4)]
    k: u32,
    /// Exponent of the range confidence.
    #[arg(long, default_value_t = 1.0)]
    range_gamma: f32,
    /// Keep stretched triangles (the paper removes them).
    #[arg(long)]
    keep_stretched: bool,
    /// Use the naive one-layer-per-scan composite instead of the k-buffer.
    #[arg(long)]
    naive: bool,
    /// With `--mode points`: render radiance (the scans whose EO frames record their
    /// exposure, made radiance by the sensor model's response curve, sRGB where it
    /// has none) and tone-map it (the flags below; Lechelek et al. 2019 §6).
    #[arg(long)]
    hdr: bool,
    #[command(flatten)]
    tone: tonemap_cli::ToneArgs,
    /// GPU memory the scans may hold, MiB: the scans the view needs are kept within
    /// it, the rest evicted and fetched again when needed.
    #[arg(long, value_name = "N", default_value_t = texel_viewer::residency::DEFAULT_BUDGET_MB)]
    gpu_budget_mb: u64,
}

impl DisplayArgs {
    fn settings(&self) -> anyhow::Result<RenderSettings> {
        if self.k == 0 || self.k > MAX_K {
            bail!("--k {} is outside 1..={MAX_K}", self.k);
        }
        if !self.blend_threshold.is_finite() || self.blend_threshold < 0.0 {
            bail!(
                "--blend-threshold {} must be finite and not negative",
                self.blend_threshold
            );
        }
        if !self.range_gamma.is_finite() || self.range_gamma <= 0.0 {
            bail!(
                "--range-gamma {} must be finite and positive",
                self.range_gamma
            );
        }
        let mut s = RenderSettings::with_mode(self.mode.scans_mode());
        s.composite.blend_threshold = self.blend_threshold;
        s.composite.k = self.k;
        s.range_gamma = self.range_gamma;
        s.keep_stretched = self.keep_stretched;
        s.points = self.mode == DisplayMode::Points;
        if self.hdr {
            if !s.points {
                bail!("--hdr renders radiance through the point proxy: add --mode points");
            }
            s.tone_map = Some(self.tone.settings()?);
        }
        if self.naive {
            s.strategy = Strategy::NaiveLayers;
        }
        Ok(s)
    }

    /// The VDTM mode's state, when it is the mode chosen; `camera`: the EO camera
    /// when known (else fitted from the scans).
    fn vdtm(&self, camera: Option<texel::PinholeCamera>) -> anyhow::Result<Option<VdtmChoice>> {
        if self.mode != DisplayMode::Vdtm {
            return Ok(None);
        }
        if !(self.vdtm_feather_px.is_finite() && self.vdtm_feather_px >= 0.0) {
            bail!(
                "--vdtm-feather-px {} must be finite and not negative",
                self.vdtm_feather_px
            );
        }
        if self.vdtm_max_views == 0 {
            bail!("--vdtm-max-views must be at least 1");
        }
        if !(self.vdtm_voxel_m.is_finite() && self.vdtm_voxel_m >= 0.005) {
            bail!(
                "--vdtm-voxel-m {} must be at least 0.005",
                self.vdtm_voxel_m
            );
        }
        let config = VdtmViewConfig {
            voxel_m: self.vdtm_voxel_m,
            max_views: self.vdtm_max_views,
            ..VdtmViewConfig::default()
        };
        Ok(Some(VdtmChoice {
            settings: VdtmSettings {
                resolution_term: self.vdtm_resolution_term,
                feather_px: self.vdtm_feather_px,
            },
            config,
            camera,
        }))
    }

    fn budget_bytes(&self) -> anyhow::Result<u64> {
        if self.gpu_budget_mb == 0 {
            bail!("--gpu-budget-mb must be at least 1");
        }
        Ok(Residency::budget_bytes_of_mb(self.gpu_budget_mb))
    }
}

#[derive(Args)]
struct RenderArgs {
    #[command(flatten)]
    source: SourceArgs,
    #[command(flatten)]
    fetch: FetchArgs,
    /// Virtual camera pose, world_from_eo: "x y z qx qy qz qw" (EO frame: x right, y down, z forward).
    #[arg(long, allow_hyphen_values = true, conflicts_with_all = ["acquisition", "views"])]
    pose: Option<String>,
    /// Render from scan N's own acquisition pose.
    #[arg(long, conflicts_with = "views")]
    acquisition: Option<u64>,
    /// A batch of views: lines "OUT.png x y z qx qy qz qw [fov_deg]".
    #[arg(long)]
    views: Option<PathBuf>,
    /// Vertical field of view in degrees (default: the model's EO camera).
    #[arg(long)]
    fov_deg: Option<f64>,
    #[arg(long)]
    width: u32,
    #[arg(long)]
    height: u32,
    #[command(flatten)]
    display: DisplayArgs,
    /// Output PNG (single view).
    #[arg(long, default_value = "view.png")]
    out: PathBuf,
    /// Draw the level-of-detail hierarchy (texel-lod, default settings) built from
    /// the model's scans: tiles selected for each view by screen-space error, all
    /// loaded before it is drawn, and below the finest tiles the view still finds too
    /// coarse, the scans themselves.
    #[arg(long)]
    lod: bool,
    /// With `--lod`: the tiles alone, no scans below the finest.
    #[arg(long, requires = "lod")]
    lod_tiles_only: bool,
}

#[derive(Args)]
struct OpenArgs {
    /// The capture to open: replayed through the daemon's pipeline in-process, scans
    /// appearing as the replay reaches them.
    capture: PathBuf,
    /// Replay speed, a multiple of real time.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Replay as fast as the pipeline goes.
    #[arg(long)]
    fast: bool,
    /// Load and fuse the whole capture first instead of replaying it.
    #[arg(long, conflicts_with_all = ["speed", "fast"])]
    load: bool,
    #[arg(long, default_value_t = 1280)]
    width: u32,
    #[arg(long, default_value_t = 800)]
    height: u32,
    #[command(flatten)]
    display: DisplayArgs,
    /// Write a read-back of the window's frame to this PNG after --frames frames, then exit.
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// Frames to draw before the screenshot.
    #[arg(long, default_value_t = 5)]
    frames: u32,
    /// Scans the model must hold before the screenshot (waits at most 60 s).
    #[arg(long, default_value_t = 1)]
    min_scans: usize,
    #[command(flatten)]
    pacing: PacingArgs,
}

fn load(path: &std::path::Path) -> anyhow::Result<LoadedCapture> {
    let loaded = load_capture(path).with_context(|| format!("loading {}", path.display()))?;
    for w in &loaded.warnings {
        eprintln!("warning: {w}");
    }
    eprintln!(
        "{}: {} scans placed by {}{}",
        path.display(),
        loaded.model.len(),
        loaded.pose_source.topic(),
        if loaded.unplaced > 0 {
            format!(" ({} frames without a pose were left out)", loaded.unplaced)
        } else {
            String::new()
        }
    );
    if loaded.model.is_empty() {
        bail!("{}: no scan could be placed", path.display());
    }
    Ok(loaded)
}

fn render(args: RenderArgs) -> anyhow::Result<()> {
    let settings = args.display.settings()?;
    let budget_bytes = args.display.budget_bytes()?;
    let loaded = args.source.load(&args.fetch)?;
    let default_fov = loaded.default_fov_deg;
    let mut views = Vec::new();
    if let Some(file) = &args.views {
        for v in parse_views(file)? {
            views.push((
                v.out,
                v.world_from_eo,
                v.fov_deg.or(args.fov_deg).unwrap_or(default_fov),
            ));
        }
    } else {
        let pose = match (&args.pose, args.acquisition) {
            (Some(text), _) => parse_pose(text).context("--pose")?,
            (None, Some(n)) => {
                loaded
                    .model
                    .get(n)
                    .with_context(|| {
                        format!(
                            "--acquisition {n}: the model has {} scans",
                            loaded.model.len()
                        )
                    })?
                    .world_from_scan
            }
            (None, None) => bail!("give --pose, --acquisition or --views"),
        };
        views.push((args.out.clone(), pose, args.fov_deg.unwrap_or(default_fov)));
    }
    let gpu = GpuContext::headless()?;
    if let Some(choice) = args.display.vdtm(loaded.eo_camera.clone())? {
        let vdtm = LiveVdtm::new(&gpu, choice);
        return render_vdtm(&gpu, vdtm, &loaded.model, &settings, &views, &args);
    }
    if args.lod {
        return render_lod(&gpu, loaded.model, &settings, budget_bytes, &views, &args);
    }
    let radiance = hdr_response(&settings, &loaded.model, loaded.eo_response.clone())?;
    let mut renderer = Renderer::new(&gpu);
    // Each view uploads what it needs within the budget (evicting what the previous
    // view needed and this one does not).
    let mut model = loaded.model;
    let mut residency = Residency::over_model(budget_bytes, &mut model);
    residency.options.hidden = settings.hidden.clone();
    for (out, pose, fov) in views {
        let camera = VirtualCamera::new(pose, fov, args.width, args.height)?;
        let resident = residency.step(&mut model, &mut renderer, &camera);
        if settings.points {
            renderer.prepare_points(&model, radiance.as_ref());
        }
        let (image, stats) = renderer.render_to_image(&camera, &settings)?;
        image
            .save(&out)
            .with_context(|| format!("writing {}", out.display()))?;
        eprintln!(
            "{}: {} scans drawn, {} outside the view, {} facing away; {}",
            out.display(),
            stats.drawn,
            stats.culled_frustum,
            stats.culled_facing,
            resident.describe()
        );
    }
    Ok(())
}

/// With `--hdr`: the response curve that makes the scans' EO frames radiance (the
/// sensor model's, sRGB where it has none); an error when no frame records its
/// exposure (nothing would be measured).
fn hdr_response(
    settings: &RenderSettings,
    model: &texel::model::Model,
    response: Option<texel::radiance::EoResponse>,
) -> anyhow::Result<Option<texel::radiance::EoResponse>> {
    if settings.tone_map.is_none() {
        return Ok(None);
    }
    let exposed = model
        .resident()
        .filter(|(_, scan)| scan.texture.exposure.is_some())
        .count();
    if exposed == 0 {
        bail!(
            "--hdr: no EO frame of the model records its exposure (/eo/exposure), so none \
             can be made radiance"
        );
    }
    Ok(Some(response.unwrap_or_else(|| {
        eprintln!(
            "--hdr: the sensor model has no response curve (texel-calib response); assuming \
             sRGB"
        );
        texel::radiance::EoResponse::srgb()
    })))
}

/// `render --mode vdtm`: the merged surface prepared once (Debevec 1998 §5-7), then
/// each view drawn from it (§8).
fn render_vdtm(
    gpu: &GpuContext,
    mut vdtm: LiveVdtm,
    model: &texel::model::Model,
    settings: &RenderSettings,
    views: &[(PathBuf, texel::Pose, f64)],
    args: &RenderArgs,
) -> anyhow::Result<()> {
    vdtm.update(gpu, model, true);
    eprintln!("{}", vdtm.status.describe());
    if let Some(e) = &vdtm.status.error {
        bail!("VDTM preprocessing failed: {e}");
    }
    for (out, pose, fov) in views {
        let camera = VirtualCamera::new(*pose, *fov, args.width, args.height)?;
        let started = std::time::Instant::now();
        let image = vdtm
            .render_to_image(gpu, &camera, settings.composite.background)?
            .context("VDTM: nothing prepared to draw")?;
        image
            .save(out)
            .with_context(|| format!("writing {}", out.display()))?;
        eprintln!(
            "{}: {} in {:.1} ms",
            out.display(),
            vdtm.settings.label(),
            started.elapsed().as_secs_f64() * 1e3
        );
    }
    Ok(())
}

/// `render --lod`: the model's scans fused into a level-of-detail hierarchy, each
/// view drawn from the tiles it selects (every wanted tile loaded first, no fade).
fn render_lod(
    gpu: &GpuContext,
    mut model: texel::model::Model,
    scan_settings: &RenderSettings,
    budget_bytes: u64,
    views: &[(PathBuf, texel::Pose, f64)],
    args: &RenderArgs,
) -> anyhow::Result<()> {
    use texel_viewer::tiles::source::MemorySource;
    use texel_viewer::tiles::{TileRenderer, TileSettings};
    let mut lod = texel_lod::LodModel::new(texel_lod::LodConfig::default())?;
    for (s, scan) in model.resident() {
        lod.add_scan(scan, &s.world_from_scan);
    }
    lod.rebuild(usize::MAX);
    let hierarchy = lod.hierarchy()?;
    eprintln!(
        "hierarchy: {} tiles in {} levels, {} triangles",
        hierarchy.nodes.len(),
        hierarchy.top_lod + 1,
        hierarchy.triangle_count()
    );
    let mut settings = TileSettings {
        fade_s: 0.0,
        budget_bytes,
        ..TileSettings::default()
    };
    settings.hybrid.enabled = !args.lod_tiles_only;
    let mut tiles = TileRenderer::new(gpu, MemorySource::new(&hierarchy), settings)?;
    // The scans below the finest tiles: held within the same budget as the scans
    // alone would be.
    let mut renderer = Renderer::new(gpu);
    let mut residency = Residency::over_model(budget_bytes, &mut model);
    residency.options.hidden = scan_settings.hidden.clone();
    for (out, pose, fov) in views {
        let camera = VirtualCamera::new(*pose, *fov, args.width, args.height)?;
        // Select and load until the selection wants nothing more, or nothing more
        // loads (failed tiles, the budget).
        loop {
            let stats = tiles.update(&camera, 0.0);
            let loaded = tiles.finish_loads(std::time::Duration::from_secs(60));
            if stats.tiles_wanted == 0 && stats.loads_in_flight == 0 {
                break;
            }
            if loaded == 0 && stats.uploaded == 0 {
                break;
            }
        }
        for e in tiles.take_errors() {
            eprintln!("{e}");
        }
        // Each frame's coverage feedback chooses more scans where the tiles still
        // showed (`tiles::coverage`): frames until it has read every pixel once,
        // holding what is wanted before each, as the window does; then one more,
        // which is written.
        let mut frame = None;
        for _ in 0..=settings.hybrid.feedback_rounds_to_read_every_pixel() {
            residency.options.only = Some(tiles.scans_wanted(model.scans(), &camera));
            let resident = residency.step(&mut model, &mut renderer, &camera);
            let drawn = tiles.render_over_scans_to_image(
                &mut renderer,
                scan_settings,
                model.scans(),
                &camera,
                0.0,
            )?;
            frame = Some((drawn, resident));
        }
        let Some(((image, stats, hybrid), resident)) = frame else {
            anyhow::bail!("no frame drawn");
        };
        let (demand, given_up) = tiles.coverage_counts();
        image
            .save(out)
            .with_context(|| format!("writing {}", out.display()))?;
        eprintln!(
            "{}: {} tiles drawn, {} triangles, {} tiles resident ({} bytes); {} finest tiles show their scans, {} scans drawn, {} points where tiles still showed ({} given up); {}",
            out.display(),
            stats.tiles_drawn,
            stats.triangles_drawn,
            stats.resident_tiles,
            stats.resident_bytes,
            stats.tiles_with_scans,
            hybrid.scans.map_or(0, |s| s.drawn),
            demand,
            given_up,
            resident.describe()
        );
    }
    Ok(())
}

fn open(args: OpenArgs) -> anyhow::Result<()> {
    let settings = args.display.settings()?;
    let (interactive_ms, exit_when_idle) = args.pacing.options()?;
    let budget_bytes = args.display.budget_bytes()?;
    let mut eo_camera = None;
    let mut eo_response = None;
    let (events, fov, keep_alive): (_, Option<f64>, Box<dyn std::any::Any>) = if args.load {
        let loaded = load(&args.capture)?;
        let fov = VirtualCamera::fov_y_deg_of(&loaded.eo_camera);
        eo_camera = Some(loaded.eo_camera);
        eo_response = loaded.eo_response;
        (
            live::spawn_model_feed(loaded.model),
            Some(fov),
            Box::new(()),
        )
    } else {
        if !(args.speed.is_finite() && args.speed > 0.0) {
            bail!("--speed {} must be finite and positive", args.speed);
        }
        let (tx, rx) = std::sync::mpsc::sync_channel(live::EVENT_QUEUE);
        let handle = live::replay::spawn(
            live::replay::ReplayOptions {
                capture: args.capture.clone(),
                speed: args.speed,
                fast: args.fast,
            },
            tx,
        );
        (rx, None, Box::new(handle))
    };
    let result = texel_viewer::app::run(texel_viewer::app::AppOptions {
        title: format!("texel-viewer: {}", args.capture.display()),
        width: args.width,
        height: args.height,
        fov_deg: fov,
        settings,
        events,
        commands: None,
        budget_bytes,
        follow_newest: false,
        screenshot: args.screenshot.map(|p| (p, args.frames, args.min_scans)),
        tiles: None,
        scans_below_tiles: true,
        vdtm: args.display.vdtm(eo_camera)?,
        eo_response,
        interactive_ms,
        exit_when_idle,
    });
    drop(keep_alive);
    result
}

/// Whether a window can be opened here.
fn have_display() -> bool {
    ["DISPLAY", "WAYLAND_DISPLAY"]
        .iter()
        .any(|v| std::env::var_os(v).is_some_and(|s| !s.is_empty()))
}

/// Sets the flag on SIGINT or SIGTERM (snapshot mode stops cleanly).
fn stop_on_signal() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let set = Arc::clone(&flag);
    let spawned = std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            let Ok(rt) = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            else {
                return;
            };
            rt.block_on(async {
                use tokio::signal::unix::{SignalKind, signal};
                let (Ok(mut term), Ok(mut int)) = (
                    signal(SignalKind::terminate()),
                    signal(SignalKind::interrupt()),
                ) else {
                    return;
                };
                tokio::select! {
                    _ = term.recv() => {}
                    _ = int.recv() => {}
                }
                set.store(true, Ordering::Release);
            });
        });
    if spawned.is_err() {
        eprintln!("warning: no signal handling; stop with SIGKILL");
    }
    flag
}

fn connect(args: LiveArgs, addr: String) -> anyhow::Result<()> {
    let settings = args.display.settings()?;
    let (interactive_ms, exit_when_idle) = args.pacing.options()?;
    let budget_bytes = args.display.budget_bytes()?;
    let (tx, rx) = std::sync::mpsc::sync_channel(live::EVENT_QUEUE);
    let (commands, command_rx) = std::sync::mpsc::sync_channel(live::COMMAND_QUEUE);
    let mut connection = live::connection::spawn(
        live::connection::ConnectOptions::new(addr.clone(), args.token.clone()),
        tx,
        command_rx,
    );
    let snapshots = args
        .snapshots
        .clone()
        .or_else(|| (!have_display()).then(|| PathBuf::from("texel-snapshots")));
    let result = match snapshots {
        Some(dir) => {
            if !(args.every_s.is_finite() && args.every_s > 0.0) {
                bail!("--every-s {} must be finite and positive", args.every_s);
            }
            std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
            let shown = std::fs::canonicalize(&dir).unwrap_or_else(|_| dir.clone());
            println!(
                "texel-viewer: no window{}; writing snapshots of the live model from {addr} to {}",
                if args.snapshots.is_some() {
                    ""
                } else {
                    " (no DISPLAY or WAYLAND_DISPLAY)"
                },
                shown.display()
            );
            let stop = stop_on_signal();
            let summary = live::snapshots::run(
                &rx,
                &live::snapshots::SnapshotOptions {
                    dir: dir.clone(),
                    every: std::time::Duration::from_secs_f64(args.every_s),
                    every_scans: args.every_scans,
                    view: args.snapshot_view,
                    width: args.width,
                    height: args.height,
                    fov_deg: args.fov_deg,
                    settings,
                    max_snapshots: args.max_snapshots,
                    budget_bytes,
                    commands: Some(commands),
                    vdtm: args.display.vdtm(None)?,
                },
                &stop,
            )?;
            println!(
                "texel-viewer: {} snapshots of up to {} scans in {}",
                summary.written.len(),
                summary.scans,
                std::fs::canonicalize(&dir).unwrap_or(dir).display()
            );
            Ok(())
        }
        None => texel_viewer::app::run(texel_viewer::app::AppOptions {
            title: format!("texel-viewer: {addr}"),
            width: args.width,
            height: args.height,
            fov_deg: args.fov_deg,
            settings,
            events: rx,
            commands: Some(commands),
            budget_bytes,
            follow_newest: true,
            screenshot: args.screenshot.map(|p| (p, args.frames, args.min_scans)),
            tiles: if args.lod {
                Some(connect_tiles(&addr, &args.token)?)
            } else {
                None
            },
            scans_below_tiles: !args.lod_tiles_only,
            vdtm: args.display.vdtm(None)?,
            eo_response: None,
            interactive_ms,
            exit_when_idle,
        }),
    };
    connection.stop();
    result
}

/// The tile connection of `--lod`.
fn connect_tiles(
    addr: &str,
    token: &str,
) -> anyhow::Result<texel_viewer::tiles::net::NetTileSource> {
    use std::net::ToSocketAddrs;
    let socket = addr
        .to_socket_addrs()
        .with_context(|| format!("resolving {addr}"))?
        .next()
        .with_context(|| format!("{addr} resolves to no address"))?;
    texel_viewer::tiles::net::NetTileSource::connect(
        socket,
        token,
        std::time::Duration::from_secs(5),
    )
    .with_context(|| format!("the level-of-detail tiles of {addr}"))
}

/// Mesa's device-selection Vulkan layer connects to Wayland to find the display's
/// GPU and, without a runtime directory, prints "XDG_RUNTIME_DIR is invalid or not
/// set" (twice) to a newcomer's terminal; wgpu chooses the adapter itself, so the
/// layer is switched off there (its own switch, `NODEVICE_SELECT`).
fn quiet_platform_layers() {
    let runtime_dir =
        std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|d| std::path::Path::new(&d).is_dir());
    if !runtime_dir && std::env::var_os("NODEVICE_SELECT").is_none() {
        // SAFETY: the first thing `main` does, before any thread exists, so nothing
        // reads the environment concurrently.
        #[allow(unsafe_code)]
        unsafe {
            std::env::set_var("NODEVICE_SELECT", "1");
        }
    }
}

fn main() -> anyhow::Result<()> {
    quiet_platform_layers();
    let cli = Cli::parse();
    match cli.command {
        Some(Command::Render(a)) => render(*a),
        Some(Command::Open(a)) => open(a),
        Some(Command::Tonemap(a)) => tonemap_cli::tonemap(a),
        None if cli.live.zenoh.zenoh => {
            let source = cli.live.zenoh.start()?;
            let addr = source.addr.clone();
            connect(cli.live, addr)
        }
        None => match cli.live.connect.clone() {
            Some(addr) => connect(cli.live, addr),
            None => bail!("give --connect HOST:PORT, --zenoh or a command (see --help)"),
        },
    }
}
