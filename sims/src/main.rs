//! `texel-sims`: render simulated captures, clean views, list effects, benchmark,
//! serve a virtual serial lidar, generate textures.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use sims::effects::effect_docs;
use sims::{BackendKind, CaptureOptions, Scene, SimOptions, Simulator, render_capture};
use texel::PinholeCamera;

mod cli_backends;
mod cli_bench;
mod cli_serial;

#[derive(Parser)]
#[command(name = "texel-sims", version, about = "The simulated texel camera")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum Backend {
    Builtin,
    Mitsuba,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene's trajectory into a capture (MCAP).
    Render {
        #[arg(long)]
        scene: PathBuf,
        #[arg(long)]
        out: PathBuf,
        /// Number of frames (default: the trajectory's).
        #[arg(long)]
        frames: Option<usize>,
        /// Seed of every random number.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Renderer (default: builtin, or mitsuba when an effect needs it).
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Replace the scene's effects: a comma-separated list of names, or "none".
        #[arg(long)]
        effects: Option<String>,
    },
    /// Render one clean ground-truth EO image from any pose: an 8-bit picture (PNG),
    /// or, when OUT ends in `.exr`, the linear radiance in 32-bit floats (OpenEXR), the
    /// truth high-dynamic-range results are scored against.
    View {
        #[arg(long)]
        scene: PathBuf,
        /// world_from_eo as "x y z qx qy qz qw" (EO optical frame: x right, y down,
        /// z forward).
        #[arg(long, allow_hyphen_values = true)]
        pose: String,
        #[arg(long)]
        out: PathBuf,
        /// Image width (default: the scene's EO camera).
        #[arg(long)]
        width: Option<u32>,
        #[arg(long)]
        height: Option<u32>,
        /// Vertical field of view of an undistorted pinhole centred on the image
        /// (default: the scene's EO camera, without distortion).
        #[arg(long)]
        fov_deg: Option<f64>,
    },
    /// List every effect with its model, parameters, units and defaults.
    Effects,
    /// Measure texel frames per second: no effects (the baseline), each effect alone,
    /// the scene's default effects, and all effects.
    Bench {
        #[arg(long)]
        scene: PathBuf,
        /// Frames rendered per configuration.
        #[arg(long, default_value_t = 30)]
        frames: usize,
        /// Interleaved rounds the frames are split into (each configuration's fastest
        /// round is shown: more rounds ride out more bursts of load).
        #[arg(long, default_value_t = 3)]
        rounds: usize,
        /// Also time the Mitsuba backend against the built-in one on the same clean
        /// range and EO images, and measure how far their images differ.
        #[arg(long)]
        mitsuba: bool,
    },
    /// Serve the scene's lidar frames as a virtual TXL1 serial device (a new
    /// pseudo-terminal whose path is printed, or --tty), with fault injection.
    ServeSerial(cli_serial::ServeSerial),
    /// Write the procedural mural texture as a PNG.
    Texture {
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 512)]
        width: u32,
        #[arg(long, default_value_t = 256)]
        height: u32,
        #[arg(long, default_value_t = 7)]
        seed: u64,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Render {
            scene,
            out,
            frames,
            seed,
            backend,
            effects,
        } => render(&scene, &out, frames, seed, backend, effects.as_deref()),
        Command::View {
            scene,
            pose,
            out,
            width,
            height,
            fov_deg,
        } => view(&scene, &pose, &out, width, height, fov_deg),
        Command::Bench {
            scene,
            frames,
            rounds,
            mitsuba,
        } => {
            cli_bench::bench(&scene, frames, rounds)?;
            if mitsuba {
                cli_backends::bench_backends(&scene, frames)?;
            }
            Ok(())
        }
        Command::ServeSerial(args) => cli_serial::serve_serial(&args),
        Command::Effects => {
            print_effects();
            Ok(())
        }
        Command::Texture {
            out,
            width,
            height,
            seed,
        } => {
            if !(1..=4096).contains(&width) || !(1..=4096).contains(&height) {
                bail!("texture sides must be in 1..=4096");
            }
            let rgb = sims::texture_gen::mural(width, height, seed);
            image::save_buffer(&out, &rgb, width, height, image::ExtendedColorType::Rgb8)
                .with_context(|| format!("cannot write {}", out.display()))
        }
    }
}

