//! `texel-calib`: calibrates a texel camera from a capture of a checkerboard target,
//! and recovers the EO camera's response curve from an exposure bracket. (Measuring
//! calibration against the simulator's truth is `texel-bench calib`.)

use std::path::{Path, PathBuf};

use anyhow::Context;
use calib::config::CalibConfig;
use calib::pipeline::{Stage, calibrate};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use texel::SensorModel;

#[derive(Parser)]
#[command(
    name = "texel-calib",
    version,
    about = "Calibrates a texel camera from a capture of a checkerboard"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Calibrate from a capture of the target and write a sensor file.
    Run {
        /// The capture (MCAP) of the target.
        #[arg(long)]
        capture: PathBuf,
        /// The sensor file to write.
        #[arg(long)]
        out: PathBuf,
        /// Also write a Markdown report (with an SVG residual plot and PNG images).
        #[arg(long)]
        report: Option<PathBuf>,
        /// Calibration settings (TOML: [target], [solver]); defaults otherwise.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Name written into the sensor file (default: the output file's stem).
        #[arg(long)]
        name: Option<String>,
    },
    /// Recover the EO camera's response curve (Debevec & Malik 1997) from a bracket
    /// of images of a still scene, and write it as CSV: `z,g_r,g_g,g_b` per 8-bit
    /// value, `g` the natural log of exposure (radiance times seconds), g(128) = 0.
    Response {
        /// One image of the bracket (PNG or any format the `image` crate reads), with
        /// its exposure time: `FILE@SECONDS`. Repeat for each exposure.
        #[arg(long = "image", required_unless_present = "capture", conflicts_with = "capture", value_parser = parse_exposure)]
        images: Vec<(PathBuf, f64)>,
        /// A capture of a still scene whose EO frames record their exposure
        /// (`/eo/exposure`): the first frame of each distinct exposure (time × gain)
        /// makes the bracket.
        #[arg(long, value_name = "BRACKET.mcap")]
        capture: Option<PathBuf>,
        /// Pixels sampled (spread over the middle exposure's values).
        #[arg(long, default_value_t = 100)]
        samples: usize,
        /// Smoothness (the paper's lambda).
        #[arg(long, default_value_t = 50.0)]
        lambda: f64,
        /// The CSV file to write.
        #[arg(long)]
        out: PathBuf,
        /// A sensor file to carry the curve: it is read, given the curve as its
        /// `[eo_response]`, and written to `--sensor-out`.
        #[arg(long, requires = "sensor_out")]
        sensor_in: Option<PathBuf>,
        /// Where the sensor file with the curve is written.
        #[arg(long, requires = "sensor_in")]
        sensor_out: Option<PathBuf>,
    },
}

/// `FILE@SECONDS`.
fn parse_exposure(text: &str) -> Result<(PathBuf, f64), String> {
    let (file, seconds) = text
        .rsplit_once('@')
        .ok_or_else(|| format!("expected FILE@SECONDS, got {text:?}"))?;
    let seconds: f64 = seconds
        .parse()
        .map_err(|e| format!("exposure time {seconds:?} in {text:?}: {e}"))?;
    Ok((PathBuf::from(file), seconds))
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Run {
            capture,
            out,
            report,
            config,
            name,
        } => run(&capture, &out, report.as_deref(), config.as_deref(), name),
        Command::Response {
            images,
            capture,
            samples,
            lambda,
            out,
            sensor_in,
            sensor_out,
        } => {
            let bracket = match &capture {
                Some(path) => bracket_of_capture(path)?,
                None => bracket_of_images(&images)?,
            };
            let curves = response(&bracket, samples, lambda, &out)?;
            if let (Some(sensor_in), Some(sensor_out)) = (sensor_in, sensor_out) {
                sensor_with_response(&curves, &sensor_in, &sensor_out)?;
            }
            Ok(())
        }
    }
}

/// A bracket: each exposure's interleaved RGB8 pixels and exposure (seconds, times
/// the gain), all of one size.
struct Bracket {
    images: Vec<Vec<u8>>,
    exposures: Vec<f64>,
}

