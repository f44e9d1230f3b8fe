//! `texel-bench tradeoffs lod-view`: what the level-of-detail tree does for the
//! viewer on the street, against drawing the scans. The street capture (the first
//! N frames of the walk, cached as the `lod` section caches it) is read with every
//! scan placed at its true pose and fused into a `texel_lod::LodModel` with the
//! default settings; the viewer then draws the same street two ways, headless at
//! 320x240: the tiles (`texel_viewer::tiles::TileRenderer` over a `MemorySource`
//! of the hierarchy, the viewer's default selection and 256 MiB budget) and the
//! scans only (the residency planner choosing the scans a view needs within the
//! viewer's default 512 MiB, drawn `blended` by the scan renderer). Measured:
//!
//! 1. frame time (median wall time of a frame rendered into an image and read back,
//!    after warm-up) and GPU bytes held, for a close view at street level and an
//!    overview of the whole walked street, with tiles drawn and triangles;
//! 2. PSNR against the simulator's own render at held-out poses, near (halfway
//!    between frames of the walk) and far (raised and pulled back), over the pixels
//!    where the truth has geometry and both renders drew;
//! 3. popping on a fly-through from the close view to the overview, every tile
//!    resident: the largest frame-to-frame change at switch frames with a 0.25 s
//!    cross-fade and without, against the same fly-through with the scans only and
//!    with the finest tiles only, and the change a switch alone makes, held still.
//!
//! Writes the "Level of detail in the viewer" section of `docs/tradeoffs.md`.

mod render;
mod report;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use texel::{PinholeCamera, Pose, TexelScan};
use texel_lod::{Hierarchy, LodConfig, LodModel};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::gpu::GpuContext;
use texel_viewer::residency::DEFAULT_BUDGET_MB;
use texel_viewer::tiles::cache::tile_gpu_bytes;
use texel_viewer::tiles::measure::{
    PopMeasure, SwitchMeasure, popping_excess, popping_measure, switch_measure,
};
use texel_viewer::tiles::source::MemorySource;
use texel_viewer::tiles::{TileRenderer, TileSettings};

use self::render::{
    FRAME_S, HEIGHT, ScanHolder, ViewFigures, Views, WIDTH, camera, covered, held_out, hybrid_view,
    lod_view, rgb, scan_settings, scans_view, settle, tile_settings, truth_geometry,
};
use crate::tradeoffs::lod::StreetArgs;
use crate::tradeoffs::registration::data::simulator;
use crate::tradeoffs::rendering::metrics;
use crate::tradeoffs::rendering::report::write_tradeoffs_section;

#[derive(Debug, Clone, clap::Args)]
pub struct LodViewArgs {
    /// Fewer frames (300), poses and frames timed, for a quick look (docs/ is left
    /// alone).
    #[arg(long)]
    pub quick: bool,
    #[command(flatten)]
    pub street: StreetArgs,
    /// Also write, per held-out pose, the truth and both renders as PNGs under this
    /// folder, to look at what the PSNR scores.
    #[arg(long)]
    pub images: Option<PathBuf>,
}

/// The tile renderer's default GPU budget (`TileSettings::default`).
const TILE_BUDGET: u64 = 256 << 20;
/// Frames of the fly-through (4 s at 30 Hz).
const FLY_FRAMES: usize = 120;

