//! `texel-bench tradeoffs rendering`: what rendering quality costs in time, measured against
//! the simulator's ground truth. For each scene, a capture is rendered (scene's
//! default effects), registered in-process with the daemon's registration
//! (`texel_register::capture::register_capture`), and rendered by every mode and
//! setting at held-out poses (between and beyond the acquisition poses); the same
//! poses rendered by the simulator without sensor effects (`sims::Scene::render_view`)
//! are the truth. Writes the rendering section of `docs/tradeoffs.md` and its Pareto
//! plot.

mod flicker;
pub mod metrics;
mod poses;
pub(crate) mod report;

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::tradeoffs::registration::data::{SequenceSpec, cached_capture, simulator};
use anyhow::{Context, Result};
use texel::PinholeCamera;
use texel::model::Model;
use texel_register::capture::register_capture;
use texel_register::config::RegistrationConfig;

use metrics::Score;
pub use poses::{HeldOutPose, held_out_poses};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::capture_load::{PoseSource, load_capture};
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{GpuContext, RenderSettings, Renderer};
use texel_viewer::vdtm::{LiveVdtm, VdtmChoice, VdtmSettings};

#[derive(Debug, Clone, clap::Args)]
pub struct TradeoffsArgs {
    /// Fewer poses and settings, for a quick look (its numbers are not the
    /// documented ones).
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
    /// Also write, per scene and held-out pose, the ground truth and the default
    /// `painter`, `best` and `blended` images (registered poses) as PNGs under this
    /// folder, to look at what the numbers score.
    #[arg(long)]
    pub images: Option<PathBuf>,
}

/// One rendering configuration of the sweep.
#[derive(Debug, Clone)]
pub struct Config {
    pub mode: Mode,
    pub k: u32,
    pub blend_threshold: f32,
    pub range_gamma: f32,
    pub width: u32,
    pub height: u32,
    /// Rendered from the model placed at the truth poses (a reference) instead of
    /// the registered ones.
    pub truth_poses: bool,
    /// View-dependent texture mapping on the merged surface (Debevec 1998) with these
    /// switches, instead of the scans composited in `mode`.
    pub vdtm: Option<VdtmSettings>,
    /// The scans as a point proxy (Lechelek et al. 2019) instead.
    pub points: bool,
}

impl Config {
    pub(crate) fn base(mode: Mode) -> Self {
        Self {
            mode,
            k: 4,
            blend_threshold: 0.15,
            range_gamma: 1.0,
            width: 320,
            height: 240,
            truth_poses: false,
            vdtm: None,
            points: false,
        }
    }

    pub(crate) fn points() -> Self {
        Self {
            points: true,
            ..Self::base(Mode::default())
        }
    }

    pub(crate) fn vdtm(settings: VdtmSettings) -> Self {
        Self {
            vdtm: Some(settings),
            ..Self::base(Mode::default())
        }
    }

    /// The mode's name: a compositing mode, or `vdtm` with its switches.
    pub fn mode_name(&self) -> String {
        if self.points {
            return "points".to_string();
        }
        self.vdtm
            .map_or_else(|| self.mode.name().to_string(), |v| v.label())
    }

    pub fn settings(&self) -> RenderSettings {
        let mut s = RenderSettings::with_mode(self.mode);
        s.composite.k = self.k;
        s.composite.blend_threshold = self.blend_threshold;
        s.composite.background = BACKGROUND;
        s.range_gamma = self.range_gamma;
        s.points = self.points;
        s
    }

    /// A short label for the plot.
    pub fn label(&self) -> String {
        let mut l = self.mode_name();
        if self.vdtm.is_some() || self.points {
        } else if self.mode == Mode::Blended {
            l.push_str(&format!(" k{} t{}", self.k, self.blend_threshold));
        } else if self.mode == Mode::Best {
            l.push_str(&format!(" k{}", self.k));
        }
        if self.range_gamma != 1.0 {
            l.push_str(&format!(" g{}", self.range_gamma));
        }
        if self.width != 320 {
            l.push_str(&format!(" {}x{}", self.width, self.height));
        }
        if self.truth_poses {
            l.push_str(" (truth poses)");
        }
        l
    }
}

/// Uncovered pixels get this colour so the mask can find them (the scenes never
/// produce pure magenta).
const BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];
pub(crate) const BACKGROUND_RGB: [u8; 3] = [255, 0, 255];

/// VDTM as published, with each switch beyond the paper, and with both.
fn vdtm_variants() -> [VdtmSettings; 4] {
    let feather_px = VdtmSettings::FEATHER_PX;
    [
        VdtmSettings::default(),
        VdtmSettings {
            resolution_term: true,
            feather_px: 0.0,
        },
        VdtmSettings {
            resolution_term: false,
            feather_px,
        },
        VdtmSettings::improved(),
    ]
}

