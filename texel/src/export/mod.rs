//! Export of texel scans to formats other tools open: PLY (points with colours, and
//! the usable triangles) for MeshLab and CloudCompare, glTF 2.0 (textured meshes) for
//! Blender and the like.
//!
//! Coordinates are each scan's own frame, or the world frame when the scans are given
//! with their `world_from_scan` poses. World coordinates stay exact: PLY stores them
//! as doubles, glTF keeps each mesh in its scan frame (f32 relative to the scan's own
//! origin) under a node whose transform carries the f64 pose.

mod gltf;
mod ply;

pub use gltf::{GltfTexture, glb_container, scan_glb, write_gltf};
pub use ply::write_ply;

use std::path::Path;

use thiserror::Error;

use crate::pose::Pose;
use crate::scan::TexelScan;

/// One scan to export, with its pose when exporting in world coordinates.
#[derive(Debug, Clone, Copy)]
pub struct ExportScan<'a> {
    pub scan: &'a TexelScan,
    /// `Some` places the scan in the world; `None` keeps its own frame.
    pub world_from_scan: Option<Pose>,
}

#[derive(Debug, Error)]
pub enum ExportError {
    #[error("cannot write {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("cannot encode the texture of scan {seq}: {message}")]
    Texture { seq: u32, message: String },
    #[error("nothing to export: {0}")]
    Empty(String),
    #[error("export of several scans needs every scan's world pose")]
    MixedFrames,
}

pub(crate) fn io_error(path: &Path) -> impl Fn(std::io::Error) -> ExportError + '_ {
    move |source| ExportError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// Triangles worth exporting: neither stretched nor degenerate.
pub(crate) fn usable_triangles(scan: &TexelScan) -> impl Iterator<Item = [u32; 3]> + '_ {
    scan.triangles
        .iter()
        .zip(&scan.triangle_flags)
        .filter(|(_, f)| f.is_usable())
        .map(|(t, _)| *t)
}

/// Several scans can only share a file in one frame: the world.
pub(crate) fn check_frames(scans: &[ExportScan<'_>]) -> Result<(), ExportError> {
    if scans.is_empty() {
        return Err(ExportError::Empty("no scans".into()));
    }
    if scans.len() > 1 && scans.iter().any(|s| s.world_from_scan.is_none()) {
        return Err(ExportError::MixedFrames);
    }
    Ok(())
}
