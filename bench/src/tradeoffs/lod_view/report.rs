//! The `lod-view` section's Markdown: a method paragraph with the command, then the
//! tables of frame time and memory, quality and popping.

use std::fmt::Write;

use texel_viewer::residency::DEFAULT_BUDGET_MB;
use texel_viewer::tiles::measure::PopMeasure;

use super::render::{HEIGHT, WIDTH};
use super::{
    FLY_FRAMES, Figures, HOW, LodViewArgs, PoseQuality, TILE_BUDGET, mean_quality, mib, ratio,
};

pub(super) fn markdown(f: &Figures, args: &LodViewArgs) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "## Level of detail in the viewer\n");
    let frames_arg = if f.frames == 1800 {
        String::new()
    } else {
        format!(" --frames {}", f.frames)
    };
    let seed_arg = if args.street.seed == 1 {
        String::new()
    } else {
        format!(" --seed {}", args.street.seed)
    };
    let v = &f.views;
    let _ = writeln!(
        s,
        "`cargo run --release -p texel-bench -- tradeoffs lod-view{frames_arg}{seed_arg}` on {} (software Vulkan on the shared 2-core machine: absolute times are slow, compare ratios within the table). Street, the first {} frames of the walk at 30 Hz ({} scans, x {:.0} to {:.0} m), placed by their true poses and fused into the default tree ({} tiles in {} levels, built in {:.1} s; {:.1} MiB on the GPU were every tile resident, against {:.1} MiB for every scan). The viewer draws at {WIDTH}x{HEIGHT} three ways: LOD, the tiles (`TileRenderer` over a `MemorySource`, default selection, {} MiB budget, cache empty at each view and filled until the selection wants nothing) with, below the finest tiles the view still finds too coarse, their scans (at most 8 per tile chosen to cover the tile's surface points in view and 64 more for the points where earlier frames still showed the tile, held by the residency planner restricted to them, drawn `blended` beneath the tiles, which give way on their surface); the tiles alone; or the scans only (the residency planner choosing the scans the view needs within the viewer's default {DEFAULT_BUDGET_MB} MiB, drawn `blended`, k 4). Close view: eye 1.7 m up at the walk's middle frame, looking 40 degrees off the street's axis at the facade {:.1} m away. Overview: from ({:.0}, {:.0}, {:.0}) m looking down at the walk's middle, the whole walked street in view. Frame time: median wall time of one frame rendered into an image and read back (the GPU waited for), after two warm-up frames. GPU bytes: the tiles or scans resident (meshes and textures); the scan renderer's size-dependent targets (k-buffer, depth) are listed apart.\n",
        f.adapter,
        f.frames,
        f.scans,
        v.walk_x.0,
        v.walk_x.1,
        f.tiles,
        f.levels,
        f.build_s,
        mib(f.tile_bytes_all),
        mib(f.scan_bytes_all),
        TILE_BUDGET >> 20,
        v.close_hit_m,
        v.overview_eye.x,
        v.overview_eye.y,
        v.overview_eye.z,
    );
    let _ = writeln!(
        s,
        "| view | drawn with | frame ms | GPU MiB (data) | targets MiB | resident | drawn | triangles drawn | notes |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
    for (k, name) in ["close", "overview"].iter().enumerate() {
        for (j, how) in HOW.iter().enumerate() {
            let x = &f.view[k][j];
            let notes = if j == 0 {
                format!(
                    "tiles and scans; settled after {} updates{}; {} finest tiles show {} scans, {} left out by the budget",
                    x.needed,
                    if x.complete { "" } else { " (incomplete)" },
                    x.tiles_with_scans,
                    x.scans_drawn,
                    x.left_out
                )
            } else if j == 1 {
                format!(
                    "tiles; settled after {} updates{}",
                    x.needed,
                    if x.complete { "" } else { " (did not settle)" }
                )
            } else {
                format!(
                    "scans; {} needed, {} left out by the budget; triangles before the stretched-triangle filter",
                    x.needed, x.left_out
                )
            };
            let _ = writeln!(
                s,
                "| {name} | {how} | {:.1} | {:.1} | {:.1} | {} | {} | {} | {notes} |",
                x.frame_ms,
                mib(x.data_bytes),
                mib(x.target_bytes),
                x.resident,
                x.drawn,
                x.triangles
            );
        }
    }
    let _ = writeln!(s);
    let _ = writeln!(
        s,
        "| ratio overview / close | frame time | GPU bytes (data) |"
    );
    let _ = writeln!(s, "|---|---|---|");
    for (j, how) in HOW.iter().enumerate() {
        let _ = writeln!(
            s,
            "| {how} | {:.2} | {:.2} |",
            ratio(f.view[1][j].frame_ms, f.view[0][j].frame_ms),
            ratio(
                f.view[1][j].data_bytes as f64,
                f.view[0][j].data_bytes as f64
            )
        );
    }
    let _ = writeln!(
        s,
        "\nQuality: PSNR against the simulator's own render (`sims::Scene::render_view`, no sensor effects) at held-out poses; near: halfway between neighbouring frames of the walk (the rendering section's `between` poses); far: from the same stretch of the walk raised 8 m and pulled back 12 m along it, looking at what the frame looked at 8 m out. Scored over the pixels where the truth has geometry (a ray from the pixel hits the scene) and all three renders drew; the tiles settled with no fade. `drawn` is the share of the truth's geometry pixels each render covers.\n"
    );
    let _ = writeln!(
        s,
        "| poses | n | PSNR LOD dB | PSNR tiles alone dB | PSNR scans only dB | LOD - scans dB | tiles alone - scans dB | finest tiles showing scans, mean | drawn LOD / tiles / scans % | scored % | scans left out by the budget, max |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|");
    for kind in ["near", "far"] {
        let of: Vec<&PoseQuality> = f.quality.iter().filter(|q| q.kind == kind).collect();
        let n = of.len().max(1) as f64;
        let m = mean_quality(&f.quality, kind);
        let _ = writeln!(
            s,
            "| {kind} | {} | {:.2} | {:.2} | {:.2} | {:+.2} | {:+.2} | {:.1} | {:.1} / {:.1} / {:.1} | {:.1} | {} |",
            m.poses,
            m.hybrid_db,
            m.lod_db,
            m.scans_db,
            m.hybrid_minus_scans_db,
            m.lod_minus_scans_db,
            of.iter().map(|q| q.tiles_with_scans as f64).sum::<f64>() / n,
            100.0 * of.iter().map(|q| q.hybrid_cover).sum::<f64>() / n,
            100.0 * of.iter().map(|q| q.lod_cover).sum::<f64>() / n,
            100.0 * of.iter().map(|q| q.scans_cover).sum::<f64>() / n,
            100.0 * of.iter().map(|q| q.scored).sum::<f64>() / n,
            of.iter().map(|q| q.left_out).max().unwrap_or(0)
        );
    }
    let hybrid = texel_viewer::tiles::hybrid::HybridSettings::default();
    let (feedback_rounds, stride) = (
        hybrid.feedback_rounds_to_read_every_pixel(),
        hybrid.feedback_stride_px,
    );
    let _ = writeln!(
        s,
        "\nWhat the scans below the finest tiles cost and buy, per count of scans a finest tile may show (8 by default) and of those its coverage feedback may add (64 by default: after the fade, each frame reads back where the tiles still showed and asks for scans holding those points; `viewer/src/tiles/coverage.rs`; the view is drawn {feedback_rounds} frames more before it is timed or scored, each reading a different pixel of every {stride} x {stride} block, so every pixel is read once): the close view's frame time, scans drawn and GPU bytes (tiles and scans, as above), and the mean PSNR over the held-out poses of each kind, with its difference from the scans only on the same pixels.\n"
    );
    let _ = writeln!(
        s,
        "| scans per finest tile | more from feedback | close: frame ms | close: scans drawn | close: GPU MiB (data) | near: PSNR dB | near: LOD - scans dB | near: scans drawn, mean | far: PSNR dB | far: LOD - scans dB |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
    for (k, close) in &f.close_sweep {
        let of = |kind: &str| -> (f64, f64, f64) {
            let rows: Vec<(f64, f64, usize)> = f
                .quality
                .iter()
                .filter(|q| q.kind == kind)
                .filter_map(|q| {
                    let (_, db, drawn) = q.swept_db.iter().find(|(kk, _, _)| kk == k)?;
                    (db.is_finite() && q.scans_db.is_finite()).then_some((
                        *db,
                        db - q.scans_db,
                        *drawn,
                    ))
                })
                .collect();
            let n = rows.len();
            if n == 0 {
                return (f64::NAN, f64::NAN, f64::NAN);
            }
            let n = n as f64;
            (
                rows.iter().map(|r| r.0).sum::<f64>() / n,
                rows.iter().map(|r| r.1).sum::<f64>() / n,
                rows.iter().map(|r| r.2 as f64).sum::<f64>() / n,
            )
        };
        let (near_db, near_d, near_drawn) = of("near");
        let (far_db, far_d, _) = of("far");
        let _ = writeln!(
            s,
            "| {} | {} | {:.1} | {} | {:.1} | {near_db:.2} | {near_d:+.2} | {near_drawn:.1} | {far_db:.2} | {far_d:+.2} |",
            k.0,
            k.1,
            close.frame_ms,
            close.scans_drawn,
            mib(close.data_bytes)
        );
    }
    let p = &f.pop;
    let _ = writeln!(
        s,
        "\nPopping: a {FLY_FRAMES}-frame fly-through (30 Hz) from the close view to the overview, the distance growing geometrically, every tile resident from the start (with the scans below the finest tiles: the scans each frame wants made resident before it is drawn, as the viewer holds them) (`viewer/tests/tiles_flythrough.rs`'s method, `texel_viewer::tiles::measure`). Change: mean absolute RGB difference between consecutive frames, 8-bit steps; switch frames: the selection changed or a cross-fade was under way (with scans below: also the finest tiles showing scans or the resident scans changed). The scans-only and finest-tiles-only fly-throughs are measured at the LOD runs' switch frames (camera motion without level of detail); `excess` is the largest amount by which a LOD frame's change exceeds the reference's at the same switch frame. Held still (tiles alone): each frame's image against the previous frame's tiles drawn from this frame's camera (the switch alone).\n"
    );
    let _ = writeln!(
        s,
        "| fly-through | switch frames | largest change at a switch | largest change, any frame | mean change | excess over scans only | excess over finest tiles |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|");
    let row = |s: &mut String, label: &str, m: &PopMeasure, e: Option<(f64, f64)>| {
        let fmt = |v: f64| {
            if v.is_finite() {
                format!("{v:.3}")
            } else {
                "-".to_string()
            }
        };
        let (a, b) = e.map_or(("-".to_string(), "-".to_string()), |(a, b)| {
            (fmt(a), fmt(b))
        });
        let _ = writeln!(
            s,
            "| {label} | {} | {:.3} | {:.3} | {:.3} | {a} | {b} |",
            m.switch_frames, m.max_switch_change, m.max_change, m.mean_change
        );
    };
    row(
        &mut s,
        &format!(
            "LOD (scans below the finest tiles), fade 0.25 s; at most {} scans drawn",
            p.hybrid_scans_max
        ),
        &p.hybrid,
        Some((p.excess_hybrid_scans, f64::NAN)),
    );
    row(
        &mut s,
        "scans only (at the LOD run's switch frames)",
        &p.scans_at_hybrid,
        None,
    );
    row(
        &mut s,
        "tiles alone, fade 0.25 s",
        &p.fade,
        Some((p.excess_fade_scans, p.excess_fade_finest)),
    );
    row(
        &mut s,
        "tiles alone, no fade",
        &p.nofade,
        Some((p.excess_nofade_scans, p.excess_nofade_finest)),
    );
    row(
        &mut s,
        "scans only (at the fade run's switch frames)",
        &p.scans_at_fade,
        None,
    );
    row(
        &mut s,
        "scans only (at the no-fade run's switch frames)",
        &p.scans_at_nofade,
        None,
    );
    row(
        &mut s,
        "finest tiles only (at the no-fade run's switch frames)",
        &p.finest_at_nofade,
        None,
    );
    let _ = writeln!(
        s,
        "\n| held still | frames | frames changed | largest change | mean change |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|");
    for (label, m) in [("fade 0.25 s", &p.still_fade), ("no fade", &p.still_nofade)] {
        let _ = writeln!(
            s,
            "| {label} | {} | {} | {:.3} | {:.3} |",
            m.frames, m.changed_frames, m.max_change, m.mean_change
        );
    }
    let _ = writeln!(
        s,
        "\nThe scans-only fly-through changed its resident scans at {} frames (largest change there {:.3}); at most {} scans the view needed were left out by the budget.\n",
        p.scans_residency_frames, p.scans_residency_max, p.scans_left_out_max
    );
    let times: Vec<String> = f
        .timings
        .iter()
        .map(|(what, t)| format!("{what} {t:.0} s"))
        .collect();
    let _ = writeln!(s, "Run time: {}.", times.join(", "));
    s
}
