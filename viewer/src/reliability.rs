//! Accumulated texture reliability (Killpack & Budge 2016, Sec. 3) on the CPU: normal
//! accuracy per vertex (from fusion's per-triangle accuracy), point-of-view
//! confidence, range confidence, and their product. `scan.wgsl` evaluates the same
//! formulas per fragment; `docs/rendering.md` gives the reasoning.

use glam::DVec3;
use texel::TexelScan;

/// Distances below this (metres) are treated as this, so ratios stay finite.
pub const MIN_DISTANCE_M: f64 = 1.0e-6;

/// Point-of-view confidence at surface point `p`: the cosine between the directions
/// from `p` to the acquisition centre of projection and to the virtual one, clamped
/// to [0, 1] (beyond 90 degrees the fragment is not used). 0 when either direction
/// is degenerate (a COP on the surface point).
pub fn pov_confidence(p: [f64; 3], acquisition_cop: [f64; 3], virtual_cop: [f64; 3]) -> f64 {
    let p = DVec3::from_array(p);
    let a = DVec3::from_array(acquisition_cop) - p;
    let v = DVec3::from_array(virtual_cop) - p;
    let (na, nv) = (a.length(), v.length());
    if na < MIN_DISTANCE_M || nv < MIN_DISTANCE_M {
        return 0.0;
    }
    (a.dot(v) / (na * nv)).clamp(0.0, 1.0)
}

/// Range confidence `min(1, d_virtual / d_acquisition)^gamma`: 1 while the virtual
/// camera is at least as far from the point as the texel camera was, falling as it
/// comes closer and the texture is magnified. `gamma` <= 0 or not finite counts as 1.
pub fn range_confidence(d_virtual_m: f64, d_acquisition_m: f64, gamma: f64) -> f64 {
    let gamma = if gamma.is_finite() && gamma > 0.0 {
        gamma
    } else {
        1.0
    };
    let ratio = d_virtual_m.max(0.0) / d_acquisition_m.max(MIN_DISTANCE_M);
    ratio.clamp(0.0, 1.0).powf(gamma)
}

/// Accumulated reliability: the product of the three measures, clamped to [0, 1].
pub fn reliability(normal_accuracy: f64, pov: f64, range: f64) -> f64 {
    let r = normal_accuracy * pov * range;
    if r.is_finite() {
        r.clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// Which triangles of a scan are drawn: neither degenerate nor (unless kept)
/// stretched.
pub fn triangle_drawn(scan: &TexelScan, t: usize, keep_stretched: bool) -> bool {
    scan.triangle_flags
        .get(t)
        .is_some_and(|f| !f.is_degenerate() && (keep_stretched || !f.is_stretched()))
}

/// Normal accuracy per vertex, to be interpolated across triangles (Sec. 1: "the
/// accuracy of a texture triangle can be interpolated"): the mean accuracy of the
/// usable triangles around the vertex; a vertex touched only by stretched triangles
/// takes their mean (it is drawn only when stretched triangles are kept); 0 for a
/// vertex of no triangle.
pub fn vertex_accuracy(scan: &TexelScan) -> Vec<f32> {
    let n = scan.vertices.len();
    let mut usable = vec![(0.0f64, 0u32); n];
    let mut stretched = vec![(0.0f64, 0u32); n];
    for (t, tri) in scan.triangles.iter().enumerate() {
        let Some(flags) = scan.triangle_flags.get(t) else {
            continue;
        };
        if flags.is_degenerate() {
            continue;
        }
        let acc = f64::from(scan.triangle_accuracy.get(t).copied().unwrap_or(0.0));
        let acc = if acc.is_finite() {
            acc.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let sums = if flags.is_stretched() {
            &mut stretched
        } else {
            &mut usable
        };
        for &v in tri {
            if let Some(s) = sums.get_mut(v as usize) {
                s.0 += acc;
                s.1 += 1;
            }
        }
    }
    usable
        .iter()
        .zip(&stretched)
        .map(|(&(su, nu), &(ss, ns))| {
            if nu > 0 {
                (su / f64::from(nu)) as f32
            } else if ns > 0 {
                (ss / f64::from(ns)) as f32
            } else {
                0.0
            }
        })
        .collect()
}

/// Range noise sigma of each vertex at its acquisition range (distance from the
/// acquisition COP), metres; and that range.
pub fn vertex_acquisition_range(scan: &TexelScan) -> Vec<f32> {
    let cop = DVec3::from_array(scan.cop_m);
    scan.vertices
        .iter()
        .map(|v| DVec3::from_array(v.map(f64::from)).distance(cop) as f32)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measures_are_one_at_the_acquisition_view_and_fall_off() {
        let p = [0.0, 0.0, 5.0];
        assert!((pov_confidence(p, [0.0; 3], [0.0; 3]) - 1.0).abs() < 1e-12);
        // 60 degrees apart: cos = 0.5.
        let side = [
            5.0 * 60f64.to_radians().sin(),
            0.0,
            5.0 - 5.0 * 60f64.to_radians().cos(),
        ];
        assert!((pov_confidence(p, [0.0; 3], side) - 0.5).abs() < 1e-12);
        // Behind (more than 90 degrees): 0.
        assert_eq!(pov_confidence(p, [0.0; 3], [0.0, 0.0, 10.0]), 0.0);
        assert_eq!(pov_confidence(p, p, [0.0; 3]), 0.0);
        assert_eq!(range_confidence(2.0, 4.0, 1.0), 0.5);
        assert_eq!(range_confidence(8.0, 4.0, 1.0), 1.0);
        assert_eq!(range_confidence(2.0, 0.0, 2.0), 1.0);
        assert_eq!(range_confidence(2.0, 4.0, 2.0), 0.25);
        assert_eq!(reliability(f64::NAN, 1.0, 1.0), 0.0);
    }
}
