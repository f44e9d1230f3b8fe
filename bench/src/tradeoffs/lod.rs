//! `texel-bench tradeoffs lod`: what the level-of-detail hierarchy costs and how
//! close it stays to the truth, per setting, on the street scene. A capture is
//! rendered and registered (cached), every registered scan is fused into a
//! `LodModel`, the hierarchy is rebuilt, and each setting reports: fusion time per
//! scan, rebuild time per tile, the tiles queued per second of a 30 Hz walk against
//! what one rebuild thread clears, tiles and triangles per level, bytes per tile as
//! 3D Tiles content, the fields' memory, and the distance of the finest and coarsest
//! tiles' vertices from the simulator's true surface. The default setting runs again
//! with its fields paged to a file beyond a small budget (as the daemon pages them):
//! its cost against the unpaged run, and its tree compared with the unpaged one's.
//! Writes the "Level of detail" section of `docs/tradeoffs.md`.

use std::fmt::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use nalgebra::{Point3, Vector3};
use texel::{Pose, TexelScan};
use texel_lod::{Hierarchy, LodConfig, LodModel, tileset_files};

use crate::tradeoffs::registration::data::{SequenceSpec, cached_capture};
use crate::tradeoffs::rendering::report::write_tradeoffs_section;

/// The street walk the level-of-detail reports measure on, and where they write.
#[derive(Debug, Clone, clap::Args)]
pub struct StreetArgs {
    /// Frames of the street walk (30 Hz).
    #[arg(long, default_value_t = 1800)]
    pub frames: usize,
    /// The repository root (scenes are read and the docs written under it).
    #[arg(long, default_value = ".")]
    pub repo: PathBuf,
    /// Where captures are kept between runs.
    #[arg(long, default_value = "target/tradeoffs-cache")]
    pub cache: PathBuf,
    /// Simulator seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Measure and print, but leave docs/tradeoffs.md alone.
    #[arg(long)]
    pub no_write: bool,
}

impl StreetArgs {
    /// The scene files' folder.
    pub fn scenes(&self) -> PathBuf {
        self.repo.join("configs").join("scenes")
    }

    /// The capture of the walk's first `frames` frames, rendered into the cache once.
    pub fn capture(&self, frames: usize) -> Result<PathBuf> {
        let spec = SequenceSpec {
            scene: "street",
            frames,
            seed: self.seed,
            orbit_period_frames: None,
        };
        cached_capture(&self.scenes(), &self.cache, &spec)
    }
}

#[derive(Debug, Clone, clap::Args)]
pub struct LodArgs {
    /// Fewer frames and settings, for a quick look (docs/ is left alone).
    #[arg(long)]
    pub quick: bool,
    #[command(flatten)]
    pub street: StreetArgs,
}

/// One setting's figures.
struct Row {
    label: String,
    scans: usize,
    fuse_ms_per_scan: f64,
    rebuild_ms_per_tile: f64,
    tiles_per_s_queued: f64,
    tiles: usize,
    levels: u8,
    leaf_triangles: usize,
    top_triangles: usize,
    bytes_mean: f64,
    bytes_max: usize,
    wire_bytes_mean: f64,
    /// The most the fields held in memory after any call.
    field_mib: f64,
    /// With the fields paged: the budget, and what paging did.
    paged: Option<(f64, texel_lod::PagingCounts)>,
    leaf_error: (f64, f64),
    top_error: (f64, f64),
}

fn settings(quick: bool) -> Vec<(String, LodConfig)> {
    let base = LodConfig::default();
    let with = |label: &str, leaf_voxel_m: f64, tile_triangle_budget: usize| {
        (
            label.to_string(),
            LodConfig {
                leaf_voxel_m,
                tile_triangle_budget,
                ..base
            },
        )
    };
    if quick {
        return vec![with("voxel 0.1 m, 16k", 0.1, 16_384)];
    }
    vec![
        with("voxel 0.05 m, 16k", 0.05, 16_384),
        with("voxel 0.1 m, 16k (default)", 0.1, 16_384),
        with("voxel 0.2 m, 16k", 0.2, 16_384),
        with("voxel 0.1 m, 4k", 0.1, 4_096),
        with("voxel 0.1 m, 64k", 0.1, 65_536),
    ]
}

