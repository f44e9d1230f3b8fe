//! `texel-bench tradeoffs calibration`: what calibration accuracy costs in time. Renders views of
//! the calib-target scene with all its effects, calibrates with a growing number of
//! views and with a growing LM iteration limit, and measures the error against the
//! simulator's truth and the time taken. Writes its section of docs/tradeoffs.md
//! between its own markers, leaving the rest of the file alone.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::calibration::simulate::{self, PoseStyle};
use anyhow::{Context, bail};
use calib::config::CalibConfig;
use calib::pipeline::{CalibInput, calibrate};

pub const BEGIN: &str = "<!-- BEGIN calibration -->";
pub const END: &str = "<!-- END calibration -->";

#[derive(clap::Args)]
pub struct Args {
    #[arg(long, default_value = "configs/scenes/calib-target.toml")]
    scene: PathBuf,
    /// The document whose calibration section is rewritten ("-": print only).
    #[arg(long, default_value = "docs/tradeoffs.md")]
    doc: PathBuf,
    /// Numbers of calibration views.
    #[arg(long, value_delimiter = ',', default_value = "4,6,8,12,16,24,32,40")]
    views: Vec<usize>,
    /// LM iteration limits (with the largest number of views).
    #[arg(long, value_delimiter = ',', default_value = "1,2,3,5,10,100")]
    iterations: Vec<usize>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

struct Row {
    label: String,
    result: Result<Measured, String>,
}

struct Measured {
    accuracy: simulate::Accuracy,
    eo_rms_px: f64,
    detect_s: f64,
    solve_s: f64,
}

fn subset(input: &CalibInput, n: usize) -> CalibInput {
    CalibInput {
        views: input.views[..n.min(input.views.len())].to_vec(),
        lidar: input.lidar.clone(),
        info: input.info.clone(),
        warnings: Vec::new(),
    }
}

fn measure(
    input: &CalibInput,
    held: &CalibInput,
    config: &CalibConfig,
    truth: &texel::SensorModel,
) -> Result<Measured, String> {
    let c = calibrate(input, config, &mut |_, _, _| {}).map_err(|e| e.to_string())?;
    Ok(Measured {
        accuracy: simulate::accuracy(&c, truth, held, &config.target),
        eo_rms_px: c.eo.rms_px,
        detect_s: c.seconds_detect,
        solve_s: c.seconds_solve,
    })
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    let max_views = args.views.iter().copied().max().unwrap_or(0);
    if max_views == 0 || args.iterations.is_empty() {
        bail!("--views and --iterations need at least one positive value each");
    }
    let scene = sims::Scene::load(&args.scene)?;
    let sim = simulate::simulator(scene, args.seed, None)?;
    let config = CalibConfig::default();
    let poses = simulate::sample_poses(
        &sim,
        &config.target,
        max_views + 6,
        PoseStyle::Varied,
        args.seed,
    );
    if poses.len() < max_views + 6 {
        bail!("could not place {} views of the board", max_views + 6);
    }
    eprintln!("rendering {} views", max_views + 6);
    let render_start = Instant::now();
    let input = simulate::render_input(&sim, &poses[..max_views], 0);
    let held = simulate::render_input(&sim, &poses[max_views..], 10_000);
    let render_s = render_start.elapsed().as_secs_f64();
    let truth = sim.sensor_model().clone();
    let mut view_rows = Vec::new();
    for &n in &args.views {
        eprintln!("{n} views");
        view_rows.push(Row {
            label: n.to_string(),
            result: measure(&subset(&input, n), &held, &config, &truth),
        });
    }
    let mut iteration_rows = Vec::new();
    for &it in &args.iterations {
        eprintln!("{it} iterations");
        let mut c = config.clone();
        c.solver.max_iterations = it.max(1);
        iteration_rows.push(Row {
            label: it.to_string(),
            result: measure(&input, &held, &c, &truth),
        });
    }
    let section = render_section(args, max_views, render_s, &view_rows, &iteration_rows);
    print!("{section}");
    if args.doc.as_os_str() != "-" {
        write_section(&args.doc, &section)?;
        eprintln!("updated {}", args.doc.display());
    }
    Ok(())
}

fn table(s: &mut String, first: &str, rows: &[Row]) {
    let _ = writeln!(
        s,
        "| {first} | EO RMS (px) | focal error (%) | principal point error (px) | held-out RMS (px) | rotation error (deg) | translation error (mm) | range bias (mm) | detection (s) | estimation (s) |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        match &r.result {
            Ok(m) => {
                let a = &m.accuracy;
                let _ = writeln!(
                    s,
                    "| {} | {:.3} | {:.3} | {:.2} | {:.3} | {:.3} | {:.2} | {:+.2} | {:.2} | {:.3} |",
                    r.label,
                    m.eo_rms_px,
                    a.focal_error_percent,
                    a.principal_point_error_px,
                    a.held_out_rms_px,
                    a.rotation_error_deg,
                    a.translation_error_mm,
                    a.range_bias_mm,
                    m.detect_s,
                    m.solve_s
                );
            }
            Err(e) => {
                let _ = writeln!(
                    s,
                    "| {} | refused: {} |||||||||",
                    r.label,
                    e.replace('|', "/")
                );
            }
        }
    }
}

fn render_section(
    args: &Args,
    max_views: usize,
    render_s: f64,
    views: &[Row],
    iterations: &[Row],
) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "{BEGIN}");
    let _ = writeln!(s, "## Calibration\n");
    let _ = writeln!(
        s,
        "Generated by `cargo run --release -p texel-bench -- tradeoffs calibration` \
         (seed {}; {} threads). Views of `{}` with all its effects (sensor noise, \
         vignetting, lens distortion, range noise, quantisation, mixed pixels, \
         dropouts) from sampled poses (board tilted 25-55 degrees; every other view puts \
         it into the EO image's corners and edges, the others inside the lidar's view); \
         errors against the simulator's true sensor model; 6 \
         held-out views score the distortion. Rendering the {} views took {:.1} s (not \
         counted below). Detection is the board search in every view (EO and lidar); \
         estimation is Zhang's initialisation, the EO bundle adjustment and the joint \
         EO-lidar refinement.\n",
        args.seed,
        rayon::current_num_threads(),
        args.scene.display(),
        max_views + 6,
        render_s
    );
    let _ = writeln!(s, "### Number of views (LM limit 100 iterations)\n");
    table(&mut s, "views", views);
    let _ = writeln!(
        s,
        "\n### LM iteration limit ({max_views} views; every stage)\n"
    );
    table(&mut s, "iterations", iterations);
    let _ = writeln!(s, "\n{END}");
    s
}

/// Replaces the text between the markers (or appends the section; creates the file).
pub fn write_section(path: &Path, section: &str) -> anyhow::Result<()> {
    let old = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let new = match (old.find(BEGIN), old.find(END)) {
        (Some(b), Some(e)) if e > b => {
            format!(
                "{}{}{}",
                &old[..b],
                section.trim_end(),
                &old[e + END.len()..]
            )
        }
        _ if old.trim().is_empty() => format!(
            "# Tradeoffs: what accuracy costs in time\n\nEach section is written by its \
             own command; numbers are measured, never edited by hand.\n\n{section}"
        ),
        _ => format!("{}\n\n{section}", old.trim_end()),
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(path, new).with_context(|| format!("writing {}", path.display()))
}
