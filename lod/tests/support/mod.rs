//! A street with ground truth, fused without the simulator: flat ground between two
//! facades, seen by a camera walking down its middle. Every surface is a plane, so
//! the distance of any point to the truth is exact.
#![allow(dead_code)] // each test file uses its own part

use texel_lod::{Hierarchy, LodConfig, build_from_field};
use texel_surface::{Sample, Tsdf, TsdfConfig};

/// Half the street's width (the facades stand at y = ±HALF_WIDTH).
pub const HALF_WIDTH: f64 = 6.0;
pub const FACADE_HEIGHT: f64 = 8.0;

/// Distance of a world point from the nearest true surface, with the street placed
/// at `offset`.
pub fn distance_to_truth(p: [f64; 3], offset: [f64; 3]) -> f64 {
    let (y, z) = (p[1] - offset[1], p[2] - offset[2]);
    let ground = z.abs();
    let facade = (y.abs() - HALF_WIDTH).abs();
    ground.min(facade)
}

/// A colour that varies along the street, so tiles differ.
fn colour_at(p: [f64; 3]) -> [u8; 3] {
    let band = ((p[0] / 2.0).floor() as i64).rem_euclid(3) as u8;
    [80 + band * 50, 120, 200 - band * 40]
}

/// Samples from a camera at 1.5 m height every `step_m` along `length_m`, each a fan
/// of rays cut where they meet the ground or a facade within 12 m.
pub fn street_samples(length_m: f64, step_m: f64, offset: [f64; 3]) -> Vec<Sample> {
    street_stops(length_m, step_m, offset).concat()
}

/// [`street_samples`] stop by stop: one "scan" per camera position.
pub fn street_stops(length_m: f64, step_m: f64, offset: [f64; 3]) -> Vec<Vec<Sample>> {
    street_stops_coloured(length_m, step_m, offset, colour_at)
}

/// [`street_stops`] with the surfaces painted by `colour` (of the point before the
/// offset).
pub fn street_stops_coloured(
    length_m: f64,
    step_m: f64,
    offset: [f64; 3],
    colour: fn([f64; 3]) -> [u8; 3],
) -> Vec<Vec<Sample>> {
    let mut stops_out = Vec::new();
    let stops = (length_m / step_m).floor() as i64;
    for s in 0..=stops {
        let mut samples = Vec::new();
        let eye = [s as f64 * step_m, 0.0, 1.5];
        for i in 0..240 {
            let azimuth = f64::from(i) / 240.0 * std::f64::consts::TAU;
            for j in 0..80 {
                let elevation = -1.3 + f64::from(j) / 79.0 * 2.3;
                let d = [
                    azimuth.cos() * elevation.cos(),
                    azimuth.sin() * elevation.cos(),
                    elevation.sin(),
                ];
                let mut best = f64::INFINITY;
                if d[2] < -1e-6 {
                    best = best.min(-eye[2] / d[2]);
                }
                for wall in [HALF_WIDTH, -HALF_WIDTH] {
                    if d[1].abs() > 1e-6 {
                        let t = (wall - eye[1]) / d[1];
                        let z = eye[2] + t * d[2];
                        if t > 0.0 && (0.0..=FACADE_HEIGHT).contains(&z) {
                            best = best.min(t);
                        }
                    }
                }
                if best >= 12.0 {
                    continue;
                }
                let p = [0, 1, 2].map(|k| eye[k] + best * d[k]);
                // Normal accuracy: the cosine between the ray and the surface normal.
                let cos = if (p[2]).abs() < 1e-9 {
                    d[2].abs()
                } else {
                    d[1].abs()
                };
                samples.push(Sample {
                    point_m: [0, 1, 2].map(|k| p[k] + offset[k]),
                    centre_m: [0, 1, 2].map(|k| eye[k] + offset[k]),
                    weight: (cos as f32).max(0.05),
                    colour: Some(colour(p)),
                });
            }
        }
        stops_out.push(samples);
    }
    stops_out
}

pub fn street_field(length_m: f64, offset: [f64; 3], config: &LodConfig) -> Tsdf {
    let mut field = Tsdf::new(TsdfConfig {
        voxel_m: config.leaf_voxel_m,
        truncation_voxels: config.truncation_voxels,
    })
    .expect("valid field");
    field.integrate(&street_samples(length_m, 1.0, offset));
    field
}

pub fn street(length_m: f64, offset: [f64; 3], config: &LodConfig) -> Hierarchy {
    build_from_field(street_field(length_m, offset, config), config).expect("a hierarchy")
}