fn parse_effects(list: &str) -> Result<Vec<sims::Effect>> {
    if list.trim() == "none" {
        return Ok(Vec::new());
    }
    list.split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|name| sims::Effect::with_defaults(name).map_err(anyhow::Error::msg))
        .collect()
}

fn render(
    scene_path: &Path,
    out: &Path,
    frames: Option<usize>,
    seed: u64,
    backend: Option<Backend>,
    effects: Option<&str>,
) -> Result<()> {
    let backend = match backend {
        None => BackendKind::Auto,
        Some(Backend::Builtin) => BackendKind::Builtin,
        Some(Backend::Mitsuba) => BackendKind::Mitsuba,
    };
    let scene = Scene::load(scene_path)?;
    let options = SimOptions {
        seed,
        frames,
        backend,
        effects: effects.map(parse_effects).transpose()?,
        ..SimOptions::default()
    };
    let sim = Simulator::with_options(scene, &options)?;
    let total = sim.frame_count();
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} frames {per_sec} ETA {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let start = Instant::now();
    let summary = render_capture(&sim, out, &CaptureOptions::default(), &mut |done, _| {
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    println!(
        "wrote {} frames ({} messages) to {} in {:.2} s ({:.1} frames/s); backend: {}; effects: {}",
        summary.frames,
        summary.messages,
        summary.path.display(),
        secs,
        summary.frames as f64 / secs.max(1e-9),
        sim.backend_name(),
        {
            let names = sim.effects().names();
            if names.is_empty() {
                "none".to_string()
            } else {
                names.join(", ")
            }
        }
    );
    Ok(())
}

fn view(
    scene_path: &Path,
    pose: &str,
    out: &Path,
    width: Option<u32>,
    height: Option<u32>,
    fov_deg: Option<f64>,
) -> Result<()> {
    let scene = Scene::load(scene_path)?;
    let world_from_eo = texel::pose::parse_pose(pose).context("--pose")?;
    let eo = &scene.sensor().eo;
    let width = width.unwrap_or(eo.width);
    let height = height.unwrap_or(eo.height);
    if !(1..=sims::scene::MAX_EO_SIDE).contains(&width)
        || !(1..=sims::scene::MAX_EO_SIDE).contains(&height)
    {
        bail!(
            "image size {width}x{height} is outside 1..={} per side",
            sims::scene::MAX_EO_SIDE
        );
    }
    // The scene camera's vertical field of view, from its focal length.
    let default_fov = 2.0 * (0.5 * f64::from(eo.height) / eo.fy).atan().to_degrees();
    let camera = PinholeCamera::from_vertical_fov(width, height, fov_deg.unwrap_or(default_fov))
        .context("--fov-deg")?;
    if out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"))
    {
        let radiance = scene.radiance_view(&world_from_eo, &camera);
        texel::radiance::exr::write_radiance_exr(out, width, height, &radiance)?;
        return Ok(());
    }
    let frame = scene.render_view(&world_from_eo, &camera);
    image::save_buffer(
        out,
        &frame.rgb,
        width,
        height,
        image::ExtendedColorType::Rgb8,
    )
    .with_context(|| format!("cannot write {}", out.display()))?;
    Ok(())
}

fn print_effects() {
    for doc in effect_docs() {
        let target = match doc.target {
            sims::effects::Target::Lidar => "lidar",
            sims::effects::Target::Eo => "EO",
            sims::effects::Target::Optics => "lidar + EO",
        };
        let needs = if doc.needs_mitsuba {
            "; needs the Mitsuba backend, which it selects"
        } else {
            ""
        };
        println!("{} ({target}{needs})", doc.name);
        println!("    {}", doc.model);
        for (p, default) in &doc.params {
            println!(
                "    {:<20} default {:<10} [{}] {}",
                p.name, default, p.unit, p.what
            );
        }
        println!();
    }
}
