//! Unproject + project per pixel for a 128x128 (lidar) and a 640x480 (EO) grid under
//! plumb_bob distortion, against the undistorted pinhole as the in-run baseline.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use nalgebra::Vector2;
use std::hint::black_box;
use texel::{Distortion, PinholeCamera, PlumbBob};

fn camera(width: u32, height: u32, distortion: Distortion) -> PinholeCamera {
    PinholeCamera {
        width,
        height,
        fx: 0.9 * f64::from(width),
        fy: 0.9 * f64::from(width),
        cx: (f64::from(width) - 1.0) / 2.0,
        cy: (f64::from(height) - 1.0) / 2.0,
        skew: 0.0,
        distortion,
    }
}

fn round_trip_grid(c: &PinholeCamera) -> f64 {
    let max_r2 = c.max_radius_squared();
    let mut acc = 0.0;
    for v in 0..c.height {
        for u in 0..c.width {
            let px = Vector2::new(f64::from(u), f64::from(v));
            let n = c.unproject_with_domain(px, max_r2).unwrap();
            let p = c
                .project_with_domain(&nalgebra::Vector3::new(n.x, n.y, 1.0), max_r2)
                .unwrap();
            acc += p.x;
        }
    }
    acc
}

fn bench(cr: &mut Criterion) {
    let plumb_bob = Distortion::PlumbBob(PlumbBob {
        k1: -0.28,
        k2: 0.09,
        p1: 0.0008,
        p2: -0.0004,
        k3: -0.01,
    });
    for (w, h) in [(128u32, 128u32), (640, 480)] {
        let mut group = cr.benchmark_group(format!("unproject_project_{w}x{h}"));
        group.throughput(Throughput::Elements(u64::from(w * h)));
        for (name, d) in [
            ("pinhole_baseline", Distortion::None),
            ("plumb_bob", plumb_bob),
        ] {
            let c = camera(w, h, d);
            group.bench_function(name, |b| {
                b.iter(|| black_box(round_trip_grid(black_box(&c))))
            });
        }
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
