//! `texel-bench tradeoffs vdtm-prep`: what view-dependent texture mapping's
//! preprocessing (Debevec 1998 §5-7, `texel-vdtm`) costs on `lab` and `courtyard`,
//! and how it grows with the number of views: visibility, hole filling and view maps
//! timed apart, their memory, and how many polygons end seen by none, one, two or
//! three and more views. Writes the "vdtm-prep" section of `docs/tradeoffs.md`.

use std::fmt::Write;
use std::time::Instant;

use anyhow::Result;
use texel::camera::PinholeCamera;
use texel::capture::{TexelItem, open_texel_frames};
use texel_lod::merged_surface;
use texel_vdtm::{AcquisitionView, VdtmConfig, VdtmModel, visibility};

use crate::tradeoffs::lod::truth_placed_scans;
use crate::tradeoffs::rendering::report::write_tradeoffs_section;
use crate::tradeoffs::surface::{SCENES, SurfaceArgs};

/// The merged surface's voxel, metres (`tradeoffs surface`: 1 mm median, 12 to 14 mm
/// at the 95th percentile on these scenes).
const VOXEL_M: f64 = 0.05;

struct Row {
    scene: &'static str,
    views: usize,
    polygons_in: usize,
    polygons_out: usize,
    seen_by_views: [usize; 4],
    visibility_ms: f64,
    fill_ms: f64,
    maps_ms: f64,
    depth_map_mib: f64,
    view_map_mib: f64,
}

pub fn run(args: &SurfaceArgs) -> Result<()> {
    let mut rows = Vec::new();
    for (scene, frames) in SCENES {
        let capture = args.capture(scene, frames)?;
        let camera = eo_camera(&capture)?;
        let placed = truth_placed_scans(&capture)?;
        let mesh = merged_surface(placed.iter().map(|(s, p)| (s.as_ref(), p)), VOXEL_M)?;
        let strides: &[usize] = if args.quick { &[1] } else { &[4, 2, 1] };
        for &stride in strides {
            let views: Vec<AcquisitionView<'_>> = placed
                .iter()
                .enumerate()
                .step_by(stride)
                .map(|(i, (scan, pose))| AcquisitionView {
                    id: i as u32,
                    // The scan frame is the EO camera's optical frame.
                    world_from_eo: *pose,
                    camera: &camera,
                    image: Some(scan.texture.as_ref()),
                })
                .collect();
            let config = VdtmConfig::default();
            let t = Instant::now();
            let (visible, stats) = visibility(&mesh, &views, &config.visibility)?;
            let visibility_ms = 1e3 * t.elapsed().as_secs_f64();
            let t = Instant::now();
            let fill = VdtmModel::fill(&visible, &views, &config.hole_fill)?;
            let fill_ms = 1e3 * t.elapsed().as_secs_f64();
            let t = Instant::now();
            let model = VdtmModel::assemble(visible, stats, &fill, &views, &config)?;
            let maps_ms = 1e3 * t.elapsed().as_secs_f64();
            let mib = |bytes: usize| bytes as f64 / f64::from(1u32 << 20);
            let row = Row {
                scene,
                views: views.len(),
                polygons_in: stats.input_triangles,
                polygons_out: stats.output_triangles,
                seen_by_views: stats.seen_by_views,
                visibility_ms,
                fill_ms,
                maps_ms,
                depth_map_mib: mib(4 * stats.depth_map_pixels),
                view_map_mib: mib(model.stats.view_map_bytes),
            };
            println!(
                "{scene}, {} views: {} -> {} polygons, seen by 0/1/2/3+ {:?}, visibility {:.0} ms, hole filling {:.0} ms, view maps {:.0} ms, depth maps {:.1} MiB, view maps {:.1} MiB",
                row.views,
                row.polygons_in,
                row.polygons_out,
                row.seen_by_views,
                row.visibility_ms,
                row.fill_ms,
                row.maps_ms,
                row.depth_map_mib,
                row.view_map_mib
            );
            rows.push(row);
        }
    }
    let body = markdown(&rows, args);
    println!("{body}");
    if args.quick || args.no_write {
        return Ok(());
    }
    write_tradeoffs_section(&args.repo, "vdtm-prep", &body)
}

/// The EO camera model the capture's first texel frame was taken with.
fn eo_camera(capture: &std::path::Path) -> Result<PinholeCamera> {
    for item in open_texel_frames(capture)? {
        if let Ok(TexelItem::Pair { sensor, .. }) = item {
            return Ok(sensor.eo.clone());
        }
    }
    anyhow::bail!("{} holds no texel frame", capture.display())
}

fn markdown(rows: &[Row], args: &SurfaceArgs) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "## View-dependent texture mapping: preprocessing\n");
    let _ = writeln!(
        s,
        "`cargo run --release -p texel-bench -- tradeoffs vdtm-prep` (seed {}): each scene's walk placed by its true poses, fused into the merged surface at {VOXEL_M} m (the finest tiles joined, unsimplified), then `texel-vdtm`'s preprocessing at its defaults from every 4th, every 2nd and every EO view (the scans' own images and poses): visibility (§5: a depth map per view at half the image's resolution, partly seen polygons split to depth 3), hole filling (§6: colours sampled from the images, then the unseen polygons filled in rounds) and view maps (§7: 9 × 9 per polygon seen by two or more views), timed apart on one core of a shared 2-core machine. Memory: the depth maps held during visibility and the view maps kept.\n",
        args.seed
    );
    let _ = writeln!(
        s,
        "| scene | views | polygons in | polygons out | seen by 0 / 1 / 2 / 3+ | visibility ms | hole filling ms | view maps ms | ms per view (all) | depth maps MiB | view maps MiB |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let [a, b, c, d] = r.seen_by_views;
        let total = r.visibility_ms + r.fill_ms + r.maps_ms;
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {a} / {b} / {c} / {d} | {:.0} | {:.0} | {:.0} | {:.1} | {:.1} | {:.1} |",
            r.scene,
            r.views,
            r.polygons_in,
            r.polygons_out,
            r.visibility_ms,
            r.fill_ms,
            r.maps_ms,
            total / r.views.max(1) as f64,
            r.depth_map_mib,
            r.view_map_mib
        );
    }
    s
}