pub fn run(args: &LodArgs) -> Result<()> {
    let frames = if args.quick {
        args.street.frames.min(300)
    } else {
        args.street.frames
    };
    let scenes = args.street.scenes();
    let capture = args.street.capture(frames)?;
    let scene = sims::Scene::load(&scenes.join("street.toml")).context("loading the street")?;
    // The true poses: what the hierarchy costs and keeps, apart from registration
    // (which is measured in its own section).
    let placed = truth_placed_scans(&capture)?;
    eprintln!("{} placed scans of {frames} frames", placed.len());
    let mut rows = Vec::new();
    let mut default_tree = None;
    let mut default_row = None;
    for (label, config) in settings(args.quick) {
        let (row, tree) = measure(&label, &config, &placed, &scene, None)?;
        if config == LodConfig::default() {
            default_tree = Some(tree);
            default_row = Some(rows.len());
        }
        println!(
            "{label}: fuse {:.2} ms/scan, rebuild {:.1} ms/tile, {:.1} tiles/s queued at 30 Hz, {} tiles in {} levels, leaf error median {:.3} p95 {:.3} m",
            row.fuse_ms_per_scan,
            row.rebuild_ms_per_tile,
            row.tiles_per_s_queued,
            row.tiles,
            row.levels,
            row.leaf_error.0,
            row.leaf_error.1
        );
        rows.push(row);
    }
    // The default again, its fields paged beyond a sixth of what they hold whole.
    let config = LodConfig::default();
    let whole_mib = default_row
        .and_then(|i| rows.get(i))
        .map_or(64.0, |r: &Row| r.field_mib);
    let budget_mib = (whole_mib / 6.0).ceil().max(1.0);
    let pages = texel_daemon::pages::FilePages::create_in(
        &std::env::temp_dir(),
        "bench-lod-fields",
        texel_lod::fields::PAGE_BYTES,
    )
    .context("creating the field page file")?;
    let label = format!("voxel 0.1 m, 16k, fields paged beyond {budget_mib:.0} MiB");
    let (row, tree) = measure(
        &label,
        &config,
        &placed,
        &scene,
        Some((Box::new(pages), budget_mib)),
    )?;
    let same = default_tree.as_ref().map(|t| *t == tree);
    if let Some(whole) = default_row.and_then(|i| rows.get(i)) {
        println!(
            "paged against whole: fuse {:.2}x, rebuild {:.2}x, peak fields {:.1} against {:.1} MiB, same tree: {same:?}",
            row.fuse_ms_per_scan / whole.fuse_ms_per_scan.max(1e-12),
            row.rebuild_ms_per_tile / whole.rebuild_ms_per_tile.max(1e-12),
            row.field_mib,
            whole.field_mib
        );
    }
    rows.push(row);
    let body = markdown(&rows, frames, same);
    println!("{body}");
    if args.street.no_write || args.quick {
        return Ok(());
    }
    write_tradeoffs_section(&args.street.repo, "lod", &body)
}

/// Every texel frame of the capture fused and placed by its `/truth/pose` (the
/// export's own reading).
pub(crate) fn truth_placed_scans(capture: &Path) -> Result<Vec<(Arc<TexelScan>, Pose)>> {
    let mut placed = Vec::new();
    texel_daemon::model_export::for_each_placed_by(
        capture,
        &texel_register::RegistrationConfig::default(),
        texel_daemon::model_export::PoseChoice::Truth,
        &mut |scan, pose| placed.push((Arc::clone(scan), *pose)),
    )
    .with_context(|| format!("reading {}", capture.display()))?;
    Ok(placed)
}

