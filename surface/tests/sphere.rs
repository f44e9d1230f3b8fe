//! The merged surface against an analytic sphere seen from around it: extracted
//! vertices lie on the true sphere within a fraction of a voxel, triangles face
//! outwards, regions that tile the plane partition the surface and meet exactly,
//! simplification keeps within its error bound, all 5,000 km from the origin.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![allow(clippy::needless_range_loop)] // x, y and z side by side read clearer indexed

use proptest::prelude::*;
use texel_surface::{Sample, SurfaceMesh, Tsdf, TsdfConfig, VoxelRegion, extract, simplify};

const FAR: [f64; 3] = [5.0e6, 4.2e6, 120.0];

/// Rays from six cameras around a sphere, cut where they hit it.
fn sphere_samples(centre: [f64; 3], radius: f64, noise_m: f64) -> Vec<Sample> {
    let mut samples = Vec::new();
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut noise = move || {
        // xorshift: a fixed, portable sequence
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * noise_m
    };
    let dirs = [
        [1.0, 0.0, 0.0],
        [-1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.0, 0.0, 1.0],
        [0.0, 0.0, -1.0],
    ];
    for d in dirs {
        let eye = [0, 1, 2].map(|k| centre[k] + 4.0 * radius * d[k]);
        // Two axes across the view direction.
        let a = if d[0] == 0.0 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let b = [
            d[1] * a[2] - d[2] * a[1],
            d[2] * a[0] - d[0] * a[2],
            d[0] * a[1] - d[1] * a[0],
        ];
        let n = 120;
        for i in 0..n {
            for j in 0..n {
                let s = (f64::from(i) / f64::from(n - 1) - 0.5) * 2.2 * radius;
                let t = (f64::from(j) / f64::from(n - 1) - 0.5) * 2.2 * radius;
                // Parallel rays (an orthographic camera) keep the geometry simple.
                let origin = [0, 1, 2].map(|k| eye[k] + s * a[k] + t * b[k]);
                let r2 = s * s + t * t;
                if r2 >= radius * radius {
                    continue;
                }
                let depth = 4.0 * radius - (radius * radius - r2).sqrt() + noise();
                let point = [0, 1, 2].map(|k| origin[k] - depth * d[k]);
                let normal_cos = ((radius * radius - r2).sqrt() / radius) as f32;
                samples.push(Sample {
                    point_m: point,
                    centre_m: origin,
                    weight: normal_cos.max(0.05),
                    colour: Some([200, 80, 40]),
                });
            }
        }
    }
    samples
}

fn fused(centre: [f64; 3], radius: f64, voxel_m: f64, noise_m: f64) -> Tsdf {
    let mut tsdf = Tsdf::new(TsdfConfig {
        voxel_m,
        ..TsdfConfig::default()
    })
    .unwrap();
    tsdf.integrate(&sphere_samples(centre, radius, noise_m));
    tsdf
}

fn whole(tsdf: &Tsdf) -> VoxelRegion {
    let (lo, hi) = tsdf.bounds().unwrap();
    VoxelRegion {
        lo: [lo[0], lo[1]],
        hi: [hi[0] + 1, hi[1] + 1],
    }
}

/// Largest distance of a vertex from the sphere's surface, and the share of
/// triangles whose normal points away from the centre.
fn fit(mesh: &SurfaceMesh, centre: [f64; 3], radius: f64) -> (f64, f64) {
    let (worst, _, outward) = fit_rms(mesh, centre, radius);
    (worst, outward)
}

/// Largest and root-mean-square distance of the vertices from the sphere, and the
/// share of triangles facing out.
fn fit_rms(mesh: &SurfaceMesh, centre: [f64; 3], radius: f64) -> (f64, f64, f64) {
    let mut worst: f64 = 0.0;
    let mut sum2 = 0.0;
    for v in 0..mesh.vertex_count() {
        let p = mesh.world(v).unwrap();
        let r = (0..3)
            .map(|k| (p[k] - centre[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        worst = worst.max((r - radius).abs());
        sum2 += (r - radius).powi(2);
    }
    let rms = (sum2 / mesh.vertex_count().max(1) as f64).sqrt();
    let outward = mesh
        .triangles
        .iter()
        .filter(|t| {
            let p = t.map(|i| mesh.world(i as usize).unwrap());
            let e1 = [0, 1, 2].map(|k| p[1][k] - p[0][k]);
            let e2 = [0, 1, 2].map(|k| p[2][k] - p[0][k]);
            let n = [
                e1[1] * e2[2] - e1[2] * e2[1],
                e1[2] * e2[0] - e1[0] * e2[2],
                e1[0] * e2[1] - e1[1] * e2[0],
            ];
            let c = (0..3).map(|k| (p[0][k] + p[1][k] + p[2][k]) / 3.0 - centre[k]);
            n.iter().zip(c).map(|(a, b)| a * b).sum::<f64>() > 0.0
        })
        .count();
    (
        worst,
        rms,
        outward as f64 / mesh.triangle_count().max(1) as f64,
    )
}

#[test]
fn the_sphere_is_recovered_within_a_fraction_of_a_voxel_far_from_the_origin() {
    let voxel = 0.05;
    let tsdf = fused(FAR, 1.0, voxel, 0.0);
    let mesh = extract(&tsdf, whole(&tsdf), FAR);
    assert!(mesh.triangle_count() > 2_000, "{}", mesh.triangle_count());
    let (worst, rms, outward) = fit_rms(&mesh, FAR, 1.0);
    assert!(worst < 0.2 * voxel, "worst {worst} m");
    assert!(rms < 0.05 * voxel, "rms {rms} m");
    assert!(outward > 0.99, "outward share {outward}");
    // Closed: every edge is shared by exactly two triangles.
    let mut edges = std::collections::HashMap::new();
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3]));
            *edges.entry((a, b)).or_insert(0u32) += 1;
        }
    }
    assert!(
        edges.values().all(|&c| c == 2),
        "the sphere's mesh has holes"
    );
    // Colour survives fusion.
    assert!(mesh.colours.iter().all(|c| *c == [200, 80, 40]));
}

