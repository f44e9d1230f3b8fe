//! The registration section of `docs/tradeoffs.md`: a sweep of registration settings
//! over simulator captures (ATE, RPE, drift and time per scan on one core), Texel's
//! pairwise registration side by side with Open3D's point-to-plane ICP on the same
//! pairs, where the geometry is blind (corridor, floor, tunnel) Texel with and
//! without its EO term against Open3D's point-to-plane and colored ICP, and the pose
//! graph's optimisation time against the number of scans.
//!
//! The recipe:
//! 1. render (or take from the cache) and fuse the captures;
//! 2. run every setting over every capture;
//! 3. make the scan pairs, run Texel and Open3D on them, and on corridor pairs
//!    Texel with and without the EO term and Open3D's two ICPs;
//! 4. time pose-graph optimisations of 10 to 500 scans;
//! 5. write the Pareto plot, the eigenvalue figure, the raw results (JSON) and the
//!    Markdown section.

pub mod data;
pub mod eo;
pub mod graph_scaling;
pub mod open3d;
mod report;
pub mod sweep;

use std::path::Path;

use anyhow::{Context, Result};
use serde::Serialize;

use super::plot::{Series, write_pareto};
use super::{Paths, RunOptions, venv_python};
use texel_register::{AlignConfig, RegistrationConfig};

/// The captures of the sweep: scene, frame count (full run, quick run) and, for an
/// orbit, the frames of a full turn when they differ from the scene's (none do now:
/// `courtyard` walks a third of its circle at 1 degree and 17 cm a frame).
const SEQUENCES: [(&str, usize, usize, Option<usize>); 5] = [
    ("lab-walk", 200, 60, None),
    ("corridor", 288, 150, None),
    ("plane", 63, 30, None),
    ("tunnel", 121, 60, None),
    ("courtyard", 120, 40, None),
];

/// The pairwise comparison's scenes and pair counts (full, quick).
const PAIRS: [(&str, usize, usize); 2] = [("lab", 8, 2), ("courtyard", 4, 1)];
/// How far apart a pair's scans are.
const PAIR_ANGLE_DEG: f64 = 3.0;
const PAIR_DISTANCE_M: f64 = 0.05;
/// Corridor pairs for the EO comparison (full, quick).
const CORRIDOR_PAIRS: (usize, usize) = (6, 2);

/// Everything the run measured, also written as JSON next to the figures.
#[derive(Debug, Serialize)]
pub struct Results {
    pub quick: bool,
    pub load_average: String,
    pub sweep: Vec<sweep::RunMetrics>,
    pub open3d_version: String,
    pub texel_pairs: Vec<open3d::PairOutcome>,
    pub open3d_pairs: Vec<open3d::PairOutcome>,
    /// Corridor pairs: Texel with and without the EO term, Open3D point-to-plane and
    /// colored ICP.
    pub corridor_pairs: Vec<open3d::PairOutcome>,
    pub graph: Vec<graph_scaling::GraphTiming>,
}

