//! The field's own tests: indices, configs, a wall's distances, removal, resampling.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use super::*;

#[test]
fn split_and_join_are_inverse_across_zero() {
    for index in [[0, 0, 0], [-1, -1, -1], [7, 8, -9], [-8, 15, 1 << 40]] {
        let (key, slot) = split(index);
        assert_eq!(join(key, slot), index);
    }
}

#[test]
fn bad_configs_are_refused_by_name() {
    let e = Tsdf::new(TsdfConfig {
        voxel_m: 0.0,
        ..TsdfConfig::default()
    })
    .unwrap_err();
    assert!(e.to_string().contains("voxel_m"), "{e}");
    let e = Tsdf::new(TsdfConfig {
        truncation_voxels: f64::NAN,
        ..TsdfConfig::default()
    })
    .unwrap_err();
    assert!(e.to_string().contains("truncation_voxels"), "{e}");
}

#[test]
fn a_plane_seen_head_on_has_the_true_distance_in_its_band() {
    let mut tsdf = Tsdf::new(TsdfConfig::default()).unwrap();
    // Wall at x = 2.01, seen from the origin along +x.
    let samples: Vec<Sample> = (-20..20)
        .flat_map(|y| (-20..20).map(move |z| (y, z)))
        .map(|(y, z)| Sample {
            point_m: [2.01, f64::from(y) * 0.02, f64::from(z) * 0.02],
            centre_m: [0.0, f64::from(y) * 0.02, f64::from(z) * 0.02],
            weight: 1.0,
            colour: Some([200, 100, 50]),
        })
        .collect();
    assert!(tsdf.integrate(&samples) > 0);
    for i in 38..42 {
        let v = tsdf.voxel([i, 0, 0]).unwrap();
        let centre = tsdf.centre_of([i, 0, 0])[0];
        assert!(
            (f64::from(v.sdf_m) - (2.01 - centre)).abs() < 1e-5,
            "{i}: {v:?}"
        );
        assert_eq!(v.colour(), Some([200, 100, 50]));
    }
    // Beyond the band nothing is written.
    assert!(tsdf.voxel([30, 0, 0]).is_none());
    assert!(tsdf.voxel([45, 0, 0]).is_none());
    // Renaming voxels moves no sample.
    let before = *tsdf.voxel([40, 0, 0]).unwrap();
    let moved = tsdf.clone().reanchored([16, -8, 0]).unwrap();
    assert_eq!(moved.voxel([24, 8, 0]), Some(&before));
    assert_eq!(moved.index_of([2.01, 0.0, 0.0]), [24, 8, 0]);
    assert!(tsdf.reanchored([3, 0, 0]).is_err());
}

#[test]
fn removing_samples_undoes_adding_them() {
    let wall = |x: f64, colour: [u8; 3]| -> Vec<Sample> {
        (-20..20)
            .flat_map(|y| (-20..20).map(move |z| (y, z)))
            .map(|(y, z)| Sample {
                point_m: [x, f64::from(y) * 0.02, f64::from(z) * 0.02],
                centre_m: [0.0, f64::from(y) * 0.013, f64::from(z) * 0.017],
                weight: 0.8,
                colour: Some(colour),
            })
            .collect()
    };
    let (a, b) = (wall(2.01, [200, 100, 50]), wall(2.07, [10, 20, 30]));
    let mut only_a = Tsdf::new(TsdfConfig::default()).unwrap();
    only_a.integrate(&a);
    let mut both = Tsdf::new(TsdfConfig::default()).unwrap();
    both.integrate(&a);
    both.integrate(&b);
    assert!(both.block_count() >= only_a.block_count());
    both.remove(&b);
    assert_eq!(both.block_count(), only_a.block_count());
    for (key, block) in &only_a.blocks {
        let other = &both.blocks[key];
        for (x, y) in block.voxels.iter().zip(other.voxels.iter()) {
            assert!((x.sdf_m - y.sdf_m).abs() < 1e-5, "{x:?} vs {y:?}");
            assert!((x.weight - y.weight).abs() < 1e-4, "{x:?} vs {y:?}");
            assert_eq!(x.colour(), y.colour());
        }
    }
    // Taking everything out leaves nothing, blocks included.
    both.remove(&a);
    assert_eq!(both.block_count(), 0);
    // Removing what was never added changes nothing.
    let mut untouched = only_a.clone();
    untouched.remove(&wall(9.0, [0, 0, 0]));
    assert_eq!(untouched.block_count(), only_a.block_count());
}

#[test]
fn degenerate_samples_write_nothing() {
    let mut tsdf = Tsdf::new(TsdfConfig::default()).unwrap();
    let bad = [
        Sample {
            point_m: [1.0, 1.0, 1.0],
            centre_m: [1.0, 1.0, 1.0],
            weight: 1.0,
            colour: None,
        },
        Sample {
            point_m: [f64::NAN, 0.0, 0.0],
            centre_m: [0.0; 3],
            weight: 1.0,
            colour: None,
        },
        Sample {
            point_m: [1.0, 0.0, 0.0],
            centre_m: [0.0; 3],
            weight: 0.0,
            colour: None,
        },
    ];
    assert_eq!(tsdf.integrate(&bad), 0);
    assert_eq!(tsdf.block_count(), 0);
    assert!(tsdf.bounds().is_none());
}

#[test]
fn downsampling_keeps_a_planar_field_exact() {
    let mut tsdf = Tsdf::new(TsdfConfig::default()).unwrap();
    let samples: Vec<Sample> = (-40..40)
        .flat_map(|y| (-40..40).map(move |z| (y, z)))
        .map(|(y, z)| Sample {
            point_m: [3.03, f64::from(y) * 0.01, f64::from(z) * 0.01],
            centre_m: [0.0, f64::from(y) * 0.01, f64::from(z) * 0.01],
            weight: 1.0,
            colour: None,
        })
        .collect();
    tsdf.integrate(&samples);
    let coarse = tsdf.downsampled();
    assert_eq!(coarse.voxel_m(), 0.1);
    let i = coarse.index_of([3.03, 0.05, 0.05]);
    let v = coarse.voxel(i).unwrap();
    let centre = coarse.centre_of(i)[0];
    assert!((f64::from(v.sdf_m) - (3.03 - centre)).abs() < 1e-4, "{v:?}");
}