#[test]
fn coarser_levels_stay_on_the_surface_within_their_voxel() {
    let tsdf = fused(FAR, 2.0, 0.05, 0.0);
    let mut level = tsdf.clone();
    for _ in 0..3 {
        level = level.downsampled();
        let mesh = extract(&level, whole(&level), FAR);
        assert!(!mesh.is_empty());
        let (worst, outward) = fit(&mesh, FAR, 2.0);
        assert!(
            worst < 0.5 * level.voxel_m(),
            "voxel {}: worst {worst} m",
            level.voxel_m()
        );
        assert!(
            outward > 0.98,
            "voxel {}: outward {outward}",
            level.voxel_m()
        );
    }
}

#[test]
fn regions_that_tile_the_plane_partition_the_surface_and_meet_exactly() {
    let tsdf = fused(FAR, 1.0, 0.05, 0.0);
    let all = whole(&tsdf);
    let full = extract(&tsdf, all, FAR);
    let mid = [(all.lo[0] + all.hi[0]) / 2, (all.lo[1] + all.hi[1]) / 2];
    let mut triangles = 0;
    let mut border_points = Vec::new();
    for (xl, xh) in [(all.lo[0], mid[0]), (mid[0], all.hi[0])] {
        for (yl, yh) in [(all.lo[1], mid[1]), (mid[1], all.hi[1])] {
            let part = extract(
                &tsdf,
                VoxelRegion {
                    lo: [xl, yl],
                    hi: [xh, yh],
                },
                FAR,
            );
            triangles += part.triangle_count();
            border_points.extend((0..part.vertex_count()).map(|v| part.positions[v]));
        }
    }
    assert_eq!(triangles, full.triangle_count());
    // Every vertex of every part is a vertex of the whole, bit for bit.
    let whole_set: std::collections::HashSet<[u32; 3]> =
        full.positions.iter().map(|p| p.map(f32::to_bits)).collect();
    assert!(
        border_points
            .iter()
            .all(|p| whole_set.contains(&p.map(f32::to_bits)))
    );
}

#[test]
fn simplification_meets_the_budget_within_its_error_bound() {
    let tsdf = fused(FAR, 1.0, 0.05, 0.0);
    let mesh = extract(&tsdf, whole(&tsdf), FAR);
    let budget = mesh.triangle_count() / 8;
    let out = simplify(&mesh, budget, 0.05);
    assert!(
        out.mesh.triangle_count() <= budget + budget / 10,
        "{}",
        out.mesh.triangle_count()
    );
    assert!(out.error_m <= 0.05 + 1e-6, "{}", out.error_m);
    let (worst, outward) = fit(&out.mesh, FAR, 1.0);
    assert!(worst < 0.05 + 0.35 * 0.05, "worst {worst}");
    assert!(outward > 0.99, "{outward}");
    // A mesh within budget is untouched.
    let same = simplify(&mesh, mesh.triangle_count(), 0.05);
    assert_eq!(same.mesh, mesh);
    assert_eq!(same.error_m, 0.0);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    /// Any sphere, any voxel size, with range noise: the surface is finite, closed to
    /// within the noise, and within noise plus a fraction of a voxel of the truth.
    #[test]
    fn noisy_spheres_stay_finite_and_close(
        radius in 0.4f64..2.0,
        voxel in 0.03f64..0.12,
        noise_frac in 0.0f64..0.3,
        offset in prop::array::uniform3(-1.0e6f64..1.0e6),
    ) {
        let noise = noise_frac * voxel;
        let tsdf = fused(offset, radius, voxel, noise);
        let mesh = extract(&tsdf, whole(&tsdf), offset);
        prop_assert!(mesh.positions.iter().flatten().all(|x| x.is_finite()));
        prop_assert!(!mesh.is_empty());
        let (worst, outward) = fit(&mesh, offset, radius);
        prop_assert!(worst < noise + 0.5 * voxel, "worst {} voxel {} noise {}", worst, voxel, noise);
        prop_assert!(outward > 0.95, "outward {}", outward);
    }
}