/// Everything measured, for the report.
struct Figures {
    frames: usize,
    scans: usize,
    adapter: String,
    build_s: f64,
    tiles: usize,
    levels: u8,
    tile_bytes_all: u64,
    scan_bytes_all: u64,
    views: Views,
    /// [close, overview] x [LOD with scans below, tiles alone, scans only].
    view: [[ViewFigures; 3]; 2],
    /// The close view with LOD at each count of scans per tile.
    close_sweep: Vec<(Sweep, ViewFigures)>,
    quality: Vec<PoseQuality>,
    pop: Popping,
    timings: Vec<(&'static str, f64)>,
}

struct PoseQuality {
    kind: &'static str,
    /// LOD with the scans below the finest tiles, the tiles alone, the scans only.
    hybrid_db: f64,
    lod_db: f64,
    scans_db: f64,
    /// Shares of the truth's geometry pixels drawn by each, and scored.
    hybrid_cover: f64,
    lod_cover: f64,
    scans_cover: f64,
    /// Finest tiles showing their scans, and scans drawn with them.
    tiles_with_scans: usize,
    hybrid_scans: usize,
    /// LOD at each count of scans per tile: the count, PSNR dB and scans drawn.
    swept_db: Vec<(Sweep, f64, usize)>,
    scored: f64,
    /// Scans the planner left out of the budget at this pose.
    left_out: usize,
}

struct Popping {
    /// The tiles with the scans below (fade 0.25 s), the scans only at its switch
    /// frames, the largest excess there, and the most scans a frame drew.
    hybrid: PopMeasure,
    scans_at_hybrid: PopMeasure,
    excess_hybrid_scans: f64,
    hybrid_scans_max: usize,
    /// The tiles alone.
    fade: PopMeasure,
    nofade: PopMeasure,
    /// The scans-only fly-through at the no-fade and fade runs' switch frames.
    scans_at_nofade: PopMeasure,
    scans_at_fade: PopMeasure,
    /// The finest tiles only at the no-fade run's switch frames.
    finest_at_nofade: PopMeasure,
    excess_fade_scans: f64,
    excess_nofade_scans: f64,
    excess_fade_finest: f64,
    excess_nofade_finest: f64,
    still_fade: SwitchMeasure,
    still_nofade: SwitchMeasure,
    /// Frames where the scans' resident set changed, and the largest change there.
    scans_residency_frames: usize,
    scans_residency_max: f64,
    scans_left_out_max: usize,
}

pub fn run(args: &LodViewArgs) -> Result<()> {
    let started = Instant::now();
    let frames = if args.quick {
        args.street.frames.min(300)
    } else {
        args.street.frames
    };
    let scenes = args.street.scenes();
    let capture = args.street.capture(frames)?;
    let mut timings = Vec::new();
    let t = Instant::now();
    let placed = crate::tradeoffs::lod::truth_placed_scans(&capture)?;
    timings.push(("read and fuse the capture", t.elapsed().as_secs_f64()));
    println!("{} placed scans of {frames} frames", placed.len());
    let t = Instant::now();
    let hierarchy = build(&placed)?;
    let build_s = t.elapsed().as_secs_f64();
    timings.push(("build the tree", build_s));
    let tile_bytes_all: u64 = hierarchy.nodes.values().map(tile_gpu_bytes).sum();
    println!(
        "tree: {} tiles in {} levels, {:.1} MiB on the GPU if all resident, built in {build_s:.1} s",
        hierarchy.nodes.len(),
        hierarchy.top_lod + 1,
        mib(tile_bytes_all)
    );
    let sim = simulator(&scenes, "street", frames, args.street.seed, None)?;
    let fov = VirtualCamera::fov_y_deg_of(&sim.sensor_model().eo);
    let gpu = GpuContext::headless()?;
    let adapter = gpu.adapter_name();
    println!("adapter: {adapter}");
    let source = MemorySource::new(&hierarchy);
    let views = Views::of(&sim);
    let mut holder = ScanHolder::new(&gpu, &placed, DEFAULT_BUDGET_MB << 20);
    let scan_bytes_all = holder.all_bytes();
    println!(
        "scans: {:.1} MiB on the GPU if all resident; the viewer's budget {DEFAULT_BUDGET_MB} MiB",
        mib(scan_bytes_all)
    );

    // 1. Frame time and GPU memory.
    let t = Instant::now();
    let timed = if args.quick { 5 } else { 9 };
    let mut view = [[ViewFigures::default(); 3]; 2];
    for (k, (name, pose)) in [("close", views.close()?), ("overview", views.overview()?)]
        .into_iter()
        .enumerate()
    {
        let cam = camera(pose, fov)?;
        let settings = tile_settings(0.25, TILE_BUDGET);
        let (hybrid, _) = hybrid_view(&gpu, &source, &mut holder, &cam, settings, timed)?;
        print_view(name, HOW[0], &hybrid);
        let (lod, _) = lod_view(&gpu, &source, &cam, tiles_alone(settings), timed)?;
        print_view(name, HOW[1], &lod);
        let (scans, _) = scans_view(&mut holder, &cam, timed)?;
        print_view(name, HOW[2], &scans);
        view[k] = [hybrid, lod, scans];
    }
    // What the scans below the tiles cost in the close view, per count per tile.
    let mut close_sweep = Vec::new();
    let close_cam = camera(views.close()?, fov)?;
    for &k in if args.quick { &SWEEP[..2] } else { &SWEEP[..] } {
        let settings = per_tile(tile_settings(0.25, TILE_BUDGET), k);
        let (f, _) = hybrid_view(&gpu, &source, &mut holder, &close_cam, settings, timed)?;
        println!(
            "close, LOD with {} scans per tile, {} more from feedback: {:.1} ms/frame, {} scans drawn, {:.1} MiB data",
            k.0,
            k.1,
            f.frame_ms,
            f.scans_drawn,
            mib(f.data_bytes)
        );
        close_sweep.push((k, f));
    }
    for (j, label) in HOW.iter().enumerate() {
        println!(
            "{label}: overview / close frame time {:.2}, GPU bytes {:.2}",
            ratio(view[1][j].frame_ms, view[0][j].frame_ms),
            ratio(view[1][j].data_bytes as f64, view[0][j].data_bytes as f64)
        );
    }
    timings.push(("frame time and memory", t.elapsed().as_secs_f64()));

    // 2. Quality at held-out poses.
    let t = Instant::now();
    let poses = held_out(&sim, if args.quick { 3 } else { 8 });
    let sweep: &[Sweep] = if args.quick { &SWEEP[..2] } else { &SWEEP };
    let quality = quality(
        &gpu,
        &source,
        &mut holder,
        &sim,
        &poses,
        fov,
        (args.images.as_deref(), sweep),
    )?;
    for kind in ["near", "far"] {
        let m = mean_quality(&quality, kind);
        println!(
            "{kind}: PSNR LOD {:.2} dB, tiles alone {:.2} dB, scans only {:.2} dB; LOD - scans {:+.2} dB, tiles alone - scans {:+.2} dB (mean over {} poses)",
            m.hybrid_db,
            m.lod_db,
            m.scans_db,
            m.hybrid_minus_scans_db,
            m.lod_minus_scans_db,
            m.poses
        );
    }
    timings.push(("quality at held-out poses", t.elapsed().as_secs_f64()));
    drop(holder);

    // 3. Popping.
    let t = Instant::now();
    let cameras: Vec<VirtualCamera> = (0..FLY_FRAMES)
        .map(|i| camera(views.fly(i as f64 / (FLY_FRAMES - 1) as f64)?, fov))
        .collect::<Result<_>>()?;
    let pop = popping(&gpu, &hierarchy, &source, &placed, &cameras, tile_bytes_all)?;
    timings.push(("popping fly-throughs", t.elapsed().as_secs_f64()));
    timings.push(("total", started.elapsed().as_secs_f64()));
    for (what, s) in &timings {
        println!("time: {what} {s:.1} s");
    }

    let figures = Figures {
        frames,
        scans: placed.len(),
        adapter,
        build_s,
        tiles: hierarchy.nodes.len(),
        levels: hierarchy.top_lod + 1,
        tile_bytes_all,
        scan_bytes_all,
        views,
        view,
        close_sweep,
        quality,
        pop,
        timings,
    };
    let body = report::markdown(&figures, args);
    println!("{body}");
    if args.street.no_write || args.quick {
        return Ok(());
    }
    write_tradeoffs_section(&args.street.repo, "lod-view", &body)
}

/// The default tree of every scan.
fn build(placed: &[(Arc<TexelScan>, Pose)]) -> Result<Hierarchy> {
    let mut model = LodModel::new(LodConfig::default())?;
    for (scan, pose) in placed {
        model.add_scan(scan, pose);
    }
    model.rebuild(usize::MAX);
    Ok(model.hierarchy()?)
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / f64::from(1u32 << 20)
}

/// `a / b`, NaN when `b` is not positive.
fn ratio(a: f64, b: f64) -> f64 {
    if b > 0.0 { a / b } else { f64::NAN }
}

/// Scans a finest tile may show, and how many more its coverage feedback may add.
type Sweep = (usize, usize);

/// The counts measured: the default (8 and 64) and without the feedback first.
const SWEEP: [Sweep; 7] = [(8, 64), (8, 0), (8, 16), (4, 64), (16, 0), (32, 0), (64, 0)];

/// The three ways the street is drawn, as the tables name them.
const HOW: [&str; 3] = ["LOD", "tiles alone", "scans only"];

/// Tile settings with `k.0` scans below each finest tile and `k.1` more from its
/// coverage feedback.
fn per_tile(mut settings: TileSettings, k: Sweep) -> TileSettings {
    settings.hybrid.scans_per_tile = k.0;
    settings.hybrid.feedback_scans_per_tile = k.1;
    settings
}

/// Tile settings without the scans below the finest tiles.
fn tiles_alone(mut settings: TileSettings) -> TileSettings {
    settings.hybrid.enabled = false;
    settings
}

fn print_view(view: &str, how: &str, f: &ViewFigures) {
    println!(
        "{view}, {how}: {:.1} ms/frame, {:.1} MiB data + {:.1} MiB targets, {} resident, {} drawn, {} triangles{}",
        f.frame_ms,
        mib(f.data_bytes),
        mib(f.target_bytes),
        f.resident,
        f.drawn,
        f.triangles,
        if how != "scans only" {
            format!(
                ", settled after {} updates{}; {} finest tiles show {} scans ({} left out by the budget)",
                f.needed,
                if f.complete { "" } else { " (incomplete)" },
                f.tiles_with_scans,
                f.scans_drawn,
                f.left_out
            )
        } else {
            format!(
                ", {} needed, {} left out by the budget",
                f.needed, f.left_out
            )
        }
    );
}

/// Renders every held-out pose both ways and scores them against the simulator's
/// render over the pixels where the truth has geometry and both drew.
fn quality(
    gpu: &GpuContext,
    source: &MemorySource,
    holder: &mut ScanHolder<'_>,
    sim: &sims::Simulator,
    poses: &[(&'static str, Pose)],
    fov: f64,
    (images, sweep): (Option<&Path>, &[Sweep]),
) -> Result<Vec<PoseQuality>> {
    if let Some(dir) = images {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let pinhole = PinholeCamera::from_vertical_fov(WIDTH, HEIGHT, fov)?;
    let settings = scan_settings();
    let (w, h) = (WIDTH as usize, HEIGHT as usize);
    let mut out = Vec::new();
    for (i, (kind, pose)) in poses.iter().enumerate() {
        let cam = camera(*pose, fov)?;
        let truth = sim.scene().render_view(pose, &pinhole).rgb;
        let geometry = truth_geometry(sim.scene(), &cam);
        let tiles = tile_settings(0.0, TILE_BUDGET);
        let (plan, _) = holder.hold_for(&cam)?;
        let (scans, _) = holder.renderer.render_to_image(&cam, &settings)?;
        let mut r = TileRenderer::new(gpu, source.clone(), tiles_alone(tiles))?;
        let (_, now_s, _) = settle(&mut r, &cam, 0.0, 400);
        let (lod, _) = r.render_to_image(&cam, now_s)?;
        // The scans below the finest tiles at each count per tile; the default's is
        // the LOD figure.
        let mut swept = Vec::new();
        for &k in sweep {
            swept.push((
                k,
                hybrid_view(gpu, source, holder, &cam, per_tile(tiles, k), 1)?,
            ));
        }
        let default_k = (
            tiles.hybrid.scans_per_tile,
            tiles.hybrid.feedback_scans_per_tile,
        );
        let (hybrid_figures, hybrid) = swept
            .iter()
            .find(|(k, _)| *k == default_k)
            .map(|(_, v)| v.clone())
            .context("the sweep leaves out the default count")?;
        if let Some(dir) = images {
            let truth_image = image::RgbImage::from_raw(WIDTH, HEIGHT, truth.clone())
                .context("a truth image of the wrong size")?;
            let path = dir.join(format!("{i:02}-{kind}-truth.png"));
            truth_image
                .save(&path)
                .with_context(|| format!("writing {}", path.display()))?;
            for (what, picture) in [("lod", &hybrid), ("tiles", &lod), ("scans", &scans)] {
                let path = dir.join(format!("{i:02}-{kind}-{what}.png"));
                picture
                    .save(&path)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
        }
        // The hybrid draws wherever the tiles alone do (they fill below the scans).
        let (hc, lc, sc) = (covered(&hybrid), covered(&lod), covered(&scans));
        let mask: Vec<bool> = (0..w * h).map(|k| geometry[k] && lc[k] && sc[k]).collect();
        let geo = geometry.iter().filter(|g| **g).count().max(1) as f64;
        let share =
            |c: &[bool]| c.iter().zip(&geometry).filter(|(a, b)| **a && **b).count() as f64 / geo;
        let score = |img: &image::RgbaImage| {
            metrics::score(&rgb(img), &truth, &mask, w, h).map_or(f64::NAN, |s| s.psnr_db())
        };
        let q = PoseQuality {
            kind,
            hybrid_db: score(&hybrid),
            lod_db: score(&lod),
            scans_db: score(&scans),
            hybrid_cover: share(&hc),
            lod_cover: share(&lc),
            scans_cover: share(&sc),
            tiles_with_scans: hybrid_figures.tiles_with_scans,
            hybrid_scans: hybrid_figures.scans_drawn,
            swept_db: swept
                .iter()
                .map(|(k, (f, img))| (*k, score(img), f.scans_drawn))
                .collect(),
            scored: share(&mask),
            left_out: plan.left_out.len(),
        };
        println!(
            "pose {i} ({kind}): PSNR LOD {:.2} dB ({} finest tiles show {} scans), tiles alone {:.2} dB, scans only {:.2} dB ({:+.2}); truth geometry drawn {:.1} % / {:.1} % / {:.1} %, scored {:.1} %; {} scans left out by the budget",
            q.hybrid_db,
            q.tiles_with_scans,
            q.hybrid_scans,
            q.lod_db,
            q.scans_db,
            q.hybrid_db - q.scans_db,
            100.0 * q.hybrid_cover,
            100.0 * q.lod_cover,
            100.0 * q.scans_cover,
            100.0 * q.scored,
            q.left_out
        );
        out.push(q);
    }
    Ok(out)
}

/// Mean PSNRs over the poses of a kind, and the mean differences.
struct MeanQuality {
    poses: usize,
    hybrid_db: f64,
    lod_db: f64,
    scans_db: f64,
    hybrid_minus_scans_db: f64,
    lod_minus_scans_db: f64,
}

/// Mean PSNR each way over the poses of a kind (poses without a score left out).
fn mean_quality(q: &[PoseQuality], kind: &str) -> MeanQuality {
    let scored: Vec<&PoseQuality> = q
        .iter()
        .filter(|p| {
            p.kind == kind
                && p.hybrid_db.is_finite()
                && p.lod_db.is_finite()
                && p.scans_db.is_finite()
        })
        .collect();
    let n = scored.len();
    let mean = |f: &dyn Fn(&PoseQuality) -> f64| {
        if n == 0 {
            f64::NAN
        } else {
            scored.iter().map(|p| f(p)).sum::<f64>() / n as f64
        }
    };
    MeanQuality {
        poses: n,
        hybrid_db: mean(&|p| p.hybrid_db),
        lod_db: mean(&|p| p.lod_db),
        scans_db: mean(&|p| p.scans_db),
        hybrid_minus_scans_db: mean(&|p| p.hybrid_db - p.scans_db),
        lod_minus_scans_db: mean(&|p| p.lod_db - p.scans_db),
    }
}

/// A fly-through's frames, per frame whether the selection switched or a fade was
/// under way, and per frame the previous frame's tiles and this frame's drawn from
/// this frame's camera (as `viewer/tests/tiles_flythrough.rs`).
type Fly = (
    Vec<image::RgbaImage>,
    Vec<bool>,
    Vec<(image::RgbaImage, image::RgbaImage)>,
);

/// The fly-through with every tile of `source` resident from the start.
fn lod_fly(
    gpu: &GpuContext,
    source: MemorySource,
    cameras: &[VirtualCamera],
    fade_s: f64,
    budget: u64,
) -> Result<Fly> {
    let tiles = source.len();
    let mut r = TileRenderer::new(gpu, source, tile_settings(fade_s, budget))?;
    r.preload_all(Duration::from_secs(600));
    anyhow::ensure!(
        r.cache().len() == tiles,
        "{} of {tiles} tiles resident after preloading",
        r.cache().len()
    );
    let (mut frames, mut switched, mut pairs) = (Vec::new(), Vec::new(), Vec::new());
    for (i, cam) in cameras.iter().enumerate() {
        let before = r.draw_to_image(cam)?;
        let (img, stats) = r.render_to_image(cam, i as f64 * FRAME_S)?;
        switched.push(stats.selection_changed || stats.fading);
        if i > 0 {
            pairs.push((before, img.clone()));
        }
        frames.push(img);
    }
    Ok((frames, switched, pairs))
}

/// The fly-through with the scans below the finest tiles, as the viewer draws it:
/// every tile resident from the start; each frame updates, makes the wanted scans
/// resident (the planner restricted to them) and draws both. A frame is a switch
/// when the tile selection changed, a fade was under way, the finest tiles showing
/// scans changed or the resident scans did.
fn hybrid_fly(
    gpu: &GpuContext,
    source: MemorySource,
    holder: &mut ScanHolder<'_>,
    cameras: &[VirtualCamera],
    fade_s: f64,
    budget: u64,
) -> Result<(Vec<image::RgbaImage>, Vec<bool>, usize)> {
    let tiles = source.len();
    let mut r = TileRenderer::new(gpu, source, tile_settings(fade_s, budget))?;
    r.preload_all(Duration::from_secs(600));
    anyhow::ensure!(
        r.cache().len() == tiles,
        "{} of {tiles} tiles resident after preloading",
        r.cache().len()
    );
    let settings = scan_settings();
    let (mut frames, mut switched, mut most_scans) = (Vec::new(), Vec::new(), 0usize);
    let mut showing = None;
    for (i, cam) in cameras.iter().enumerate() {
        let stats = r.update(cam, i as f64 * FRAME_S);
        holder.set_only(Some(r.scans_wanted(&holder.model_scans, cam)));
        let hold = holder.hold_for(cam);
        holder.set_only(None);
        let (_, changed) = hold?;
        let (img, hybrid) =
            r.draw_over_scans_to_image(&mut holder.renderer, &settings, &holder.model_scans, cam)?;
        most_scans = most_scans.max(hybrid.scans.map_or(0, |s| s.drawn));
        let shown_changed = showing.is_some_and(|n| n != stats.tiles_with_scans);
        showing = Some(stats.tiles_with_scans);
        switched
            .push(i > 0 && (stats.selection_changed || stats.fading || shown_changed || changed));
        frames.push(img);
    }
    Ok((frames, switched, most_scans))
}

fn popping(
    gpu: &GpuContext,
    hierarchy: &Hierarchy,
    source: &MemorySource,
    placed: &[(Arc<TexelScan>, Pose)],
    cameras: &[VirtualCamera],
    tile_bytes_all: u64,
) -> Result<Popping> {
    let budget = tile_bytes_all.saturating_add(16 << 20);
    let (faded, faded_sw, faded_pairs) = lod_fly(gpu, source.clone(), cameras, 0.25, budget)?;
    let (popped, popped_sw, popped_pairs) = lod_fly(gpu, source.clone(), cameras, 0.0, budget)?;
    let finest_source =
        MemorySource::from_nodes(hierarchy.nodes.values().filter(|n| n.id.lod == 0));
    let (finest, _, _) = lod_fly(gpu, finest_source, cameras, 0.0, budget)?;
    let mut holder = ScanHolder::new(gpu, placed, DEFAULT_BUDGET_MB << 20);
    let (hybrid, hybrid_sw, hybrid_scans_max) =
        hybrid_fly(gpu, source.clone(), &mut holder, cameras, 0.25, budget)?;
    // The same fly-through with the scans only, as the viewer holds them.
    let settings = scan_settings();
    let (mut scans, mut residency, mut left_out) = (Vec::new(), Vec::new(), 0usize);
    for cam in cameras {
        let (plan, changed) = holder.hold_for(cam)?;
        left_out = left_out.max(plan.left_out.len());
        residency.push(changed);
        scans.push(holder.renderer.render_to_image(cam, &settings)?.0);
    }
    residency[0] = false;
    let scans_residency = popping_measure(&scans, &residency);
    let pop = Popping {
        hybrid: popping_measure(&hybrid, &hybrid_sw),
        scans_at_hybrid: popping_measure(&scans, &hybrid_sw),
        excess_hybrid_scans: popping_excess(&hybrid, &scans, &hybrid_sw),
        hybrid_scans_max,
        fade: popping_measure(&faded, &faded_sw),
        nofade: popping_measure(&popped, &popped_sw),
        scans_at_nofade: popping_measure(&scans, &popped_sw),
        scans_at_fade: popping_measure(&scans, &faded_sw),
        finest_at_nofade: popping_measure(&finest, &popped_sw),
        excess_fade_scans: popping_excess(&faded, &scans, &faded_sw),
        excess_nofade_scans: popping_excess(&popped, &scans, &popped_sw),
        excess_fade_finest: popping_excess(&faded, &finest, &faded_sw),
        excess_nofade_finest: popping_excess(&popped, &finest, &popped_sw),
        still_fade: switch_measure(&faded_pairs),
        still_nofade: switch_measure(&popped_pairs),
        scans_residency_frames: scans_residency.switch_frames,
        scans_residency_max: scans_residency.max_switch_change,
        scans_left_out_max: left_out,
    };
    println!(
        "fly-through, LOD with scans below, fade 0.25 s: {:?} (at most {} scans drawn)",
        pop.hybrid, pop.hybrid_scans_max
    );
    println!(
        "fly-through, scans only at its switch frames: {:?}; largest excess {:.3}",
        pop.scans_at_hybrid, pop.excess_hybrid_scans
    );
    println!("fly-through, tiles alone fade 0.25 s: {:?}", pop.fade);
    println!("fly-through, LOD fade 0:      {:?}", pop.nofade);
    println!(
        "fly-through, scans only at the no-fade switch frames: {:?}",
        pop.scans_at_nofade
    );
    println!(
        "fly-through, scans only at the fade switch frames: {:?}",
        pop.scans_at_fade
    );
    println!(
        "fly-through, finest tiles only at the no-fade switch frames: {:?}",
        pop.finest_at_nofade
    );
    println!(
        "largest excess at a switch over scans only: fade {:.3}, no fade {:.3}; over the finest tiles: fade {:.3}, no fade {:.3}",
        pop.excess_fade_scans,
        pop.excess_nofade_scans,
        pop.excess_fade_finest,
        pop.excess_nofade_finest
    );
    println!("held still, fade 0.25 s: {:?}", pop.still_fade);
    println!("held still, fade 0:      {:?}", pop.still_nofade);
    println!(
        "scans only: resident set changed at {} frames, largest change there {:.3}; at most {} needed scans left out",
        pop.scans_residency_frames, pop.scans_residency_max, pop.scans_left_out_max
    );
    Ok(pop)
}