/// The sweep: the three shading modes at the defaults and VDTM's variants, then one
/// knob at a time.
pub fn sweep(quick: bool) -> Vec<Config> {
    let mut configs: Vec<Config> = [Mode::Painter, Mode::Best, Mode::Blended]
        .into_iter()
        .map(Config::base)
        .collect();
    configs.extend(vdtm_variants().into_iter().map(Config::vdtm));
    configs.push(Config::points());
    let ks: &[u32] = if quick { &[1] } else { &[1, 2, 8] };
    for &k in ks {
        configs.push(Config {
            k,
            ..Config::base(Mode::Blended)
        });
    }
    let thresholds: &[f32] = if quick { &[0.3] } else { &[0.05, 0.3, 0.5] };
    for &t in thresholds {
        configs.push(Config {
            blend_threshold: t,
            ..Config::base(Mode::Blended)
        });
    }
    let gammas: &[f32] = if quick { &[2.0] } else { &[0.5, 2.0, 4.0] };
    for &g in gammas {
        for mode in [Mode::Best, Mode::Blended] {
            configs.push(Config {
                range_gamma: g,
                ..Config::base(mode)
            });
        }
    }
    let sizes: &[(u32, u32)] = if quick {
        &[(160, 120)]
    } else {
        &[(160, 120), (640, 480)]
    };
    for &(width, height) in sizes {
        for mode in [Mode::Painter, Mode::Best, Mode::Blended] {
            configs.push(Config {
                width,
                height,
                ..Config::base(mode)
            });
        }
    }
    for mode in [Mode::Painter, Mode::Best, Mode::Blended] {
        configs.push(Config {
            truth_poses: true,
            ..Config::base(mode)
        });
    }
    configs
}

/// The scenes measured: name and frames of the capture.
const SCENES: [(&str, usize); 2] = [("lab", 36), ("courtyard", 72)];

/// One configuration's result on one scene.
#[derive(Debug, Clone)]
pub struct Row {
    pub config: Config,
    /// Mean over poses of the per-pose PSNR, dB.
    pub psnr_db: f64,
    pub ssim: f64,
    /// Pooled MSE over all scored pixels (for the plot's RMSE).
    pub mse: f64,
    /// Fraction of the image this configuration covers, and the fraction scored.
    pub coverage: f64,
    pub scored: f64,
    /// Median render time per frame, milliseconds (render + read-back).
    pub frame_ms: f64,
}

/// What one scene gave.
#[derive(Debug, Clone)]
pub struct SceneResult {
    pub scene: String,
    pub frames: usize,
    pub scans: usize,
    pub poses: usize,
    pub registration_ate_mm: f64,
    pub registration_s: f64,
    pub rows: Vec<Row>,
    /// VDTM's preparation of the registered model (merged surface and §5-7) and
    /// what it made.
    pub vdtm: Option<texel_viewer::vdtm::VdtmStatus>,
    /// Per mode, the fly-through's flicker (see `flicker.rs`).
    pub flicker: Vec<flicker::FlickerRow>,
}

pub fn run(args: &TradeoffsArgs) -> Result<()> {
    let gpu = GpuContext::headless()?;
    println!("adapter: {}", gpu.adapter_name());
    let scenes_dir = args.repo.join("configs").join("scenes");
    let mut results = Vec::new();
    for (scene, frames) in SCENES {
        let r = measure_scene(&gpu, &scenes_dir, &args.cache, scene, frames, args)?;
        report::print(&r);
        results.push(r);
    }
    if args.no_write {
        return Ok(());
    }
    let figures = args.repo.join("docs").join("tradeoffs");
    std::fs::create_dir_all(&figures).with_context(|| format!("creating {}", figures.display()))?;
    report::plot(&figures.join("rendering-pareto"), &results)?;
    let body = report::markdown(&results, args, &gpu.adapter_name());
    report::write_tradeoffs_section(&args.repo, "rendering", &body)
}

/// The capture registered with the daemon's defaults, kept in the cache.
pub(crate) fn registered_capture(capture: &Path) -> Result<(PathBuf, f64)> {
    let out = capture.with_extension("registered.mcap");
    if out.exists() {
        return Ok((out, f64::NAN));
    }
    let partial = capture.with_extension("registered.partial.mcap");
    let start = Instant::now();
    eprintln!("registering {}", capture.display());
    register_capture(
        capture,
        &partial,
        RegistrationConfig::default(),
        None,
        &mut |_| {},
    )
    .with_context(|| format!("registering {}", capture.display()))?;
    std::fs::rename(&partial, &out)
        .with_context(|| format!("moving {} into place", partial.display()))?;
    Ok((out, start.elapsed().as_secs_f64()))
}

