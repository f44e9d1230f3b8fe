//! Binary little-endian PLY: one vertex per lidar return with its texture colour
//! (grey where the EO camera did not see it) and the usable triangles as faces.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use nalgebra::Point3;

use super::{ExportError, ExportScan, check_frames, io_error, usable_triangles};

/// Colour of points the EO camera did not see.
const UNTEXTURED: [u8; 3] = [128, 128, 128];

/// Writes the scans to one PLY file: float coordinates in the scan's frame for a
/// single scan without a pose, double world coordinates otherwise.
pub fn write_ply(scans: &[ExportScan<'_>], path: &Path) -> Result<(), ExportError> {
    check_frames(scans)?;
    let world = scans[0].world_from_scan.is_some();
    let vertex_count: usize = scans.iter().map(|s| s.scan.vertex_count()).sum();
    let face_count: usize = scans.iter().map(|s| usable_triangles(s.scan).count()).sum();
    let io = io_error(path);
    let mut out = BufWriter::new(File::create(path).map_err(&io)?);
    let coordinate = if world { "double" } else { "float" };
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment texel scans, {} frame\n\
         element vertex {vertex_count}\nproperty {coordinate} x\nproperty {coordinate} y\n\
         property {coordinate} z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {face_count}\nproperty list uchar int vertex_indices\nend_header\n",
        if world { "world" } else { "scan (EO optical)" },
    )
    .map_err(&io)?;
    for s in scans {
        for (k, v) in s.scan.vertices.iter().enumerate() {
            let rgb = s.scan.vertex_colour(k).unwrap_or(UNTEXTURED);
            match s.world_from_scan {
                Some(pose) => {
                    let p = pose * Point3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
                    for c in [p.x, p.y, p.z] {
                        out.write_all(&c.to_le_bytes()).map_err(&io)?;
                    }
                }
                None => {
                    for c in v {
                        out.write_all(&c.to_le_bytes()).map_err(&io)?;
                    }
                }
            }
            out.write_all(&rgb).map_err(&io)?;
        }
    }
    let mut base = 0u32;
    for s in scans {
        for t in usable_triangles(s.scan) {
            out.write_all(&[3u8]).map_err(&io)?;
            for i in t {
                // Vertex counts are bounded by the lidar grid (at most 16384²).
                out.write_all(&((base + i) as i32).to_le_bytes())
                    .map_err(&io)?;
            }
        }
        base += s.scan.vertex_count() as u32;
    }
    out.flush().map_err(&io)
}
