//! `texel-bench tradeoffs retirement`: what retiring redundant scans
//! (`texel::coverage`) costs in held-out image quality and what it saves in scans
//! and memory. Follows the rendering trade-offs' method (same captures, registration,
//! held-out poses, ground truth and PSNR): each scene's registered scans are fed in
//! time order to a `Retirement` index per setting, and the model is rendered with the
//! retired scans hidden, against the model with every scan. Writes the retirement
//! section of `docs/tradeoffs.md`.

use std::collections::BTreeSet;
use std::fmt::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use texel::coverage::{CoverageConfig, Retirement, ScanCoverage};
use texel::model::ScanId;
use texel::{PinholeCamera, Pose, TexelScan};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::capture_load::{PoseSource, load_capture};
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{GpuContext, Renderer};

use crate::tradeoffs::registration::data::{SequenceSpec, cached_capture, simulator};
use crate::tradeoffs::rendering::report::write_tradeoffs_section;
use crate::tradeoffs::rendering::{
    BACKGROUND_RGB, Config, held_out_poses, metrics, registered_capture,
};

#[derive(Debug, Clone, clap::Args)]
pub struct RetirementArgs {
    /// Fewer held-out poses and settings, for a quick look (its numbers are not the
    /// documented ones; docs/ is left alone).
    #[arg(long)]
    pub quick: bool,
    /// The repository root (scenes are read and the docs written under it).
    #[arg(long, default_value = ".")]
    pub repo: PathBuf,
    /// Where captures and their registrations are kept between runs.
    #[arg(long, default_value = "target/tradeoffs-cache")]
    pub cache: PathBuf,
    /// Simulator seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Measure and print, but leave docs/tradeoffs.md alone.
    #[arg(long)]
    pub no_write: bool,
    /// Only print how many scans each setting retires (no rendering; implies
    /// --no-write).
    #[arg(long)]
    pub counts_only: bool,
}

/// The scenes measured: name and frames of the capture.
const SCENES: [(&str, usize); 2] = [("lab-walk", 200), ("courtyard", 72)];

/// Held-out poses per scene.
const POSES: usize = 8;
const QUICK_POSES: usize = 4;

/// The settings measured: `None` is the model with every scan.
fn settings(quick: bool) -> Vec<Option<CoverageConfig>> {
    let base = CoverageConfig::default();
    let with = |angle_tolerance_deg: f64, reliability_margin: f64, cell_m: f64| {
        Some(CoverageConfig {
            angle_tolerance_deg,
            reliability_margin,
            cell_m,
            ..base
        })
    };
    if quick {
        return vec![
            None,
            Some(base),
            with(10.0, 0.1, 0.5),
            with(20.0, 0.1, 0.5),
            with(10.0, 0.1, 1.0),
            with(20.0, 0.2, 1.0),
            with(30.0, 0.3, 1.0),
        ];
    }
    vec![
        None,
        with(5.0, 0.1, 0.5),
        with(10.0, 0.1, 0.5),
        with(20.0, 0.1, 0.5),
        with(30.0, 0.1, 0.5),
        with(10.0, 0.05, 0.5),
        with(10.0, 0.2, 0.5),
        with(10.0, 0.1, 0.25),
        with(10.0, 0.1, 1.0),
        with(20.0, 0.1, 1.0),
        with(30.0, 0.1, 1.0),
        with(20.0, 0.2, 1.0),
    ]
}

/// One setting's result on one scene.
#[derive(Debug, Clone)]
struct Row {
    setting: Option<CoverageConfig>,
    served: usize,
    /// Sum of the served scans' heap bytes.
    held_bytes: usize,
    /// The index's own heap bytes after the last scan.
    index_bytes: usize,
    /// Mean CPU time of one `add`, microseconds.
    add_us: f64,
    psnr_db: f64,
    coverage: f64,
}

struct SceneResult {
    scene: &'static str,
    frames: usize,
    scans: usize,
    poses: usize,
    rows: Vec<Row>,
}