/// The ground truth and the default configurations' images of every pose, as
/// `POSE-truth.png` and `POSE-MODE.png` in `dir`.
fn write_images(
    dir: &Path,
    configs: &[Config],
    rendered: &[(Vec<Vec<u8>>, Vec<f64>)],
    truth_images: &std::collections::BTreeMap<(u32, u32), Vec<Vec<u8>>>,
) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let save = |name: String, width: u32, height: u32, rgb: &[u8]| -> Result<()> {
        let path = dir.join(name);
        let image = image::RgbImage::from_raw(width, height, rgb.to_vec())
            .with_context(|| format!("{}: image of the wrong size", path.display()))?;
        image
            .save(&path)
            .with_context(|| format!("writing {}", path.display()))
    };
    let base = Config::base(Mode::Painter);
    if let Some(truths) = truth_images.get(&(base.width, base.height)) {
        for (i, rgb) in truths.iter().enumerate() {
            save(format!("{i:02}-truth.png"), base.width, base.height, rgb)?;
        }
    }
    for (c, (images, _)) in configs.iter().zip(rendered) {
        let default = Config::base(c.mode);
        let is_default = c.vdtm.is_some() || c.points || c.label() == default.label();
        if !is_default || c.truth_poses || c.width != base.width {
            continue;
        }
        for (i, rgb) in images.iter().enumerate() {
            save(
                format!("{i:02}-{}.png", c.mode_name()),
                c.width,
                c.height,
                rgb,
            )?;
        }
    }
    Ok(())
}

/// RMSE of scan positions, registered against truth, matched by timestamp (mm).
fn ate_mm(registered: &Model, truth: &Model) -> f64 {
    let truth_by_time: std::collections::HashMap<u64, texel::Pose> = truth
        .scans()
        .iter()
        .map(|s| (s.listing.timestamp_ns, s.world_from_scan))
        .collect();
    let (mut sq, mut n) = (0.0, 0usize);
    for s in registered.scans() {
        if let Some(t) = truth_by_time.get(&s.listing.timestamp_ns) {
            sq += (s.world_from_scan.translation.vector - t.translation.vector).norm_squared();
            n += 1;
        }
    }
    if n == 0 {
        f64::NAN
    } else {
        (sq / n as f64).sqrt() * 1e3
    }
}

