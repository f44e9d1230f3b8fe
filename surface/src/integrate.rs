//! A registered texel scan as TSDF samples: each return placed in the world, weighted
//! by the normal accuracy of the surface around it and coloured by its EO pixel.

use nalgebra::Point3;
use texel::{Pose, TexelScan};

use crate::tsdf::{Sample, Tsdf};

/// The scan's returns as samples in the world. A vertex counts only where a usable
/// triangle (neither stretched nor degenerate) touches it: lone returns and the
/// edges of depth discontinuities are where range is least trustworthy. Its weight
/// is the best normal accuracy among those triangles (Killpack & Budge 2016 §3.1),
/// floored at 0.05 so grazing surfaces still close up where nothing better saw them.
pub fn scan_samples(scan: &TexelScan, world_from_scan: &Pose) -> Vec<Sample> {
    let mut accuracy = vec![0.0f32; scan.vertices.len()];
    for ((tri, acc), flags) in scan
        .triangles
        .iter()
        .zip(&scan.triangle_accuracy)
        .zip(&scan.triangle_flags)
    {
        if !flags.is_usable() {
            continue;
        }
        for &v in tri {
            if let Some(a) = accuracy.get_mut(v as usize) {
                *a = a.max(acc.clamp(0.05, 1.0));
            }
        }
    }
    let centre = world_from_scan * Point3::from(scan.cop_m);
    let centre_m = [centre.x, centre.y, centre.z];
    scan.vertices
        .iter()
        .zip(&accuracy)
        .enumerate()
        .filter(|(_, (_, a))| **a > 0.0)
        .map(|(i, (p, a))| {
            let world =
                world_from_scan * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            Sample {
                point_m: [world.x, world.y, world.z],
                centre_m,
                weight: *a,
                colour: scan.vertex_colour(i),
            }
        })
        .collect()
}

/// Fuses one registered scan into `tsdf`; returns the number of voxel updates.
pub fn integrate_scan(tsdf: &mut Tsdf, scan: &TexelScan, world_from_scan: &Pose) -> usize {
    tsdf.integrate(&scan_samples(scan, world_from_scan))
}

/// Takes one registered scan back out of `tsdf` (it must have been fused at this
/// pose); returns the number of voxel updates. A revised pose moves a scan: out at
/// the old pose, in at the new.
pub fn remove_scan(tsdf: &mut Tsdf, scan: &TexelScan, world_from_scan: &Pose) -> usize {
    tsdf.remove(&scan_samples(scan, world_from_scan))
}