fn bracket_of_images(images: &[(PathBuf, f64)]) -> anyhow::Result<Bracket> {
    let mut pixels = Vec::with_capacity(images.len());
    let mut size: Option<(u32, u32)> = None;
    for (path, _) in images {
        let img = image::open(path)
            .with_context(|| format!("reading {}", path.display()))?
            .to_rgb8();
        let dims = img.dimensions();
        if let Some(first) = size
            && first != dims
        {
            anyhow::bail!(
                "{} is {}x{}, the first image is {}x{}: a bracket's images must align",
                path.display(),
                dims.0,
                dims.1,
                first.0,
                first.1
            );
        }
        size = Some(dims);
        pixels.push(img.into_raw());
    }
    Ok(Bracket {
        images: pixels,
        exposures: images.iter().map(|(_, t)| *t).collect(),
    })
}

/// The first EO frame of each distinct exposure in a capture of a still scene.
fn bracket_of_capture(path: &Path) -> anyhow::Result<Bracket> {
    use texel::capture::{CaptureEvent, CaptureReader, topics};
    let mut reader = CaptureReader::open(path)?;
    let mut bracket = Bracket {
        images: Vec::new(),
        exposures: Vec::new(),
    };
    let mut size = None;
    let mut without_exposure = 0usize;
    reader.for_each_event(
        &[
            topics::EO_IMAGE,
            topics::EO_IMAGE_COMPRESSED,
            topics::EO_EXPOSURE,
        ],
        |event| {
            let CaptureEvent::Eo(frame) = event else {
                return;
            };
            let Some(exposure) = frame.exposure else {
                without_exposure += 1;
                return;
            };
            let scale = exposure.scale();
            if bracket.exposures.len() >= calib::response::MAX_EXPOSURES
                || bracket
                    .exposures
                    .iter()
                    .any(|e| (e / scale - 1.0).abs() < 1e-9)
                || size.is_some_and(|s| s != (frame.width, frame.height))
            {
                return;
            }
            size = Some((frame.width, frame.height));
            bracket.exposures.push(scale);
            bracket.images.push(frame.rgb);
        },
    );
    if bracket.exposures.len() < 2 {
        anyhow::bail!(
            "{}: {} distinct exposures recorded ({without_exposure} EO frames say nothing of \
             theirs): a bracket needs at least two (/eo/exposure)",
            path.display(),
            bracket.exposures.len()
        );
    }
    println!(
        "{}: a bracket of {} exposures from {:.6} to {:.6} s",
        path.display(),
        bracket.exposures.len(),
        bracket
            .exposures
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min),
        bracket.exposures.iter().copied().fold(0.0, f64::max)
    );
    Ok(bracket)
}

fn response(
    bracket: &Bracket,
    samples: usize,
    lambda: f64,
    out: &Path,
) -> anyhow::Result<[calib::response::ResponseCurve; 3]> {
    let refs: Vec<&[u8]> = bracket.images.iter().map(Vec::as_slice).collect();
    let curves = calib::response::recover_rgb_response(&refs, &bracket.exposures, samples, lambda)?;
    let mut text = String::from("z,g_r,g_g,g_b\n");
    for z in 0..calib::response::LEVELS {
        text.push_str(&format!(
            "{z},{:.6},{:.6},{:.6}\n",
            curves[0].log_exposure[z], curves[1].log_exposure[z], curves[2].log_exposure[z]
        ));
    }
    std::fs::write(out, text).with_context(|| format!("writing {}", out.display()))?;
    println!(
        "response from {} exposures: ln exposure at z = 16 / 240: r {:.3} / {:.3}, g {:.3} / {:.3}, b {:.3} / {:.3}; wrote {}",
        bracket.exposures.len(),
        curves[0].log_exposure[16],
        curves[0].log_exposure[240],
        curves[1].log_exposure[16],
        curves[1].log_exposure[240],
        curves[2].log_exposure[16],
        curves[2].log_exposure[240],
        out.display()
    );
    Ok(curves)
}