fn measure_scene(
    gpu: &GpuContext,
    scenes_dir: &Path,
    cache: &Path,
    scene: &str,
    frames: usize,
    args: &TradeoffsArgs,
) -> Result<SceneResult> {
    let capture = cached_capture(
        scenes_dir,
        cache,
        &SequenceSpec {
            scene,
            frames,
            seed: args.seed,
            orbit_period_frames: None,
        },
    )?;
    let (registered_path, registration_s) = registered_capture(&capture)?;
    let registered = load_capture(&registered_path)?;
    anyhow::ensure!(
        registered.pose_source == PoseSource::Registered,
        "{}: no /texel/pose after registration",
        registered_path.display()
    );
    let truth = load_capture(&capture)?;
    let sim = simulator(scenes_dir, scene, frames, args.seed, None)?;
    let count = if args.quick { 6 } else { 20 };
    let poses = held_out_poses(&sim, count);
    let fov = VirtualCamera::fov_y_deg_of(&registered.eo_camera);
    let configs = sweep(args.quick);

    let mut reg_renderer = Renderer::new(gpu);
    reg_renderer.sync_model(&registered.model)?;
    // The point proxy's points and acquisition depth maps, built once, timed.
    let started = Instant::now();
    reg_renderer.prepare_points(&registered.model, None);
    reg_renderer.wait_idle()?;
    eprintln!(
        "{scene}: point proxy of {} scans built in {:.2} s, {:.1} MB on the GPU",
        registered.model.len(),
        started.elapsed().as_secs_f64(),
        reg_renderer.points_bytes() as f64 / 1e6
    );
    let mut truth_renderer = Renderer::new(gpu);
    truth_renderer.sync_model(&truth.model)?;
    // VDTM prepared once from the registered model, its EO camera from the capture.
    let mut vdtm = LiveVdtm::new(
        gpu,
        VdtmChoice {
            camera: Some(registered.eo_camera.clone()),
            ..VdtmChoice::default()
        },
    );
    vdtm.update(gpu, &registered.model, true);
    if let Some(e) = &vdtm.status.error {
        anyhow::bail!("{scene}: VDTM preparation failed: {e}");
    }
    eprintln!("{scene}: {}", vdtm.status.describe());

    // Ground truth per resolution and pose.
    let mut truth_images: std::collections::BTreeMap<(u32, u32), Vec<Vec<u8>>> = Default::default();
    for c in &configs {
        if truth_images.contains_key(&(c.width, c.height)) {
            continue;
        }
        let camera = PinholeCamera::from_vertical_fov(c.width, c.height, fov)?;
        let started = Instant::now();
        let images: Vec<Vec<u8>> = poses
            .iter()
            .map(|p| sim.scene().render_view(&p.world_from_eo, &camera).rgb)
            .collect();
        eprintln!(
            "{scene}: ground truth at {}x{} for {} poses in {:.1} s",
            c.width,
            c.height,
            poses.len(),
            started.elapsed().as_secs_f64()
        );
        truth_images.insert((c.width, c.height), images);
    }

    // Every configuration at every pose: images (RGB) and times.
    let mut rendered: Vec<(Vec<Vec<u8>>, Vec<f64>)> = Vec::with_capacity(configs.len());
    for c in &configs {
        let renderer = if c.truth_poses {
            &mut truth_renderer
        } else {
            &mut reg_renderer
        };
        let settings = c.settings();
        let mut draw = |camera: &VirtualCamera| -> Result<image::RgbaImage> {
            match c.vdtm {
                Some(v) => {
                    vdtm.settings = v;
                    vdtm.render_to_image(gpu, camera, BACKGROUND)?
                        .context("VDTM: nothing prepared")
                }
                None => Ok(renderer.render_to_image(camera, &settings)?.0),
            }
        };
        // One warm-up frame (pipelines for the format, targets of this size).
        let warm = VirtualCamera::new(poses[0].world_from_eo, fov, c.width, c.height)?;
        draw(&warm)?;
        let mut images = Vec::with_capacity(poses.len());
        let mut times = Vec::with_capacity(poses.len());
        for p in &poses {
            let camera = VirtualCamera::new(p.world_from_eo, fov, c.width, c.height)?;
            let started = Instant::now();
            let image = draw(&camera)?;
            times.push(started.elapsed().as_secs_f64() * 1e3);
            images.push(
                image
                    .pixels()
                    .flat_map(|px| [px[0], px[1], px[2]])
                    .collect::<Vec<u8>>(),
            );
        }
        rendered.push((images, times));
    }
    if let Some(dir) = &args.images {
        write_images(&dir.join(scene), &configs, &rendered, &truth_images)?;
    }

    // The mask of a pose at a resolution: pixels every configuration of that
    // resolution covers.
    let covered =
        |rgb: &[u8]| -> Vec<bool> { rgb.chunks_exact(3).map(|p| p != BACKGROUND_RGB).collect() };
    let mut masks: std::collections::BTreeMap<(u32, u32, usize), Vec<bool>> = Default::default();
    for (c, (images, _)) in configs.iter().zip(&rendered) {
        for (i, img) in images.iter().enumerate() {
            let cov = covered(img);
            masks
                .entry((c.width, c.height, i))
                .and_modify(|m| m.iter_mut().zip(&cov).for_each(|(a, b)| *a &= *b))
                .or_insert(cov);
        }
    }

    let mut rows = Vec::new();
    for (c, (images, times)) in configs.iter().zip(&rendered) {
        let truths = &truth_images[&(c.width, c.height)];
        let pixels = (c.width * c.height) as usize;
        let (mut psnr, mut ssim, mut sq, mut scored, mut cov) = (0.0, 0.0, 0.0, 0usize, 0usize);
        let mut n = 0usize;
        for (i, img) in images.iter().enumerate() {
            let mask = &masks[&(c.width, c.height, i)];
            cov += covered(img).iter().filter(|v| **v).count();
            let Some(Score {
                mse,
                ssim: s,
                pixels: p,
            }) = metrics::score(img, &truths[i], mask, c.width as usize, c.height as usize)
            else {
                continue;
            };
            psnr += metrics::psnr_db(mse);
            ssim += s;
            sq += mse * p as f64;
            scored += p;
            n += 1;
        }
        let n_f = n.max(1) as f64;
        let mut sorted = times.clone();
        sorted.sort_by(f64::total_cmp);
        rows.push(Row {
            config: c.clone(),
            psnr_db: psnr / n_f,
            ssim: ssim / n_f,
            mse: if scored > 0 {
                sq / scored as f64
            } else {
                f64::NAN
            },
            coverage: cov as f64 / (pixels * images.len().max(1)) as f64,
            scored: scored as f64 / (pixels * images.len().max(1)) as f64,
            frame_ms: sorted.get(sorted.len() / 2).copied().unwrap_or(f64::NAN),
        });
    }
    let flicker = flicker::measure(
        gpu,
        &sim,
        &mut reg_renderer,
        &mut vdtm,
        fov,
        if args.quick { 12 } else { 36 },
    )?;
    Ok(SceneResult {
        scene: scene.to_string(),
        frames,
        scans: registered.model.len(),
        poses: poses.len(),
        registration_ate_mm: ate_mm(&registered.model, &truth.model),
        registration_s,
        rows,
        vdtm: Some(vdtm.status.clone()),
        flicker,
    })
}
