//! `texel-bench tradeoffs surface`: the merged surface that view-dependent texture
//! mapping renders and the level of detail's finest tiles hold, on `lab` and
//! `courtyard`, per voxel size: fusion time and field memory per scan, the time to
//! cut the mesh, its triangles, and the distance of its vertices from the simulator's
//! true surface. Writes the "merged-surface" section of `docs/tradeoffs.md`.

use std::fmt::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use texel_lod::{LodModel, whole_surface_config};

use crate::tradeoffs::lod::{distances, truth_placed_scans};
use crate::tradeoffs::registration::data::{SequenceSpec, cached_capture};
use crate::tradeoffs::rendering::report::write_tradeoffs_section;

/// The arguments of the reports on `lab` and `courtyard`'s merged surface (this one
/// and `vdtm-prep`).
#[derive(Debug, Clone, clap::Args)]
pub struct SurfaceArgs {
    /// One voxel size (`surface`) or every view only (`vdtm-prep`), for a quick look
    /// (docs/ is left alone).
    #[arg(long)]
    pub quick: bool,
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

/// The scenes measured, with the frames of each (the whole of each scene's walk).
pub(crate) const SCENES: [(&str, usize); 2] = [("lab", 36), ("courtyard", 120)];

impl SurfaceArgs {
    /// The scene files' folder.
    pub(crate) fn scenes(&self) -> PathBuf {
        self.repo.join("configs").join("scenes")
    }

    /// The capture of a scene's walk, rendered into the cache once.
    pub(crate) fn capture(&self, scene: &'static str, frames: usize) -> Result<PathBuf> {
        let spec = SequenceSpec {
            scene,
            frames,
            seed: self.seed,
            orbit_period_frames: None,
        };
        cached_capture(&self.scenes(), &self.cache, &spec)
    }
}

/// One scene at one voxel size.
struct Row {
    scene: &'static str,
    voxel_m: f64,
    scans: usize,
    fuse_ms_per_scan: f64,
    mesh_ms: f64,
    triangles: usize,
    field_mib: f64,
    error_m: (f64, f64),
}

pub fn run(args: &SurfaceArgs) -> Result<()> {
    let voxels: &[f64] = if args.quick {
        &[0.05]
    } else {
        &[0.025, 0.05, 0.1]
    };
    let mut rows = Vec::new();
    for (scene_name, frames) in SCENES {
        let capture = args.capture(scene_name, frames)?;
        let scene = sims::Scene::load(&args.scenes().join(format!("{scene_name}.toml")))
            .with_context(|| format!("loading {scene_name}"))?;
        // The true poses: the surface's own error, apart from registration's.
        let placed = truth_placed_scans(&capture)?;
        for &voxel_m in voxels {
            let mut model = LodModel::new(whole_surface_config(voxel_m))?;
            let t = Instant::now();
            for (scan, pose) in &placed {
                model.add_scan(scan, pose);
            }
            let fuse_s = t.elapsed().as_secs_f64();
            let t = Instant::now();
            model.rebuild(usize::MAX);
            let hierarchy = model.hierarchy()?;
            let mesh_s = t.elapsed().as_secs_f64();
            let triangles = hierarchy
                .nodes
                .values()
                .filter(|n| n.id.lod == 0)
                .map(|n| n.mesh.triangle_count())
                .sum();
            let row = Row {
                scene: scene_name,
                voxel_m,
                scans: placed.len(),
                fuse_ms_per_scan: 1e3 * fuse_s / placed.len().max(1) as f64,
                mesh_ms: 1e3 * mesh_s,
                triangles,
                field_mib: model.field_bytes() as f64 / f64::from(1u32 << 20),
                error_m: distances(&hierarchy, 0, &scene),
            };
            println!(
                "{scene_name}, voxel {voxel_m} m: {} scans, fuse {:.2} ms/scan, mesh {:.0} ms, {} triangles, fields {:.1} MiB, error median {:.4} p95 {:.4} m",
                row.scans,
                row.fuse_ms_per_scan,
                row.mesh_ms,
                row.triangles,
                row.field_mib,
                row.error_m.0,
                row.error_m.1
            );
            rows.push(row);
        }
    }
    let body = markdown(&rows, args);
    println!("{body}");
    if args.quick || args.no_write {
        return Ok(());
    }
    write_tradeoffs_section(&args.repo, "merged-surface", &body)
}

fn markdown(rows: &[Row], args: &SurfaceArgs) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "## The merged surface\n");
    let _ = writeln!(
        s,
        "`cargo run --release -p texel-bench -- tradeoffs surface` (seed {}): every frame of each scene's walk, placed by its true pose (registration is measured in its own section), fused into the signed distance field of `texel-surface` through `texel_lod::LodModel` at each voxel size, the finest level's mesh cut whole (no simplification, no atlas): the surface view-dependent texture mapping renders. Fuse: time per scan; mesh: time to cut the whole surface once; fields: memory of the distance fields after the last scan. Error: distance of the mesh's vertices from the simulator's true surface along their normals (median / 95th percentile; vertices with no true surface within a metre left out). One core of a shared 2-core machine.\n",
        args.seed
    );
    let _ = writeln!(
        s,
        "| scene | voxel m | scans | fuse ms/scan | mesh ms | triangles | fields MiB | fields KiB/scan | error median mm | error p95 mm |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.2} | {:.0} | {} | {:.1} | {:.0} | {:.1} | {:.1} |",
            r.scene,
            r.voxel_m,
            r.scans,
            r.fuse_ms_per_scan,
            r.mesh_ms,
            r.triangles,
            r.field_mib,
            1024.0 * r.field_mib / r.scans.max(1) as f64,
            1e3 * r.error_m.0,
            1e3 * r.error_m.1
        );
    }
    s
}