/// Runs the measurements and returns the section's Markdown.
pub fn run(paths: &Paths, options: &RunOptions) -> Result<String> {
    let quick = options.quick;
    let load_before = load_average();
    // Step 1: the captures.
    let mut sequences = Vec::new();
    for (scene, full, short, orbit_period_frames) in SEQUENCES {
        let spec = data::SequenceSpec {
            scene,
            frames: if quick { short } else { full },
            seed: 1,
            orbit_period_frames,
        };
        sequences.push(data::sequence(&paths.scenes(), &paths.cache, &spec)?);
    }
    // Step 2: the sweep.
    let settings = sweep::settings(quick);
    let mut metrics = Vec::new();
    for setting in &settings {
        for sequence in &sequences {
            eprintln!("registering {} with {}", sequence.scene, setting.name);
            metrics.push(sweep::run(sequence, setting));
        }
    }
    // Step 3: pairs, Texel and Open3D.
    let mut pairs = Vec::new();
    for (scene, full, short) in PAIRS {
        let count = if quick { short } else { full };
        pairs.extend(data::perturbed_pairs(
            &paths.scenes(),
            scene,
            count,
            PAIR_ANGLE_DEG,
            PAIR_DISTANCE_M,
            5,
        )?);
    }
    let repeats = if quick { 2 } else { 5 };
    let align = AlignConfig::default();
    eprintln!("pairwise: Texel on {} pairs", pairs.len());
    let mut texel_pairs = open3d::run_texel(&pairs, "defaults", &align, repeats);
    let stride_1 = AlignConfig {
        point_stride: 1,
        ..align.clone()
    };
    texel_pairs.extend(open3d::run_texel(
        &pairs,
        "point stride 1",
        &stride_1,
        repeats,
    ));
    let python = options.python.clone().unwrap_or_else(venv_python);
    eprintln!(
        "pairwise: Open3D on {} pairs ({})",
        pairs.len(),
        python.display()
    );
    let (open3d_version, open3d_pairs) = open3d::run_open3d(
        &python,
        &open3d::script(&paths.repo),
        &paths.cache.join("open3d-pairs"),
        &pairs,
        &open3d::Open3dSettings {
            max_correspondence_distance_m: align.max_correspondence_distance_m,
            max_iterations: 30,
            repeats,
            colored: false,
        },
    )?;
    // Step 3b: corridor pairs, where the geometry leaves the axis free.
    let corridor = data::perturbed_pairs(
        &paths.scenes(),
        "corridor",
        if quick {
            CORRIDOR_PAIRS.1
        } else {
            CORRIDOR_PAIRS.0
        },
        PAIR_ANGLE_DEG,
        PAIR_DISTANCE_M,
        7,
    )?;
    eprintln!("corridor pairs: Texel and Open3D on {}", corridor.len());
    let (_, corridor_pairs) = eo::corridor_pairs(
        &corridor,
        &python,
        &open3d::script(&paths.repo),
        &paths.cache.join("open3d-corridor-pairs"),
        repeats,
    )?;
    // Step 4: the pose graph's cost.
    let sizes: &[usize] = if quick {
        &[10, 50, 100, 200]
    } else {
        &[10, 20, 50, 100, 200, 300, 400, 500]
    };
    eprintln!("pose graph: optimising {} sizes", sizes.len());
    let graph = graph_scaling::measure(
        sizes,
        RegistrationConfig::default().global.max_iterations,
        if quick { 1 } else { 3 },
    );
    let eigen_stem = (if quick {
        paths.quick_dir()
    } else {
        paths.figures()
    })
    .join(if quick {
        "registration-eo-eigenvalues-quick"
    } else {
        "registration-eo-eigenvalues"
    });
    std::fs::create_dir_all(eigen_stem.parent().unwrap_or(Path::new(".")))?;
    eo::write_eigenvalue_figure(&eigen_stem, &metrics)?;
    eo::keep_figure_eigenvalues(&mut metrics);
    let results = Results {
        quick,
        load_average: format!("{load_before} (before), {} (after)", load_average()),
        sweep: metrics,
        open3d_version,
        texel_pairs,
        open3d_pairs,
        corridor_pairs,
        graph,
    };
    // Step 5: figures, raw results and the Markdown.
    let figures = if quick {
        paths.quick_dir()
    } else {
        paths.figures()
    };
    std::fs::create_dir_all(&figures)
        .with_context(|| format!("cannot create {}", figures.display()))?;
    let stem = figures.join(if quick {
        "registration-pareto-quick"
    } else {
        "registration-pareto"
    });
    write_pareto(
        &stem,
        "Registration: accuracy against time per scan (one core), per setting",
        "registration time per scan, median (ms, CPU, one core)",
        "ATE RMSE (mm)",
        &pareto_series(&results),
    )?;
    let json = stem.with_extension("json");
    std::fs::write(&json, serde_json::to_string_pretty(&results)?)
        .with_context(|| format!("cannot write {}", json.display()))?;
    Ok(report::markdown(&results, &stem))
}

/// Scenes whose trajectory error says nothing about the settings (their motion is
/// along unobservable directions), left out of the plot.
const NOT_PLOTTED: [&str; 1] = ["tunnel"];

fn pareto_series(results: &Results) -> Vec<Series> {
    let mut series: Vec<Series> = Vec::new();
    for m in results
        .sweep
        .iter()
        .filter(|m| !NOT_PLOTTED.contains(&m.scene.as_str()))
    {
        let point = (m.time_median_ms, m.ate_rmse_mm, m.setting.clone());
        match series.iter_mut().find(|s| s.name == m.scene) {
            Some(s) => s.points.push(point),
            None => series.push(Series {
                name: m.scene.clone(),
                points: vec![point],
            }),
        }
    }
    series
}

/// The 1, 5 and 15 minute load averages, from `/proc/loadavg`.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|| "unknown".to_string())
}
