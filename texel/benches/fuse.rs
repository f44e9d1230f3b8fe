//! Fusion of one texel frame on one core: a 128x128 and a 256x256 lidar frame with a
//! 1280x960 EO image (target: <= 0.5 ms for 128x128). The EO image is moved into the
//! scan, so the bench hands each iteration its own frame, made outside the timing.
//! Baseline in the same run: copying the EO image once, the cost fusion avoids by
//! moving it.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use nalgebra::Vector2;
use std::hint::black_box;
use std::time::Instant;
use texel::pose::pose_from_parts;
use texel::{
    Distortion, EoFrame, FuseConfig, PinholeCamera, PlumbBob, RangeFrame, RangeNoise, Sensor,
    SensorModel, fuse,
};

fn sensor(side: u32) -> Sensor {
    let eo = PinholeCamera {
        width: 1280,
        height: 960,
        fx: 1100.0,
        fy: 1100.0,
        cx: 639.5,
        cy: 479.5,
        skew: 0.0,
        distortion: Distortion::PlumbBob(PlumbBob {
            k1: -0.12,
            k2: 0.03,
            p1: 0.0005,
            p2: -0.0003,
            k3: 0.0,
        }),
    };
    Sensor::new(SensorModel {
        name: "bench".into(),
        lidar: PinholeCamera::from_vertical_fov(side, side, 45.0).unwrap(),
        eo,
        eo_from_lidar: pose_from_parts([0.03, 0.0, 0.0], [0.0, 0.002, 0.0, 1.0]).unwrap(),
        range_noise: RangeNoise {
            sigma_m: 0.005,
            sigma_per_m: 0.001,
        },
        range_bias_m: 0.0,
        min_range_m: 0.3,
        max_range_m: 30.0,
        eo_response: None,
    })
}

/// A wall at 4 m with a box at 2.5 m in the middle and a few no-returns.
fn range_frame(s: &Sensor) -> RangeFrame {
    let lidar = &s.model.lidar;
    let mut f = RangeFrame::empty(lidar.width, lidar.height, 1, 1);
    for v in 0..lidar.height {
        for u in 0..lidar.width {
            let ray = lidar
                .unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                .unwrap();
            let in_box = (lidar.width / 3..2 * lidar.width / 3).contains(&u)
                && (lidar.height / 3..2 * lidar.height / 3).contains(&v);
            let depth = if in_box { 2.5 } else { 4.0 };
            if (u * 7 + v * 13) % 97 != 0 {
                f.ranges_m[(v * lidar.width + u) as usize] = (depth / ray.z) as f32;
            }
        }
    }
    f
}

/// A known loop for turning instruction counts into time on a shared machine: a
/// vectorised polynomial over 16384 values (L2-resident), like fusion's per-pixel
/// arithmetic. Its instruction count (callgrind) over its time in the same run is the
/// machine's rate for such code at that moment.
#[inline(never)]
fn calibration(xs: &[f64], out: &mut [f64]) {
    for (o, &x) in out.iter_mut().zip(xs) {
        *o = (((0.1 * x + 0.2) * x + 0.3) * x + 0.4) * x + 0.5;
    }
}

fn bench(c: &mut Criterion) {
    let xs: Vec<f64> = (0..16384).map(|i| f64::from(i) * 1e-4).collect();
    let mut out = vec![0.0; xs.len()];
    let eo = EoFrame {
        width: 1280,
        height: 960,
        rgb: vec![128; 1280 * 960 * 3],
        timestamp_ns: 1,
        exposure: None,
    };
    let mut group = c.benchmark_group("fuse_one_core");
    group.bench_function("baseline_copy_eo_1280x960", |b| {
        b.iter(|| black_box(eo.clone()))
    });
    group.bench_function("calibration_poly_16384", |b| {
        b.iter(|| calibration(black_box(&xs), black_box(&mut out)))
    });
    for side in [128u32, 256] {
        let s = sensor(side);
        let frame = range_frame(&s);
        let config = FuseConfig::default();
        group.bench_function(format!("fuse_{side}x{side}_eo_1280x960"), |b| {
            b.iter_batched(
                || eo.clone(),
                |eo| black_box(fuse(&frame, eo, &s, &config).unwrap()),
                BatchSize::LargeInput,
            )
        });
    }
    group.finish();
}

/// Pairs of (calibration, fusion) timed alternately by [`calibrated`].
const PAIRS: usize = 300;

/// Fusion timed alternately with the calibration loop in this process, so both meet
/// the same load: the median ratio of their times, times the calibration's best
/// (least disturbed) time, estimates fusion's time on an unloaded core. Printed after
/// criterion's figures; skipped under `--profile-time` (profilers).
fn calibrated(_: &mut Criterion) {
    if std::env::args().any(|a| a == "--profile-time" || a == "--list") {
        return;
    }
    let xs: Vec<f64> = (0..16384).map(|i| f64::from(i) * 1e-4).collect();
    let mut out = vec![0.0; xs.len()];
    let eo = EoFrame {
        width: 1280,
        height: 960,
        rgb: vec![128; 1280 * 960 * 3],
        timestamp_ns: 1,
        exposure: None,
    };
    for side in [128u32, 256] {
        let s = sensor(side);
        let frame = range_frame(&s);
        let config = FuseConfig::default();
        let mut ratios = Vec::with_capacity(PAIRS);
        let (mut best_calibration, mut best_fuse) = (f64::INFINITY, f64::INFINITY);
        for _ in 0..PAIRS {
            let eo = eo.clone();
            let t0 = Instant::now();
            calibration(black_box(&xs), black_box(&mut out));
            let t1 = Instant::now();
            let scan = fuse(&frame, eo, &s, &config).unwrap();
            let t2 = Instant::now();
            drop(black_box(scan));
            let (c, f) = ((t1 - t0).as_secs_f64(), (t2 - t1).as_secs_f64());
            ratios.push(f / c);
            best_calibration = best_calibration.min(c);
            best_fuse = best_fuse.min(f);
        }
        ratios.sort_by(f64::total_cmp);
        let ratio = ratios[PAIRS / 2];
        println!(
            "fuse_{side}x{side}: {ratio:.1} x calibration (median of {PAIRS} interleaved pairs); \
             calibration best {:.1} us, so about {:.0} us on an unloaded core; fuse best {:.0} us",
            best_calibration * 1e6,
            ratio * best_calibration * 1e6,
            best_fuse * 1e6,
        );
    }
}

criterion_group!(benches, bench, calibrated);
criterion_main!(benches);