pub fn run(args: &RetirementArgs) -> Result<()> {
    let gpu = GpuContext::headless()?;
    println!("adapter: {}", gpu.adapter_name());
    let mut results = Vec::new();
    for (scene, frames) in SCENES {
        let r = measure_scene(&gpu, args, scene, frames)?;
        print!("{}", table(&r));
        results.push(r);
    }
    if args.no_write || args.quick || args.counts_only {
        return Ok(());
    }
    let body = markdown(&results, &gpu.adapter_name());
    write_tradeoffs_section(&args.repo, "retirement", &body)
}

/// The registered scans of a loaded capture with their poses, in time order.
fn placed_scans(model: &texel::model::Model) -> Vec<(ScanId, Arc<TexelScan>, Pose)> {
    model
        .resident()
        .map(|(s, scan)| (s.id, Arc::clone(scan), s.world_from_scan))
        .collect()
}

/// The ids a setting retires when the scans arrive in time order, with the mean
/// time of one `add` (coverage signature included), microseconds, and the index's
/// heap bytes.
fn retire(
    scans: &[(ScanId, Arc<TexelScan>, Pose)],
    config: &CoverageConfig,
) -> (BTreeSet<ScanId>, f64, usize) {
    let mut index = Retirement::new(*config);
    let started = Instant::now();
    for (id, scan, pose) in scans {
        index.add(*id, ScanCoverage::of(scan, config), pose);
    }
    let add_us = started.elapsed().as_secs_f64() * 1e6 / scans.len().max(1) as f64;
    let retired = scans
        .iter()
        .map(|(id, _, _)| *id)
        .filter(|id| index.is_retired(*id))
        .collect();
    (retired, add_us, index.heap_bytes())
}

fn measure_scene(
    gpu: &GpuContext,
    args: &RetirementArgs,
    scene: &'static str,
    frames: usize,
) -> Result<SceneResult> {
    let scenes_dir = args.repo.join("configs").join("scenes");
    let spec = SequenceSpec {
        scene,
        frames,
        seed: args.seed,
        orbit_period_frames: None,
    };
    let capture = cached_capture(&scenes_dir, &args.cache, &spec)?;
    let (registered_path, _) = registered_capture(&capture)?;
    let loaded = load_capture(&registered_path)?;
    anyhow::ensure!(
        loaded.pose_source == PoseSource::Registered,
        "{}: no /texel/pose after registration",
        registered_path.display()
    );
    let scans = placed_scans(&loaded.model);
    let sim = simulator(&scenes_dir, scene, frames, args.seed, None)?;
    let poses = held_out_poses(&sim, if args.quick { QUICK_POSES } else { POSES });
    let render = Config::base(Mode::Blended);
    let fov = VirtualCamera::fov_y_deg_of(&loaded.eo_camera);
    let camera = PinholeCamera::from_vertical_fov(render.width, render.height, fov)?;
    let truths: Vec<Vec<u8>> = poses
        .iter()
        .map(|p| sim.scene().render_view(&p.world_from_eo, &camera).rgb)
        .collect();
    let mut renderer = Renderer::new(gpu);
    renderer.sync_model(&loaded.model)?;

    // Every setting: the retired set, then the model rendered without it.
    let mut images: Vec<Vec<Vec<u8>>> = Vec::new();
    let mut partial: Vec<Row> = Vec::new();
    for setting in settings(args.quick) {
        let (retired, add_us, index_bytes) = match &setting {
            Some(c) => retire(&scans, c),
            None => (BTreeSet::new(), 0.0, 0),
        };
        eprintln!(
            "{scene}: {} of {} scans retired ({})",
            retired.len(),
            scans.len(),
            setting_label(&setting)
        );
        if args.counts_only {
            continue;
        }
        let mut s = render.settings();
        s.hidden = retired.clone();
        let started = Instant::now();
        let mut per_pose = Vec::with_capacity(poses.len());
        for p in &poses {
            let cam = VirtualCamera::new(p.world_from_eo, fov, render.width, render.height)?;
            let (image, _) = renderer.render_to_image(&cam, &s)?;
            per_pose.push(
                image
                    .pixels()
                    .flat_map(|px| [px[0], px[1], px[2]])
                    .collect(),
            );
        }
        let served: Vec<&(ScanId, Arc<TexelScan>, Pose)> = scans
            .iter()
            .filter(|(id, _, _)| !retired.contains(id))
            .collect();
        eprintln!(
            "{scene}: rendered {} poses in {:.1} s",
            poses.len(),
            started.elapsed().as_secs_f64()
        );
        partial.push(Row {
            setting,
            served: served.len(),
            held_bytes: served.iter().map(|(_, s, _)| s.heap_bytes()).sum(),
            index_bytes,
            add_us,
            psnr_db: f64::NAN,
            coverage: f64::NAN,
        });
        images.push(per_pose);
    }

    // Scored pixels: those every setting covers at that pose (as the rendering
    // trade-offs do), so a setting is not rewarded for leaving holes.
    let covered = |rgb: &[u8]| -> Vec<bool> {
        rgb.chunks_exact(3)
            .map(|p| p != BACKGROUND_RGB.as_slice())
            .collect()
    };
    let masks: Vec<Vec<bool>> = (0..poses.len())
        .map(|i| {
            images
                .iter()
                .fold(vec![true; truths[i].len() / 3], |mut m, per_pose| {
                    m.iter_mut()
                        .zip(covered(&per_pose[i]))
                        .for_each(|(a, b)| *a &= b);
                    m
                })
        })
        .collect();
    let (w, h) = (render.width as usize, render.height as usize);
    for (row, per_pose) in partial.iter_mut().zip(&images) {
        let (mut psnr, mut n, mut cov) = (0.0, 0usize, 0usize);
        for (i, img) in per_pose.iter().enumerate() {
            cov += covered(img).iter().filter(|v| **v).count();
            if let Some(score) = metrics::score(img, &truths[i], &masks[i], w, h) {
                psnr += score.psnr_db();
                n += 1;
            }
        }
        row.psnr_db = if n > 0 { psnr / n as f64 } else { f64::NAN };
        row.coverage = cov as f64 / (w * h * per_pose.len().max(1)) as f64;
    }
    Ok(SceneResult {
        scene,
        frames,
        scans: scans.len(),
        poses: poses.len(),
        rows: partial,
    })
}

