//! The rendering trade-offs as a printed table, a Markdown section and a Pareto plot
//! (time per frame against RMSE; `crate::tradeoffs::plot` draws it).

use std::fmt::Write;
use std::path::Path;

use crate::tradeoffs::plot::{Series, write_pareto};
use anyhow::{Context, Result};

use super::{Row, SceneResult, TradeoffsArgs};
use texel_viewer::composite::Mode;

fn row_line(r: &Row) -> String {
    let c = &r.config;
    // VDTM and the point proxy have none of the compositing knobs.
    let scans = c.vdtm.is_none() && !c.points;
    format!(
        "| {} | {} | {} | {} | {} | {}x{} | {:.2} | {:.4} | {:.1} | {:.1} | {:.1} |",
        c.mode_name(),
        if c.mode == Mode::Painter || !scans {
            "-".to_string()
        } else {
            c.k.to_string()
        },
        if c.mode == Mode::Blended && scans {
            format!("{}", c.blend_threshold)
        } else {
            "-".into()
        },
        if c.mode == Mode::Painter || !scans {
            "-".to_string()
        } else {
            format!("{}", c.range_gamma)
        },
        if c.truth_poses { "truth" } else { "registered" },
        c.width,
        c.height,
        r.psnr_db,
        r.ssim,
        100.0 * r.coverage,
        100.0 * r.scored,
        r.frame_ms
    )
}

const HEADER: &str = "| mode | k | blend threshold | range gamma | poses | resolution | PSNR (dB) | SSIM | coverage (%) | scored (%) | ms/frame |\n|---|---|---|---|---|---|---|---|---|---|---|";

/// Prints one scene's table.
pub fn print(r: &SceneResult) {
    println!(
        "\n{}: {} scans registered (ATE {:.1} mm), {} held-out poses",
        r.scene, r.scans, r.registration_ate_mm, r.poses
    );
    println!("{HEADER}");
    for row in &r.rows {
        println!("{}", row_line(row));
    }
    if let Some((best, blended)) = gains(r) {
        println!(
            "{}: best {:+.2} dB, blended {:+.2} dB against painter (registered, 320x240)",
            r.scene, best, blended
        );
    }
    println!("{}", vdtm_text(r));
}

/// VDTM's preparation and the fly-through's flicker, as markdown.
fn vdtm_text(r: &SceneResult) -> String {
    let mut s = String::new();
    if let Some(v) = &r.vdtm {
        let _ = writeln!(
            s,
            "\nVDTM prepared the registered model in {:.1} s (merged surface and \
             preprocessing; {} views, {} polygons of which {} holes) and uploaded it in {:.2} s.\n",
            v.build_s, v.views, v.polygons, v.holes, v.upload_s
        );
    }
    if !r.flicker.is_empty() {
        let _ = writeln!(
            s,
            "Fly-through flicker (mean absolute change per pixel between consecutive \
             frames, grey levels, over pixels every mode covers; the truth changes by {:.2} \
             there):\n\n| mode | change | beyond the truth's |\n|---|---|---|",
            r.flicker.first().map_or(f64::NAN, |f| f.truth_change)
        );
        for f in &r.flicker {
            let _ = writeln!(s, "| {} | {:.2} | {:+.2} |", f.mode, f.change, f.flicker());
        }
    }
    s
}

/// PSNR of `best` and `blended` minus `painter` at the defaults (registered poses).
pub fn gains(r: &SceneResult) -> Option<(f64, f64)> {
    let base = |mode: Mode| {
        r.rows.iter().find(|row| {
            let c = &row.config;
            c.mode == mode
                && c.vdtm.is_none()
                && !c.points
                && !c.truth_poses
                && c.width == 320
                && c.k == 4
                && c.blend_threshold == 0.15
                && c.range_gamma == 1.0
        })
    };
    let p = base(Mode::Painter)?.psnr_db;
    Some((
        base(Mode::Best)?.psnr_db - p,
        base(Mode::Blended)?.psnr_db - p,
    ))
}

/// The Pareto plot: one series per scene, registered poses only.
pub fn plot(stem: &Path, results: &[SceneResult]) -> Result<()> {
    let series: Vec<Series> = results
        .iter()
        .map(|r| Series {
            name: r.scene.clone(),
            points: r
                .rows
                .iter()
                .filter(|row| !row.config.truth_poses)
                .map(|row| (row.frame_ms, row.mse.sqrt(), row.config.label()))
                .collect(),
        })
        .collect();
    write_pareto(
        stem,
        "Rendering: quality against time per frame (lavapipe)",
        "milliseconds per frame (render + read-back)",
        "RMSE against ground truth, grey levels (PSNR = 20 log10(255 / RMSE))",
        &series,
    )
    .map_err(Into::into)
}