/// Writes `sensor_in` with the recovered curve as its `[eo_response]` to `sensor_out`.
fn sensor_with_response(
    curves: &[calib::response::ResponseCurve; 3],
    sensor_in: &Path,
    sensor_out: &Path,
) -> anyhow::Result<()> {
    let mut sensor = texel::SensorModel::load(sensor_in)?;
    sensor.eo_response = Some(
        calib::response::to_eo_response(curves)
            .context("the recovered curve cannot go into a sensor file")?,
    );
    let text = format!(
        "# {} with the EO response curve recovered by texel-calib response\n{}",
        sensor_in.display(),
        sensor.to_toml_string()
    );
    std::fs::write(sensor_out, text)
        .with_context(|| format!("writing {}", sensor_out.display()))?;
    println!(
        "wrote {} with the curve as [eo_response]",
        sensor_out.display()
    );
    Ok(())
}

fn progress_bar() -> ProgressBar {
    let bar = ProgressBar::new(1);
    bar.set_style(
        ProgressStyle::with_template("{msg:28} [{bar:40}] {pos}/{len} ({elapsed})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar
}

fn run(
    capture: &Path,
    out: &Path,
    report: Option<&Path>,
    config: Option<&Path>,
    name: Option<String>,
) -> anyhow::Result<()> {
    let config = match config {
        Some(p) => CalibConfig::load(p)?,
        None => CalibConfig::default(),
    };
    eprintln!("reading {}", capture.display());
    let mut input = calib::capture::read_capture(capture)?;
    for w in &input.warnings {
        eprintln!("warning: {w}");
    }
    input.info.name = name.unwrap_or_else(|| {
        out.file_stem()
            .map_or_else(|| "calibrated".into(), |s| s.to_string_lossy().into_owned())
    });
    let bar = progress_bar();
    let mut stage = None;
    let result = calibrate(&input, &config, &mut |s: Stage, done, total| {
        if stage != Some(s) {
            stage = Some(s);
            bar.set_message(s.name());
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    let calibration = result?;
    let text = calibration.sensor_file_text(&capture.display().to_string());
    // The written file must read back as a sensor file.
    SensorModel::from_toml_str(&text, &out.display().to_string())
        .context("the calibrated sensor file does not read back")?;
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(out, text).with_context(|| format!("writing {}", out.display()))?;
    let eo = &calibration.eo;
    let l = &calibration.lidar;
    println!(
        "EO: fx {:.3} ± {:.3}, fy {:.3} ± {:.3}, cx {:.3} ± {:.3}, cy {:.3} ± {:.3} px; \
         RMS {:.4} px over {} views",
        eo.intrinsics[0],
        eo.intrinsics_std[0],
        eo.intrinsics[1],
        eo.intrinsics_std[1],
        eo.intrinsics[2],
        eo.intrinsics_std[2],
        eo.intrinsics[3],
        eo.intrinsics_std[3],
        eo.rms_px,
        eo.per_view.len()
    );
    let t = l.eo_from_lidar.translation.vector * 1e3;
    println!(
        "eo_from_lidar: translation [{:.2}, {:.2}, {:.2}] mm (std [{:.2}, {:.2}, {:.2}]), \
         rotation {:.4} deg (std [{:.4}, {:.4}, {:.4}]); range bias {:+.2} ± {:.2} mm; \
         {} lidar views",
        t.x,
        t.y,
        t.z,
        l.translation_std_m[0] * 1e3,
        l.translation_std_m[1] * 1e3,
        l.translation_std_m[2] * 1e3,
        l.eo_from_lidar.rotation.angle().to_degrees(),
        l.rotation_std_deg[0],
        l.rotation_std_deg[1],
        l.rotation_std_deg[2],
        l.range_bias_m * 1e3,
        l.range_bias_std_m * 1e3,
        l.per_view.len()
    );
    println!("wrote {}", out.display());
    if let Some(report) = report {
        let files = calib::report::write_report(
            &calibration,
            &input,
            &capture.display().to_string(),
            report,
        )?;
        println!(
            "wrote {} (+ {} and {} images)",
            files.markdown.display(),
            files.plot.display(),
            files.images.len()
        );
    }
    Ok(())
}