fn setting_label(s: &Option<CoverageConfig>) -> String {
    match s {
        None => "every scan".to_string(),
        Some(c) => format!(
            "{} deg, margin {}, cell {} m",
            c.angle_tolerance_deg, c.reliability_margin, c.cell_m
        ),
    }
}

/// The scene's table in Markdown (also what is printed).
fn table(r: &SceneResult) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "### {}\n\n{} frames, {} scans registered, {} held-out poses.\n",
        r.scene, r.frames, r.scans, r.poses
    );
    let _ = writeln!(
        s,
        "| angle tolerance (deg) | reliability margin | cell (m) | scans served | retired (%) | \
         scan memory held (MB) | index (KB) | add (us/scan) | PSNR (dB) | against every scan (dB) | \
         coverage (%) |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|");
    let reference = r
        .rows
        .iter()
        .find(|x| x.setting.is_none())
        .map(|x| x.psnr_db);
    for row in &r.rows {
        let (angle, margin, cell) = match &row.setting {
            None => ("every scan".to_string(), "-".to_string(), "-".to_string()),
            Some(c) => (
                format!(
                    "{}{}",
                    c.angle_tolerance_deg,
                    if *c == CoverageConfig::default() {
                        " (default)"
                    } else {
                        ""
                    }
                ),
                format!("{}", c.reliability_margin),
                format!("{}", c.cell_m),
            ),
        };
        let delta = reference.map_or(f64::NAN, |p| row.psnr_db - p);
        let _ = writeln!(
            s,
            "| {angle} | {margin} | {cell} | {} | {:.1} | {:.1} | {:.0} | {:.0} | {:.2} | {:+.2} | {:.1} |",
            row.served,
            100.0 * (1.0 - row.served as f64 / r.scans.max(1) as f64),
            row.held_bytes as f64 / 1e6,
            row.index_bytes as f64 / 1e3,
            row.add_us,
            row.psnr_db,
            delta,
            100.0 * row.coverage,
        );
    }
    s.push('\n');
    s
}

