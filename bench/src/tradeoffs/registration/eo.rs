//! Where the geometry is blind: the photometric term's share of the registration
//! section. The smallest eigenvalue of each corridor alignment's information with
//! the geometry alone and with the EO term (a figure), and Texel with and without
//! the EO term against Open3D's point-to-plane and colored ICP on pairs of
//! `corridor` scans.

use std::path::Path;

use anyhow::{Context, Result};
use texel_plots::{Line, write_lines};
use texel_register::{AlignConfig, PhotometricMode};

use super::data::ScanPair;
use super::open3d::{self, Open3dSettings, PairOutcome};
use super::sweep::RunMetrics;

/// The scene and setting the eigenvalue figure is drawn for.
pub const FIGURE_SCENE: &str = "corridor";
pub const FIGURE_SETTING: &str = "defaults";

/// Keeps the per-frame eigenvalues of the figure's run only (the JSON stays small).
pub fn keep_figure_eigenvalues(sweep: &mut [RunMetrics]) {
    for m in sweep {
        if !(m.scene == FIGURE_SCENE && m.setting == FIGURE_SETTING) {
            m.min_eigenvalues.clear();
        }
    }
}

/// Writes the figure: log10 of the smallest eigenvalue per frame, geometry alone and
/// with the EO term, on the corridor walk.
pub fn write_eigenvalue_figure(stem: &Path, sweep: &[RunMetrics]) -> Result<()> {
    let Some(run) = sweep
        .iter()
        .find(|m| m.scene == FIGURE_SCENE && m.setting == FIGURE_SETTING)
    else {
        return Ok(());
    };
    // Guard: log10 of at least 1 (an eigenvalue below one is no information worth
    // a decade of the axis).
    let log = |x: f64| x.max(1.0).log10();
    let line = |name: &str, k: usize| Line {
        name: name.to_string(),
        points: run
            .min_eigenvalues
            .iter()
            .enumerate()
            .map(|(f, e)| ((f + 1) as f64, log(e[k])))
            .collect(),
    };
    write_lines(
        stem,
        "Corridor walk: smallest eigenvalue of each alignment's information",
        "frame",
        "log10 smallest eigenvalue (scaled, 1/m²)",
        &[line("geometry alone", 0), line("with the EO term", 1)],
    )
    .with_context(|| format!("cannot write {}", stem.display()))
}

/// Texel (defaults, and with the photometric term off) and Open3D (point-to-plane,
/// colored ICP) on the same corridor pairs.
pub fn corridor_pairs(
    pairs: &[ScanPair],
    python: &Path,
    script: &Path,
    dir: &Path,
    repeats: u32,
) -> Result<(String, Vec<PairOutcome>)> {
    let defaults = AlignConfig::default();
    let mut off = defaults.clone();
    off.photometric.mode = PhotometricMode::Off;
    let mut out = open3d::run_texel(pairs, "defaults", &defaults, repeats);
    out.extend(open3d::run_texel(pairs, "photometric off", &off, repeats));
    let mut version = String::new();
    for colored in [false, true] {
        let (v, outcomes) = open3d::run_open3d(
            python,
            script,
            &dir.join(if colored { "colored" } else { "point-to-plane" }),
            pairs,
            &Open3dSettings {
                max_correspondence_distance_m: defaults.max_correspondence_distance_m,
                max_iterations: 30,
                repeats,
                colored,
            },
        )?;
        version = v;
        out.extend(outcomes);
    }
    Ok((version, out))
}

/// The settings the EO table compares, in order.
const TABLE_SETTINGS: [&str; 3] = ["photometric off", "defaults", "photometric full"];

/// The Markdown of the EO subsection; `figure` is the eigenvalue figure's file stem.
pub fn markdown(sweep: &[RunMetrics], corridor_pairs: &[PairOutcome], figure: &str) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(s, "### Where the geometry is blind: the EO term\n");
    let _ = writeln!(
        s,
        "`corridor` (28.7 m out and back through a textured corridor with two U-turns, \
         glossy floor, swinging and flickering lights), `plane` (a walk over a textured \
         floor), `tunnel` (weak, low-contrast texture), and the two scenes where the \
         geometry suffices, `lab-walk` and `courtyard`. `photometric off` is geometry \
         alone; `defaults` admit the photometric term in the directions the geometry \
         leaves weak (the selective mode); `photometric full` adds it in every \
         direction. \"Named\" counts the registered frames whose result names a \
         direction neither sensor fixed (or fixed ambiguously).\n"
    );
    let _ = writeln!(
        s,
        "| scene | setting | ATE RMSE (mm) | end drift (% of path) | RPE (deg) | RPE (mm) | time median (ms) | frames with a direction named |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|");
    for scene in ["corridor", "plane", "tunnel", "lab-walk", "courtyard"] {
        for setting in TABLE_SETTINGS {
            let Some(m) = sweep
                .iter()
                .find(|m| m.scene == scene && m.setting == setting)
            else {
                continue;
            };
            let _ = writeln!(
                s,
                "| {scene} | {setting} | {:.1} | {:.2} | {:.4} | {:.2} | {:.2} | {}/{} |",
                m.ate_rmse_mm,
                m.drift_percent,
                m.rpe_deg,
                m.rpe_mm,
                m.time_median_ms,
                m.degenerate_frames,
                m.registered.saturating_sub(1)
            );
        }
    }
    let _ = writeln!(
        s,
        "\n![Smallest eigenvalue per frame]({figure}.svg)\n\nThe smallest eigenvalue of \
         each corridor alignment's information (scaled coordinates, the default \
         settings), geometry alone and with the EO term where it was admitted: the \
         axis the walls leave free is filled by the image ([PNG]({figure}.png)).\n"
    );
    let _ = writeln!(
        s,
        "Pairs of `corridor` scans 3 degrees and 5 cm apart (seeded random axes, so \
         partly along the free axis), from the identity: Texel's `align_pair` with and \
         without the EO term, Open3D's point-to-plane ICP and its colored ICP (Park, \
         Zhou & Koltun 2017, each point with its texel colour, normals on both clouds), \
         at most 30 iterations, 10 cm correspondence distance. Errors median (max) \
         over pairs, times median CPU time.\n"
    );
    let _ = writeln!(
        s,
        "| method | pairs | rotation error (deg) | translation error (mm) | time (ms): normals + alignment |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|");
    let mut methods: Vec<&str> = Vec::new();
    for p in corridor_pairs {
        if !methods.contains(&p.method.as_str()) {
            methods.push(&p.method);
        }
    }
    for method in methods {
        let rows: Vec<&PairOutcome> = corridor_pairs
            .iter()
            .filter(|p| p.method == method)
            .collect();
        let median = |f: &dyn Fn(&PairOutcome) -> f64| {
            let v: Vec<f64> = rows.iter().map(|p| f(p)).collect();
            texel_register::clock::quantile(&v, 0.5)
        };
        let max = |f: &dyn Fn(&PairOutcome) -> f64| rows.iter().map(|p| f(p)).fold(0.0, f64::max);
        let label = if method.starts_with("open3d") {
            method.replacen("open3d", "Open3D", 1)
        } else {
            format!("Texel, {method}")
        };
        let _ = writeln!(
            s,
            "| {label} | {} | {:.4} ({:.4}) | {:.2} ({:.2}) | {:.2} + {:.2} |",
            rows.len(),
            median(&|p| p.rotation_error_deg),
            max(&|p| p.rotation_error_deg),
            median(&|p| p.translation_error_mm),
            max(&|p| p.translation_error_mm),
            median(&|p| p.normals_ms),
            median(&|p| p.align_ms),
        );
    }
    s
}
