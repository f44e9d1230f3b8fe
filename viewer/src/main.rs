//! `texel-viewer`: renders the texel model headless (`render`), in a window (`open`),
//! or measures the renderer (`bench`).

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};
use texel::pose::parse_pose;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::capture_load::{LoadedCapture, load_capture};
use texel_viewer::composite::{MAX_K, Mode};
use texel_viewer::gpu::{GpuContext, RenderSettings, Renderer, Strategy};
use texel_viewer::headless::parse_views;

#[derive(Parser)]
#[command(
    name = "texel-viewer",
    version,
    about = "Renders the texel model with view-dependent blending"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render views of a capture's model to PNG files.
    Render(RenderArgs),
    /// Open a window on a capture's model.
    Open(OpenArgs),
    /// Measure frame time and GPU memory (k-buffer against naive layers).
    Bench(texel_viewer::bench::BenchArgs),
}

/// Where the model comes from: exactly one source (a live `--connect` joins this group).
#[derive(Args)]
#[group(required = true, multiple = false)]
struct SourceArgs {
    /// A capture (MCAP): every texel frame fused and placed by /texel/pose, else /truth/pose.
    #[arg(long, value_name = "RESULT.mcap")]
    capture: Option<PathBuf>,
}

impl SourceArgs {
    fn load(&self) -> anyhow::Result<LoadedCapture> {
        match &self.capture {
            Some(path) => load(path),
            None => bail!("give a model source (--capture)"),
        }
    }
}

#[derive(Args, Clone)]
struct DisplayArgs {
    /// painter, best, blended, scan-colour or reliability.
    #[arg(long, default_value = "blended")]
    mode: Mode,
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
        let mut s = RenderSettings::with_mode(self.mode);
        s.composite.blend_threshold = self.blend_threshold;
        s.composite.k = self.k;
        s.range_gamma = self.range_gamma;
        s.keep_stretched = self.keep_stretched;
        if self.naive {
            s.strategy = Strategy::NaiveLayers;
        }
        Ok(s)
    }
}

#[derive(Args)]
struct RenderArgs {
    #[command(flatten)]
    source: SourceArgs,
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
}

#[derive(Args)]
struct OpenArgs {
    /// The capture to open.
    capture: PathBuf,
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
    let loaded = args.source.load()?;
    let default_fov = VirtualCamera::fov_y_deg_of(&loaded.eo_camera);
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
    let mut renderer = Renderer::new(&gpu);
    renderer.sync_model(&loaded.model)?;
    for (out, pose, fov) in views {
        let camera = VirtualCamera::new(pose, fov, args.width, args.height)?;
        let (image, stats) = renderer.render_to_image(&camera, &settings)?;
        image
            .save(&out)
            .with_context(|| format!("writing {}", out.display()))?;
        eprintln!(
            "{}: {} scans drawn, {} outside the view, {} facing away",
            out.display(),
            stats.drawn,
            stats.culled_frustum,
            stats.culled_facing
        );
    }
    Ok(())
}

fn open(args: OpenArgs) -> anyhow::Result<()> {
    let settings = args.display.settings()?;
    let loaded = load(&args.capture)?;
    let (tx, rx) = std::sync::mpsc::sync_channel(64);
    let fov = VirtualCamera::fov_y_deg_of(&loaded.eo_camera);
    // The model reaches the window through the same channel a live stream will use.
    std::thread::spawn(move || {
        for event in loaded.model.snapshot() {
            if tx.send(event).is_err() {
                break;
            }
        }
    });
    texel_viewer::app::run(texel_viewer::app::AppOptions {
        title: format!("texel-viewer: {}", args.capture.display()),
        width: args.width,
        height: args.height,
        fov_deg: fov,
        settings,
        events: rx,
        screenshot: args.screenshot.map(|p| (p, args.frames)),
    })
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Render(a) => render(a),
        Command::Open(a) => open(a),
        Command::Bench(a) => texel_viewer::bench::run(&a),
    }
}
