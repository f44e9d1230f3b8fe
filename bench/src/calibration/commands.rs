//! `texel-bench calib`: calibration measured against the simulator's truth (accuracy
//! over simulated views of the target, the fusion and registration check with a
//! calibrated sensor, the poses of the calibration scene, the tradeoffs section).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use calib::config::CalibConfig;
use calib::pipeline::calibrate;
use clap::Subcommand;
use texel::SensorModel;
use texel_register::RegistrationConfig;

use super::lab_check;
use super::simulate::{self, PoseStyle};

/// Calibration against the simulator's truth.
#[derive(Subcommand)]
pub enum CalibCommand {
    /// Calibrate from simulated views of the calib-target scene and print the errors
    /// against the true sensor model, and the fusion check on the lab scene.
    Accuracy {
        #[arg(long, default_value = "configs/scenes/calib-target.toml")]
        scene: PathBuf,
        #[arg(long, default_value = "configs/scenes/lab.toml")]
        lab: PathBuf,
        /// Calibration views (plus 6 held-out views).
        #[arg(long, default_value_t = 40)]
        views: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Lab frames fused for the fusion check.
        #[arg(long, default_value_t = 3)]
        lab_frames: usize,
        /// Lab frames rendered into a capture and registered for the registration
        /// check (0: none).
        #[arg(long, default_value_t = 0)]
        register_frames: usize,
    },
    /// Fuse frames of a scene (rendered with its true sensor) with a sensor file and
    /// with the true sensor, and compare the errors; then register a capture of the
    /// scene with the daemon's offline path (`texeld register`) using each sensor, and
    /// compare the trajectory errors.
    FusionCheck {
        #[arg(long)]
        sensor: PathBuf,
        #[arg(long, default_value = "configs/scenes/lab.toml")]
        scene: PathBuf,
        #[arg(long, default_value_t = 3)]
        frames: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Frames of the scene rendered into a capture and registered (0: skip the
        /// registration check).
        #[arg(long, default_value_t = 12)]
        register_frames: usize,
        /// Register this capture (rendered with the true sensor, with /truth/pose)
        /// instead of rendering one.
        #[arg(long)]
        lab_capture: Option<PathBuf>,
        /// Registration settings (TOML, the keys of `texeld register --config`).
        #[arg(long)]
        registration: Option<PathBuf>,
    },
    /// Print the `[trajectory] poses` of a calibration capture as TOML lines: views of
    /// the scene's board sampled as the calibration guide asks (the poses of
    /// configs/scenes/calib-target.toml are `--count 80 --seed 2024`).
    Poses {
        #[arg(long, default_value = "configs/scenes/calib-target.toml")]
        scene: PathBuf,
        #[arg(long, default_value_t = 80)]
        count: usize,
        #[arg(long, default_value_t = 2024)]
        seed: u64,
    },
}

/// Runs one `texel-bench calib` command.
pub fn run(command: CalibCommand) -> anyhow::Result<()> {
    match command {
        CalibCommand::Accuracy {
            scene,
            lab,
            views,
            seed,
            lab_frames,
            register_frames,
        } => accuracy(&scene, &lab, views, seed, lab_frames, register_frames),
        CalibCommand::FusionCheck {
            sensor,
            scene,
            frames,
            seed,
            register_frames,
            lab_capture,
            registration,
        } => {
            let model = SensorModel::load(&sensor)?;
            compare_fusion(&model, &scene, frames, seed)?;
            let config = match registration {
                Some(p) => RegistrationConfig::load(&p)?,
                None => RegistrationConfig::default(),
            };
            match lab_capture {
                Some(capture) => compare_registration(&model, &capture, &config),
                None if register_frames > 0 => {
                    render_and_register(&model, &scene, register_frames, seed, &config)
                }
                None => Ok(()),
            }
        }
        CalibCommand::Poses { scene, count, seed } => print_poses(&scene, count, seed),
    }
}

fn print_poses(scene: &Path, count: usize, seed: u64) -> anyhow::Result<()> {
    let sim = simulate::simulator(sims::Scene::load(scene)?, seed, Some(Vec::new()))?;
    let poses = simulate::sample_poses(
        &sim,
        &CalibConfig::default().target,
        count,
        PoseStyle::Varied,
        seed,
    );
    if poses.len() < count {
        bail!(
            "could place only {} of {count} views of the board",
            poses.len()
        );
    }
    for pose in &poses {
        let (t, q) = texel::pose::pose_to_parts(pose);
        println!(
            "    {{ position = [{:.4}, {:.4}, {:.4}], rotation_xyzw = [{:.6}, {:.6}, {:.6}, \
             {:.6}] }},",
            t[0], t[1], t[2], q[0], q[1], q[2], q[3]
        );
    }
    Ok(())
}

fn accuracy(
    scene: &Path,
    lab: &Path,
    views: usize,
    seed: u64,
    lab_frames: usize,
    register_frames: usize,
) -> anyhow::Result<()> {
    if views < 3 {
        bail!("--views must be at least 3");
    }
    let config = CalibConfig::default();
    let sim = simulate::simulator(sims::Scene::load(scene)?, seed, None)?;
    let poses = simulate::sample_poses(&sim, &config.target, views + 6, PoseStyle::Varied, seed);
    if poses.len() < views + 6 {
        bail!("could not place {} views of the board", views + 6);
    }
    eprintln!("rendering {} views", views + 6);
    let input = simulate::render_input(&sim, &poses[..views], 0);
    let held = simulate::render_input(&sim, &poses[views..], 10_000);
    let calibration = calibrate(&input, &config, &mut |_, _, _| {})?;
    let a = simulate::accuracy(&calibration, sim.sensor_model(), &held, &config.target);
    println!(
        "calibration from {views} simulated views (seed {seed}), all effects of {}:",
        scene.display()
    );
    println!(
        "  focal length error        {:.4} %   (limit 0.2 %)",
        a.focal_error_percent
    );
    println!(
        "  principal point error     {:.3} px  (limit 1 px; cx {:+.3}, cy {:+.3})",
        a.principal_point_error_px,
        calibration.sensor.eo.cx - sim.sensor_model().eo.cx,
        calibration.sensor.eo.cy - sim.sensor_model().eo.cy
    );
    println!(
        "    (EO-only stage: cx {:+.3}, cy {:+.3}; standard deviations {:.3}, {:.3})",
        calibration.eo_only.intrinsics[2] - sim.sensor_model().eo.cx,
        calibration.eo_only.intrinsics[3] - sim.sensor_model().eo.cy,
        calibration.eo.intrinsics_std[2],
        calibration.eo.intrinsics_std[3]
    );
    println!(
        "  held-out reprojection RMS {:.4} px  (limit 0.2 px; {} held-out views)",
        a.held_out_rms_px, a.held_out_views
    );
    println!(
        "  EO model difference RMS   {:.3} px  (same rays, whole image)",
        a.model_rms_px
    );
    println!(
        "  extrinsic rotation error  {:.4} deg (limit 0.05 deg; stated standard deviations \
         {:.4}, {:.4}, {:.4} deg about x, y, z)",
        a.rotation_error_deg,
        calibration.lidar.rotation_std_deg[0],
        calibration.lidar.rotation_std_deg[1],
        calibration.lidar.rotation_std_deg[2]
    );
    println!(
        "  extrinsic translation err {:.3} mm  (limit 2 mm)",
        a.translation_error_mm
    );
    println!(
        "  range bias                {:+.3} mm ± {:.3} (truth {:+.3} mm)",
        a.range_bias_mm,
        calibration.lidar.range_bias_std_m * 1e3,
        sim.sensor_model().range_bias_m * 1e3
    );
    println!(
        "  time: detection {:.2} s, estimation {:.2} s",
        calibration.seconds_detect, calibration.seconds_solve
    );
    if lab_frames > 0 {
        compare_fusion(&calibration.sensor, lab, lab_frames, seed)?;
    }
    if register_frames > 0 {
        let config = RegistrationConfig::default();
        render_and_register(&calibration.sensor, lab, register_frames, seed, &config)?;
    }
    Ok(())
}

/// Renders `frames` frames of `scene` into a temporary capture and compares their
/// registration with `model` and with the true sensor.
fn render_and_register(
    model: &SensorModel,
    scene: &Path,
    frames: usize,
    seed: u64,
    config: &RegistrationConfig,
) -> anyhow::Result<()> {
    let dir = tempfile::tempdir().context("creating a temporary directory")?;
    let capture = dir.path().join("lab.mcap");
    eprintln!(
        "rendering {frames} frames of {} into a capture",
        scene.display()
    );
    lab_check::render_lab_capture(sims::Scene::load(scene)?, seed, frames, &capture)?;
    compare_registration(model, &capture, config)
}

fn compare_registration(
    model: &SensorModel,
    capture: &Path,
    config: &RegistrationConfig,
) -> anyhow::Result<()> {
    let dir = tempfile::tempdir().context("creating a temporary directory")?;
    eprintln!("registering {} with each sensor", capture.display());
    let c = lab_check::compare_registration(capture, model, dir.path(), config)?;
    println!(
        "registration of {} ({} frames, texeld register's path, against /truth/pose):",
        capture.display(),
        c.truth.frames
    );
    println!(
        "  sensor     ATE RMSE (mm)  aligned ATE (mm)  mean RPE (mm)  mean RPE (deg)  registered"
    );
    for (name, e) in [("true", c.truth), ("calibrated", c.calibrated)] {
        println!(
            "  {name:10} {:13.3}  {:16.3}  {:13.3}  {:14.4}  {}/{}",
            e.ate_rmse_mm,
            e.aligned_ate_rmse_mm,
            e.rpe_translation_mm,
            e.rpe_rotation_deg,
            e.registered,
            e.frames
        );
    }
    println!(
        "  ratio calibrated/true: ATE {:.3}, aligned ATE {:.3} (within 10 % means <= 1.10)",
        c.ate_ratio(),
        c.aligned_ate_ratio()
    );
    Ok(())
}

fn compare_fusion(
    model: &SensorModel,
    scene: &Path,
    frames: usize,
    seed: u64,
) -> anyhow::Result<()> {
    let sim = simulate::simulator(sims::Scene::load(scene)?, seed, None)?;
    let n = frames.clamp(1, sim.frame_count());
    let step = (sim.frame_count() / n).max(1);
    let list: Vec<usize> = (0..n).map(|k| k * step).collect();
    let truth = simulate::fusion_errors(&sim, sim.sensor_model(), &list);
    let calibrated = simulate::fusion_errors(&sim, model, &list);
    let ratio = lab_check::ratio;
    println!(
        "fusion of {} frames of {} (rendered with the true sensor):",
        list.len(),
        scene.display()
    );
    println!("  sensor     point RMS (mm)  texture RMS (px)  colour RMS (8-bit)  points");
    for (name, e) in [("true", truth), ("calibrated", calibrated)] {
        println!(
            "  {name:10} {:14.3}  {:16.3}  {:18.3}  {}",
            e.point_rms_mm, e.texture_rms_px, e.colour_rms, e.points
        );
    }
    println!(
        "  ratio calibrated/true: points {:.3}, colour {:.3} (within 10 % means <= 1.10)",
        ratio(calibrated.point_rms_mm, truth.point_rms_mm),
        ratio(calibrated.colour_rms, truth.colour_rms)
    );
    Ok(())
}
