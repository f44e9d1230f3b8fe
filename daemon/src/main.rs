//! `texeld`: the Texel daemon and its capture tools.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use texel_daemon::cli::{self, RunOverrides};

#[derive(Parser)]
#[command(name = "texeld", version, about = "The Texel daemon and capture tools")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a session from a TOML session file (configs/sessions/*.toml): sources,
    /// pipeline, recording and the viewer stream, until SIGINT/SIGTERM (or the end of
    /// a replay when the session says so).
    Run {
        #[arg(long)]
        config: PathBuf,
        #[command(flatten)]
        overrides: RunOverrides,
    },
    /// Replay a capture through the pipeline, serving viewers and optionally recording
    /// the result; exits at the end of the capture. Scans are registered, unless the
    /// capture carries /texel/pose (then they are placed there).
    Replay {
        /// The capture (MCAP) file.
        capture: PathBuf,
        /// Times real time.
        #[arg(long, conflicts_with = "fast", default_value_t = 1.0)]
        speed: f64,
        /// As fast as the pipeline goes.
        #[arg(long)]
        fast: bool,
        /// Record the replayed frames and the poses to this capture.
        #[arg(long)]
        out: Option<PathBuf>,
        /// A session file for every other setting.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Keep serving the model after the capture ends, until SIGINT/SIGTERM.
        #[arg(long)]
        stay: bool,
        /// Register every scan, even when the capture carries /texel/pose.
        #[arg(long, conflicts_with = "capture_poses")]
        register: bool,
        /// Place scans at the capture's /texel/pose (else /truth/pose), no registration.
        #[arg(long)]
        capture_poses: bool,
        #[command(flatten)]
        overrides: RunOverrides,
    },
    /// Show what a capture holds: topics, message counts, duration, frame sizes,
    /// calibrations and the sensor JSON; report damage and spec violations.
    Info {
        /// The capture (MCAP) file.
        capture: PathBuf,
    },
    /// Write a capture's registered model (every frame placed by its /texel/pose, or
    /// registered now when the capture has none), or one texel frame with --frame, as
    /// PLY (points with colours and triangles) or glTF 2.0 (textured meshes; `.glb` for
    /// the binary container).
    Export {
        /// The capture (MCAP) file.
        capture: PathBuf,
        /// Only this texel frame, counting from 0 in file order.
        #[arg(long)]
        frame: Option<usize>,
        #[arg(long, value_enum)]
        format: texel_daemon::export::ExportFormat,
        /// With --frame: place the scan in the world by /texel/pose (else
        /// /truth/pose) instead of its own EO frame.
        #[arg(long, requires = "frame")]
        world: bool,
        /// With --format 3dtiles: LAT,LON,HEIGHT (degrees, degrees, metres above the
        /// WGS84 ellipsoid) of the world origin, world x east and y north there.
        /// Without it the tileset stays in the model's local frame.
        #[arg(long, value_parser = texel_daemon::tiles_export::parse_georef)]
        georef: Option<texel_lod::GeoReference>,
        /// With --format 3dtiles: TOML overrides of the level-of-detail defaults
        /// (leaf_voxel_m, tile_voxels, tile_triangle_budget, simplify_error_voxels,
        /// truncation_voxels).
        #[arg(long)]
        lod_config: Option<PathBuf>,
        /// With --format 3dtiles: compress each tile's geometry with
        /// EXT_meshopt_compression (CesiumJS, loaders.gl and three.js read it; readers
        /// without the extension cannot).
        #[arg(long)]
        meshopt: bool,
        /// With --format 3dtiles: the memory the tree's fields may hold, MiB (0: only
        /// what one scan or tile needs); the rest is paged to an unlinked file in the
        /// system's temporary folder.
        #[arg(long, default_value_t = 256)]
        field_memory_mb: u64,
        /// Which poses place the scans of a whole-model export: texel (/texel/pose, or
        /// registered now) or truth (/truth/pose of a simulated capture).
        #[arg(long, value_enum, default_value = "texel")]
        poses: texel_daemon::model_export::PoseChoice,
        #[arg(long)]
        out: PathBuf,
    },
    /// Register a capture offline: write a copy with /texel/pose for every registered
    /// frame, and optionally a JSON report (status, time, fitness, errors vs truth).
    Register {
        /// The capture (MCAP) file.
        capture: PathBuf,
        #[arg(long)]
        out: PathBuf,
        /// TOML overrides of the registration defaults.
        #[arg(long)]
        config: Option<PathBuf>,
        #[arg(long)]
        report: Option<PathBuf>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Run { config, overrides } => cli::run_command(Some(&config), None, &overrides),
        Command::Replay {
            capture,
            speed,
            fast,
            out,
            config,
            stay,
            register,
            capture_poses,
            mut overrides,
        } => {
            if out.is_some() {
                overrides.record = out;
            }
            use texel_daemon::config::RegistrationMode;
            let replay = cli::ReplayArgs {
                capture,
                speed,
                fast,
                stay,
                registration: match (register, capture_poses) {
                    (true, _) => Some(RegistrationMode::Register),
                    (_, true) => Some(RegistrationMode::CapturePoses),
                    _ => None,
                },
            };
            cli::run_command(config.as_deref(), Some(replay), &overrides)
        }
        Command::Info { capture } => match texel_daemon::info::summarize(&capture) {
            Ok(summary) => {
                print!("{summary}");
                if summary.is_clean() {
                    ExitCode::SUCCESS
                } else {
                    ExitCode::FAILURE
                }
            }
            Err(e) => {
                eprintln!("texeld info: {e}");
                ExitCode::FAILURE
            }
        },
        Command::Export {
            capture,
            frame,
            format,
            world,
            georef,
            lod_config,
            meshopt,
            field_memory_mb,
            poses,
            out,
        } => {
            if (georef.is_some() || lod_config.is_some() || meshopt)
                && format != texel_daemon::export::ExportFormat::Tiles3d
            {
                eprintln!(
                    "texeld export: --georef, --lod-config and --meshopt shape a 3D Tiles tileset; use them with --format 3dtiles"
                );
                return ExitCode::FAILURE;
            }
            let Some(frame) = frame else {
                if format == texel_daemon::export::ExportFormat::Tiles3d {
                    return export_tiles(
                        &capture,
                        &out,
                        georef.as_ref(),
                        lod_config.as_deref(),
                        if meshopt {
                            texel_lod::TileCompression::Meshopt
                        } else {
                            texel_lod::TileCompression::None
                        },
                        field_memory_mb,
                        poses,
                    );
                }
                return export_model(&capture, format, &out, poses);
            };
            export_frame(&capture, frame, format, world, &out)
        }
        Command::Register {
            capture,
            out,
            config,
            report,
        } => texel_daemon::register_cli::run(&capture, &out, config.as_deref(), report.as_deref()),
    }
}