/// The retirement section.
fn markdown(results: &[SceneResult], adapter: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "## Retirement\n");
    let _ = writeln!(
        s,
        "Generated by `cargo run {}-p texel-bench -- tradeoffs retirement` (seed 1) on {adapter}, \
         on a shared 2-core machine.\n",
        if cfg!(debug_assertions) {
            ""
        } else {
            "--release "
        }
    );
    let _ = writeln!(
        s,
        "Method. As in the rendering section: each scene is rendered by the simulator with its \
         default effects, registered with the daemon's defaults, loaded like any capture and \
         rendered (`blended`, k 4, threshold 0.15, 320x240) at held-out poses against the \
         simulator's effect-free view. Each setting feeds the registered scans in time order to a \
         `texel::coverage::Retirement` index (what the daemon does as scans arrive) and renders \
         the model with the retired scans hidden. PSNR is over the pixels every setting covers, per \
         pose, then averaged; `coverage` is the share of the image a setting covers. `scan memory \
         held` is the sum of the served scans' `TexelScan::heap_bytes` (what the daemon would keep); \
         `index` is the index's own heap bytes (signatures included); `add` is the mean CPU time of \
         one `add` with the scan's coverage signature, in this ({}) build. The criterion \
         is in `docs/model.md` (\"Retirement\"); the other settings are the defaults (one sample per \
         8x8 lidar pixels, range gamma 1, {} candidates a cell, revalidation).\n",
        if cfg!(debug_assertions) {
            "unoptimised"
        } else {
            "optimised"
        },
        CoverageConfig::default().max_candidates_per_cell
    );
    let _ = writeln!(
        s,
        "Reading the tables. PSNR is scored only on the pixels every setting covers, so what \
         retirement loses at the edges of surfaces shows in `coverage`, not in PSNR; the choice \
         below bounds both. Where PSNR rises as scans are retired, a likely reason is that fewer \
         overlapping scans reach each pixel's blend, each with its own registration error and EO \
         noise. These are held-out views of two simulated scenes, not a guarantee: \
         `docs/model.md` states the bound that holds for every view.\n"
    );
    for r in results {
        s.push_str(&table(r));
    }
    s.push_str(&choice(results));
    s
}

/// Largest loss of image coverage (percentage points) a chosen setting may have:
/// the PSNR is scored on pixels every setting covers, so holes need their own limit.
const MAX_COVERAGE_LOSS_PERCENT: f64 = 0.5;

/// The setting that retires the most scans (summed over the scenes) while losing at
/// most 0.1 dB against every scan and at most [`MAX_COVERAGE_LOSS_PERCENT`] of
/// coverage on each scene, as a sentence.
fn choice(results: &[SceneResult]) -> String {
    let Some(first) = results.first() else {
        return String::new();
    };
    let within = |r: &SceneResult, i: usize| {
        let (Some(reference), Some(row)) =
            (r.rows.iter().find(|x| x.setting.is_none()), r.rows.get(i))
        else {
            return false;
        };
        reference.psnr_db - row.psnr_db <= 0.1
            && 100.0 * (reference.coverage - row.coverage) <= MAX_COVERAGE_LOSS_PERCENT
    };
    let best = (0..first.rows.len())
        .filter(|&i| first.rows[i].setting.is_some())
        .filter(|&i| results.iter().all(|r| within(r, i)))
        .max_by_key(|&i| {
            results
                .iter()
                .map(|r| r.scans - r.rows.get(i).map_or(r.scans, |x| x.served))
                .sum::<usize>()
        });
    match best.and_then(|i| first.rows[i].setting.as_ref()) {
        Some(c) => format!(
            "The setting that retires the most scans while losing at most 0.1 dB and at most \
             {MAX_COVERAGE_LOSS_PERCENT} percentage points of coverage on both scenes: {}.\n",
            setting_label(&Some(*c))
        ),
        None => {
            "No setting keeps within 0.1 dB and the coverage limit on both scenes.\n".to_string()
        }
    }
}
