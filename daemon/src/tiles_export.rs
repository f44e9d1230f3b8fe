//! `texeld export CAPTURE --format 3dtiles --out DIR`: the registered model's
//! level-of-detail hierarchy written as an OGC 3D Tiles 1.1 tileset. Scans stream
//! into the hierarchy's field one at a time (with `/texel/pose` in the capture), so
//! memory follows the surface, not the capture's length.

use std::path::{Path, PathBuf};
use std::time::Instant;

use texel_lod::{GeoReference, LodConfig, LodModel, TileCompression, tileset_files};
use texel_register::RegistrationConfig;

use crate::export::ExportCommandError;
use crate::model_export::{Placement, PoseChoice, for_each_placed_by};
use crate::pages::FilePages;

/// What the export wrote and what it cost.
#[derive(Debug)]
pub struct TilesExportSummary {
    pub placement: Placement,
    pub tiles: usize,
    /// Levels from the finest to the top.
    pub levels: u8,
    pub triangles: usize,
    pub bytes: u64,
    /// Bytes of the fields of every level in memory at the end, and the most they
    /// held after any scan or the build.
    pub field_bytes: usize,
    pub peak_field_bytes: usize,
    /// Bytes of the fields' blocks in the page file at the end.
    pub field_paged_bytes: u64,
    pub fuse_s: f64,
    pub build_s: f64,
}

/// Parses `LAT,LON,HEIGHT` (degrees, degrees, metres above the WGS84 ellipsoid): the
/// world origin's place on the globe, world x east and y north there.
pub fn parse_georef(text: &str) -> Result<GeoReference, String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let [lat, lon, height] = parts.as_slice() else {
        return Err(format!("expected LAT,LON,HEIGHT, got {text:?}"));
    };
    let num = |name: &str, s: &str| {
        s.parse::<f64>()
            .map_err(|e| format!("{name} {s:?} is not a number: {e}"))
    };
    let geo = GeoReference {
        latitude_deg: num("latitude", lat)?,
        longitude_deg: num("longitude", lon)?,
        height_m: num("height", height)?,
        world_point_m: [0.0; 3],
    };
    geo.validate().map_err(|e| e.to_string())?;
    Ok(geo)
}

/// Reads a TOML file of level-of-detail overrides (keys of `LodConfig`; unknown keys
/// and bad values are errors naming the file).
pub fn load_lod_config(path: &Path) -> Result<LodConfig, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let config: LodConfig =
        toml::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    config
        .validate()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(config)
}

/// What the tileset is built with: the tree's knobs, where it lies on the globe, how
/// its tiles carry their geometry.
#[derive(Debug, Clone, Copy, Default)]
pub struct TilesetChoice {
    pub lod: LodConfig,
    pub geo: Option<GeoReference>,
    pub compression: TileCompression,
    /// The fields the tiles are cut from are held within this many bytes, the rest
    /// paged to an unlinked file in the system's temporary folder; `None` holds them
    /// all in memory.
    pub field_memory_budget_bytes: Option<usize>,
}

/// Builds the hierarchy of `capture`'s registered model and writes the tileset into
/// `out_dir` (created if missing). `tileset.json` is written last, through a
/// temporary name, so a failed export never leaves a tileset pointing at missing
/// tiles.
pub fn export_tiles(
    capture: &Path,
    out_dir: &Path,
    registration: &RegistrationConfig,
    tileset: &TilesetChoice,
    poses: PoseChoice,
) -> Result<TilesExportSummary, ExportCommandError> {
    let started = Instant::now();
    let mut model = LodModel::new(tileset.lod)?;
    if let Some(budget) = tileset.field_memory_budget_bytes {
        let dir = std::env::temp_dir();
        let pages = FilePages::create_in(&dir, "export-fields", texel_lod::fields::PAGE_BYTES)
            .map_err(|source| ExportCommandError::Io { path: dir, source })?;
        model.page_fields_to(Box::new(pages), budget);
    }
    let mut peak_field_bytes = 0;
    let placement = for_each_placed_by(capture, registration, poses, &mut |scan, pose| {
        model.add_scan(scan, pose);
        peak_field_bytes = peak_field_bytes.max(model.field_bytes());
    })?;
    let fuse_s = started.elapsed().as_secs_f64();
    let built = Instant::now();
    model.rebuild(usize::MAX);
    let field_bytes = model.field_bytes();
    let peak_field_bytes = peak_field_bytes.max(field_bytes);
    let field_paged_bytes = model.field_paging().bytes_out;
    let hierarchy = model.hierarchy()?;
    let files = tileset_files(&hierarchy, tileset.geo.as_ref(), tileset.compression)?;
    let build_s = built.elapsed().as_secs_f64();
    let io = |path: PathBuf| move |source| ExportCommandError::Io { path, source };
    std::fs::create_dir_all(out_dir).map_err(io(out_dir.to_path_buf()))?;
    let mut bytes = 0u64;
    let mut tileset = None;
    for file in files {
        bytes += file.bytes.len() as u64;
        if file.path == "tileset.json" {
            tileset = Some(file);
            continue;
        }
        let path = out_dir.join(&file.path);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(io(parent.to_path_buf()))?;
        }
        std::fs::write(&path, &file.bytes).map_err(io(path.clone()))?;
    }
    if let Some(file) = tileset {
        let temporary = out_dir.join("tileset.json.partial");
        std::fs::write(&temporary, &file.bytes).map_err(io(temporary.clone()))?;
        let path = out_dir.join("tileset.json");
        std::fs::rename(&temporary, &path).map_err(io(path.clone()))?;
    }
    Ok(TilesExportSummary {
        placement,
        tiles: hierarchy.nodes.len(),
        levels: hierarchy.top_lod + 1,
        triangles: hierarchy.triangle_count(),
        bytes,
        field_bytes,
        peak_field_bytes,
        field_paged_bytes,
        fuse_s,
        build_s,
    })
}