/// One setting's figures and its tree; with `pages`, the fields are paged to that
/// store beyond that many MiB.
fn measure(
    label: &str,
    config: &LodConfig,
    placed: &[(Arc<TexelScan>, Pose)],
    scene: &sims::Scene,
    pages: Option<(Box<dyn texel::paged::PageStore>, f64)>,
) -> Result<(Row, Hierarchy)> {
    let mut model = LodModel::new(*config)?;
    let mib = f64::from(1u32 << 20);
    let budget_mib = pages.as_ref().map(|(_, b)| *b);
    if let Some((store, budget_mib)) = pages {
        model.page_fields_to(store, (budget_mib * mib) as usize);
    }
    let mut peak_field_bytes = 0usize;
    // Fusion, and the tiles each second of a 30 Hz walk queues: the queue after
    // every 30 scans, rebuilt as it goes so each count is of new work.
    let mut fuse_s = 0.0;
    let mut rebuild_s = 0.0;
    let mut queued = 0usize;
    let mut rebuilt = 0usize;
    for (i, (scan, pose)) in placed.iter().enumerate() {
        let t = Instant::now();
        model.add_scan(scan, pose);
        fuse_s += t.elapsed().as_secs_f64();
        peak_field_bytes = peak_field_bytes.max(model.field_bytes());
        if (i + 1) % 30 == 0 || i + 1 == placed.len() {
            let pending = model.pending_tiles();
            let t = Instant::now();
            let done = model.rebuild(usize::MAX);
            rebuild_s += t.elapsed().as_secs_f64();
            peak_field_bytes = peak_field_bytes.max(model.field_bytes());
            debug_assert_eq!(pending, done);
            queued += done;
            rebuilt += done;
        }
    }
    let hierarchy = model.hierarchy()?;
    let files = tileset_files(&hierarchy, None, texel_lod::TileCompression::None)?;
    let glbs: Vec<usize> = files.iter().skip(1).map(|f| f.bytes.len()).collect();
    let wire: Vec<usize> = hierarchy
        .nodes
        .values()
        .filter(|n| !n.mesh.is_empty())
        .map(|n| texel_lod::encode_tile(n).len())
        .collect();
    let seconds = placed.len() as f64 / 30.0;
    let level_triangles = |lod: u8| -> usize {
        hierarchy
            .nodes
            .values()
            .filter(|n| n.id.lod == lod)
            .map(|n| n.mesh.triangle_count())
            .sum()
    };
    eprintln!("{label}: measuring distances to the truth");
    let row = Row {
        label: label.to_string(),
        scans: placed.len(),
        fuse_ms_per_scan: 1e3 * fuse_s / placed.len().max(1) as f64,
        rebuild_ms_per_tile: 1e3 * rebuild_s / rebuilt.max(1) as f64,
        tiles_per_s_queued: queued as f64 / seconds.max(1e-9),
        tiles: hierarchy.nodes.len(),
        levels: hierarchy.top_lod + 1,
        leaf_triangles: level_triangles(0),
        top_triangles: level_triangles(hierarchy.top_lod),
        bytes_mean: glbs.iter().sum::<usize>() as f64 / glbs.len().max(1) as f64,
        bytes_max: glbs.iter().copied().max().unwrap_or(0),
        wire_bytes_mean: wire.iter().sum::<usize>() as f64 / wire.len().max(1) as f64,
        field_mib: peak_field_bytes as f64 / mib,
        paged: budget_mib.map(|b| (b, model.field_paging())),
        leaf_error: distances(&hierarchy, 0, scene),
        top_error: distances(&hierarchy, hierarchy.top_lod, scene),
    };
    Ok((row, hierarchy))
}

