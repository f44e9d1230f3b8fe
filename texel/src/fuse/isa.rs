//! Which instruction set fusion's row loop runs with: the row loop is compiled twice,
//! for the baseline x86-64 target (SSE2) and for AVX2, and the AVX2 build is chosen
//! at run time on CPUs that have it.
//!
//! Why: the loops over a row are branch-free array code that the compiler vectorises;
//! AVX2 doubles the lanes (8 f32, 4 f64), and the baseline target cannot assume it.
//! Why it is exact: only the lane count changes. Every lane computes the same IEEE
//! operations in the same order (no fused multiply-add is enabled, and Rust never
//! contracts `a * b + c` on its own), so both builds give bit-identical scans, as
//! `tests::builds_agree` checks.

use crate::frames::RangeFrame;
use crate::sensor::Sensor;

use super::mesh::Mesh;
use super::rows::Points;

/// An instruction set the row loop is built for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Isa {
    /// The compilation target's baseline.
    Baseline,
    /// x86-64 with AVX2 (checked at run time before it is chosen).
    #[cfg(target_arch = "x86_64")]
    Avx2,
}

impl Isa {
    /// The widest instruction set this CPU supports.
    pub fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            return Self::Avx2;
        }
        Self::Baseline
    }
}

/// [`super::fuse_rows`] built for `isa`; an `isa` the CPU lacks falls back to the
/// baseline.
pub(super) fn fuse_rows_with(
    isa: Isa,
    range: &RangeFrame,
    sensor: &Sensor,
    points: &mut Points,
    mesh: &mut Mesh,
) {
    match isa {
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 if std::arch::is_x86_feature_detected!("avx2") => {
            // SAFETY: `fuse_rows_avx2` only requires AVX2, which the CPU was just
            // found to support; it is otherwise safe code.
            #[allow(unsafe_code)]
            unsafe {
                fuse_rows_avx2(range, sensor, points, mesh)
            }
        }
        _ => super::fuse_rows(range, sensor, points, mesh),
    }
}

/// The row loop compiled with AVX2 enabled (everything it calls is inlined into it).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn fuse_rows_avx2(range: &RangeFrame, sensor: &Sensor, points: &mut Points, mesh: &mut Mesh) {
    super::fuse_rows(range, sensor, points, mesh);
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use proptest::prelude::*;

    use std::sync::Arc;

    use super::Isa;
    use crate::camera::{Distortion, PinholeCamera};
    use crate::distortion::PlumbBob;
    use crate::frames::{EoFrame, RangeFrame};
    use crate::fuse::{FuseConfig, fuse_with};
    use crate::pose::pose_from_parts;
    use crate::scan::TexelScan;
    use crate::sensor::{RangeNoise, Sensor, SensorModel};

    fn sensor(side: u32, k1: f64, p1: f64, turn: f64) -> Sensor {
        let eo = PinholeCamera {
            width: 96,
            height: 72,
            fx: 80.0,
            fy: 81.0,
            cx: 47.2,
            cy: 35.9,
            skew: 0.0,
            distortion: Distortion::PlumbBob(PlumbBob {
                k1,
                k2: 0.02,
                p1,
                p2: -0.0004,
                k3: 0.0,
            }),
        };
        let half = (turn * 0.5).sin();
        Sensor::new(SensorModel {
            name: "isa".into(),
            lidar: PinholeCamera::from_vertical_fov(side, side - 3, 50.0).unwrap(),
            eo,
            eo_from_lidar: pose_from_parts(
                [0.02, -0.01, 0.005],
                [0.0, half, 0.0, (turn * 0.5).cos()],
            )
            .unwrap(),
            range_noise: RangeNoise {
                sigma_m: 0.004,
                sigma_per_m: 0.001,
            },
            range_bias_m: 0.003,
            min_range_m: 0.1,
            max_range_m: 100.0,
            eo_response: None,
        })
    }

    /// Every array of the scan, floats as bit patterns.
    fn bits(scan: &TexelScan) -> Vec<u32> {
        let mut out = Vec::new();
        out.extend(scan.vertices.iter().flatten().map(|v| v.to_bits()));
        out.extend(scan.tex_coords.iter().flatten().map(|v| v.to_bits()));
        out.extend(scan.vertex_textured.iter().map(|&t| u32::from(t)));
        out.extend(&scan.vertex_pixel);
        out.extend(&scan.pixel_vertex);
        out.extend(scan.triangles.iter().flatten());
        out.extend(scan.triangle_accuracy.iter().map(|v| v.to_bits()));
        out.extend(scan.triangle_flags.iter().map(|f| u32::from(f.0)));
        out
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// The AVX2 build of the row loop gives the baseline build's scan bit for bit,
        /// on frames with steps, grazing slopes, every kind of no-return and points
        /// off the EO image.
        #[test]
        fn builds_agree(
            side in 5u32..40,
            k1 in -0.3f64..0.1,
            p1 in -0.002f64..0.002,
            turn in -0.3f64..0.3,
            ranges in proptest::collection::vec(
                prop_oneof![
                    8 => 0.05f32..40.0,
                    1 => Just(f32::NAN),
                    1 => Just(0.0f32),
                    1 => Just(f32::INFINITY),
                    1 => Just(-1.0f32),
                ],
                1600,
            ),
        ) {
            let s = sensor(side, k1, p1, turn);
            let (w, h) = (s.model.lidar.width, s.model.lidar.height);
            let mut frame = RangeFrame::empty(w, h, 9, 3);
            for (r, &x) in frame.ranges_m.iter_mut().zip(&ranges) {
                *r = x;
            }
            let eo = EoFrame {
                width: 96,
                height: 72,
                rgb: vec![7; 96 * 72 * 3],
                timestamp_ns: 9,
                exposure: None,
            };
            let config = FuseConfig::default();
            let baseline = fuse_with(Isa::Baseline, &frame, Arc::new(eo.clone()), &s, &config).unwrap();
            let detected = fuse_with(Isa::detect(), &frame, Arc::new(eo), &s, &config).unwrap();
            prop_assert!(baseline.vertex_count() > 0);
            prop_assert_eq!(bits(&baseline), bits(&detected));
        }
    }
}