/// Writes `body` as section `name` of the repository's `docs/tradeoffs.md`
/// ([`replace_or_append`]) and says so.
pub fn write_tradeoffs_section(repo: &Path, name: &str, body: &str) -> Result<()> {
    let doc = repo.join("docs").join("tradeoffs.md");
    let text =
        std::fs::read_to_string(&doc).with_context(|| format!("reading {}", doc.display()))?;
    let updated = replace_or_append(&text, name, body);
    std::fs::write(&doc, updated).with_context(|| format!("writing {}", doc.display()))?;
    println!("updated the {name} section of {}", doc.display());
    Ok(())
}

/// `text` with the section between `<!-- BEGIN name -->` and `<!-- END name -->`
/// replaced, or appended with its markers when it is not there yet.
pub fn replace_or_append(text: &str, name: &str, body: &str) -> String {
    match crate::tradeoffs::replace_section(text, name, body) {
        Ok(t) => t,
        Err(_) => format!(
            "{}\n<!-- BEGIN {name} -->\n{}\n<!-- END {name} -->\n",
            text.trim_end_matches('\n').to_string() + "\n",
            body.trim_matches('\n')
        ),
    }
}

/// The Markdown of the rendering section.
pub fn markdown(results: &[SceneResult], args: &TradeoffsArgs, adapter: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "## Rendering\n");
    let _ = writeln!(
        s,
        "Generated by `cargo run {}-p texel-bench -- tradeoffs rendering{}` (seed {}) on {adapter}, \
         on a shared 2-core machine: times are medians over the held-out poses of one run, \
         comparable with each other, not absolute.\n",
        // The profile this binary was built with (the GPU work runs in the driver
        // either way).
        if cfg!(debug_assertions) {
            ""
        } else {
            "--release "
        },
        if args.quick { " --quick" } else { "" },
        args.seed
    );
    let _ = writeln!(
        s,
        "Method. Each scene is rendered by the simulator into a capture with the scene's \
         default effects (mixed pixels, dropouts, range noise and quantisation, lens \
         distortion, vignetting, sensor noise), registered in-process with the daemon's \
         registration (defaults, global refinement on; `texeld register`), loaded like any \
         capture (fused, placed at `/texel/pose`) and rendered at held-out poses: a third \
         halfway between neighbouring acquisition poses, a third pulled back by a quarter \
         of the viewing distance and raised by an eighth, a third moved a third of the way \
         towards the scene (closer than any scan). Ground truth is the simulator's \
         effect-free view at the same pose and intrinsics (`sims::Scene::render_view`, \
         what `texel-sims view` renders). Scored pixels: those covered by every \
         configuration at that resolution (the renderer's background is set to a colour no \
         scene produces, so coverage is exact); PSNR over RGB per pose, then averaged; SSIM \
         on BT.601 luma with an 11x11 Gaussian window (sigma 1.5) whose weights are \
         restricted to scored pixels. `coverage` is the share of the image the \
         configuration covers, `scored` the share every configuration covers. Rows \
         marked `truth` place the same scans at the simulator's true poses (a reference \
         for what registration error costs). `vdtm` rows draw the merged surface fused \
         from the registered scans by view-dependent texture mapping (Debevec 1998, \
         `--mode vdtm`, its EO camera from the capture): as published, with the \
         resolution term (`+res`), with feathering at image borders (`+feather`, 24 px) \
         and with both. The `points` row draws the registered scans as the point proxy \
         of Lechelek et al. 2019 (`--mode points`: splatted depth map with front/back \
         classification and pull-push, each pixel coloured from the acquisition views \
         that see it, tested against each view's own depth map). The fly-through crosses four acquisition intervals from a third \
         of the way into the walk, at 320x240.\n"
    );
    for r in results {
        let _ = writeln!(
            s,
            "### {}\n\n{} frames, {} scans registered (position RMSE against truth {:.1} mm{}), \
             {} held-out poses.\n",
            r.scene,
            r.frames,
            r.scans,
            r.registration_ate_mm,
            if r.registration_s.is_finite() {
                format!(", registration took {:.0} s", r.registration_s)
            } else {
                String::new()
            },
            r.poses
        );
        let _ = writeln!(s, "{HEADER}");
        for row in &r.rows {
            let _ = writeln!(s, "{}", row_line(row));
        }
        if let Some((best, blended)) = gains(r) {
            let _ = writeln!(
                s,
                "\nAgainst `painter` (registered poses, 320x240, defaults): `best` {best:+.2} dB, \
                 `blended` {blended:+.2} dB.\n"
            );
        }
        s.push_str(&vdtm_text(r));
    }
    let _ = writeln!(
        s,
        "![rendering Pareto plot](tradeoffs/rendering-pareto.png)\n\n\
         ([SVG](tradeoffs/rendering-pareto.svg)) Each point is a configuration of the \
         tables above with registered poses; lower and further left is better; the line \
         joins each scene's Pareto front.\n"
    );
    s
}