/// Median and 95th percentile distance, metres, of a level's vertices from the true
/// surface: rays cast both ways along each vertex's normal (area-weighted over its
/// triangles) from half a metre out; the nearer hit counts. Vertices with no hit
/// within a metre (surface the walk never reached) are left out.
pub(crate) fn distances(h: &Hierarchy, lod: u8, scene: &sims::Scene) -> (f64, f64) {
    let mut d = Vec::new();
    for node in h.nodes.values().filter(|n| n.id.lod == lod) {
        let mesh = &node.mesh;
        let mut normals = vec![Vector3::<f64>::zeros(); mesh.vertex_count()];
        for t in &mesh.triangles {
            let p = t.map(|i| {
                let q = mesh.positions[i as usize];
                Vector3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2]))
            });
            let n = (p[1] - p[0]).cross(&(p[2] - p[0]));
            for &i in t {
                normals[i as usize] += n;
            }
        }
        // Every 7th vertex: the distribution, not every sample.
        for v in (0..mesh.vertex_count()).step_by(7) {
            let (Some(w), Some(n)) = (mesh.world(v), normals[v].try_normalize(1e-12)) else {
                continue;
            };
            let p = Point3::from(w);
            let nearest = [n, -n]
                .iter()
                .filter_map(|dir| {
                    let hit = scene.cast_ray(p - dir * 0.5, *dir)?;
                    (hit.distance_m < 1.0).then(|| (hit.distance_m - 0.5).abs())
                })
                .fold(f64::INFINITY, f64::min);
            if nearest.is_finite() {
                d.push(nearest);
            }
        }
    }
    if d.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    d.sort_by(f64::total_cmp);
    let at = |q: f64| d[((d.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.95))
}

fn markdown(rows: &[Row], frames: usize, paged_same_tree: Option<bool>) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "## Level of detail\n");
    let _ = writeln!(
        s,
        "`cargo run --release -p texel-bench -- tradeoffs lod` (street, the first {frames} frames of the walk at 30 Hz, placed by their true poses so that registration, measured in its own section, does not enter; {} scans). Each setting fuses every scan into a `texel_lod::LodModel` and rebuilds the tiles a 30 Hz walk queues each second. Error: distance of a level's vertices from the simulator's true surface along their normals (median / 95th percentile). Bytes: one tile as 3D Tiles content (binary glTF, uncompressed) and through `texel_lod::encode_tile` (16-bit positions, meshoptimizer's vertex and index codecs), the form a tile is to travel in. Fields MiB: the most the fields held in memory after any scan or rebuild. One core.\n",
        rows.first().map_or(0, |r| r.scans)
    );
    let _ = writeln!(
        s,
        "| setting | fuse ms/scan | rebuild ms/tile | tiles queued/s | rebuild load | tiles | levels | finest-level triangles | top-level triangles | glTF bytes/tile mean / max | encoded bytes/tile mean | fields MiB | finest error m | top error m |"
    );
    let _ = writeln!(
        s,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for r in rows {
        // The share of one core the rebuilds take at 30 Hz: above 1, the queue grows.
        let load = r.tiles_per_s_queued * r.rebuild_ms_per_tile / 1e3;
        let _ = writeln!(
            s,
            "| {} | {:.2} | {:.1} | {:.1} | {:.2} | {} | {} | {} | {} | {:.0} / {} | {:.0} | {:.0} | {:.3} / {:.3} | {:.3} / {:.3} |",
            r.label,
            r.fuse_ms_per_scan,
            r.rebuild_ms_per_tile,
            r.tiles_per_s_queued,
            load,
            r.tiles,
            r.levels,
            r.leaf_triangles,
            r.top_triangles,
            r.bytes_mean,
            r.bytes_max,
            r.wire_bytes_mean,
            r.field_mib,
            r.leaf_error.0,
            r.leaf_error.1,
            r.top_error.0,
            r.top_error.1
        );
    }
    if let Some((budget_mib, p)) = rows.iter().find_map(|r| r.paged) {
        let same = match paged_same_tree {
            Some(true) => "identical to the default's, tile for tile (compared in the run)",
            Some(false) => "NOT identical to the default's",
            None => "not compared (the default did not run)",
        };
        let _ = writeln!(
            s,
            "\nThe paged row holds the fields within {budget_mib:.0} MiB and pages the blocks used longest ago to an unlinked file (`model.lod.field_memory_budget_mb` in the daemon): {} MiB in the file at the end, {} block writes and {} reads of 12 KiB. Its tree is {same}.",
            p.bytes_out >> 20,
            p.writes,
            p.reads
        );
    }
    s
}