fn export_frame(
    capture: &std::path::Path,
    frame: usize,
    format: texel_daemon::export::ExportFormat,
    world: bool,
    out: &std::path::Path,
) -> ExitCode {
    match texel_daemon::export::export_frame(capture, frame, format, world, out) {
        Ok(s) => {
            println!(
                "exported frame {frame} ({} ns): {} vertices, {} triangles, {} frame -> {}",
                s.timestamp_ns,
                s.vertices,
                s.usable_triangles,
                if s.world_from_scan.is_some() {
                    "world"
                } else {
                    "EO"
                },
                out.display()
            );
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("texeld export: {e}");
            ExitCode::FAILURE
        }
    }
}

fn export_tiles(
    capture: &std::path::Path,
    out: &std::path::Path,
    georef: Option<&texel_lod::GeoReference>,
    lod_config: Option<&std::path::Path>,
    compression: texel_lod::TileCompression,
    field_memory_mb: u64,
    poses: texel_daemon::model_export::PoseChoice,
) -> ExitCode {
    let registration = texel_register::RegistrationConfig::default();
    let lod = match lod_config.map(texel_daemon::tiles_export::load_lod_config) {
        None => texel_lod::LodConfig::default(),
        Some(Ok(config)) => config,
        Some(Err(e)) => {
            eprintln!("texeld export: {e}");
            return ExitCode::FAILURE;
        }
    };
    let tileset = texel_daemon::tiles_export::TilesetChoice {
        lod,
        geo: georef.copied(),
        compression,
        field_memory_budget_bytes: Some(
            usize::try_from(field_memory_mb.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
        ),
    };
    match texel_daemon::tiles_export::export_tiles(capture, out, &registration, &tileset, poses) {
        Ok(s) => {
            println!(
                "exported the model as 3D Tiles: {} scans of {} frames, {} tiles in {} levels, {} triangles, {} bytes (fields at most {} MiB in memory, {} MiB paged at the end; fused in {:.1} s, built in {:.1} s) -> {}",
                s.placement.scans,
                s.placement.frames,
                s.tiles,
                s.levels,
                s.triangles,
                s.bytes,
                s.peak_field_bytes / (1 << 20),
                s.field_paged_bytes / (1 << 20),
                s.fuse_s,
                s.build_s,
                out.display()
            );
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("texeld export: {e}");
            ExitCode::FAILURE
        }
    }
}

fn export_model(
    capture: &std::path::Path,
    format: texel_daemon::export::ExportFormat,
    out: &std::path::Path,
    poses: texel_daemon::model_export::PoseChoice,
) -> ExitCode {
    let config = texel_register::RegistrationConfig::default();
    match texel_daemon::model_export::export_model(capture, format, out, &config, poses) {
        Ok(s) => {
            println!(
                "exported the model: {} scans of {} frames ({} left out, poses {}): {} vertices, {} triangles -> {}",
                s.scans,
                s.frames,
                s.left_out,
                match s.poses {
                    texel_daemon::model_export::PoseSource::Capture => "from /texel/pose",
                    texel_daemon::model_export::PoseSource::Registered => "registered now",
                    texel_daemon::model_export::PoseSource::Truth => "from /truth/pose",
                },
                s.vertices,
                s.usable_triangles,
                out.display()
            );
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("texeld export: {e}");
            ExitCode::FAILURE
        }
    }
}
