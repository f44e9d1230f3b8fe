//! Registration speed on one core (a one-thread rayon pool):
//! - pairwise: a 16k-point `lab` pair 3 degrees and 5 cm apart with range noise,
//!   `align_pair` alone and with both pyramids built (as Open3D's time includes its
//!   normal estimation);
//! - per scan: `Registrar::register` over a 128x128 `lab-walk` sequence;
//! - the in-run baseline: building one 128x128 pyramid (points, normals, levels).
//!
//! Times are CPU time of the process (`CLOCK_PROCESS_CPUTIME_ID`), which a shared,
//! loaded machine inflates less than wall time. Prints each median and its ratio to
//! the baseline measured in the same run (ratios travel better than times). The Open3D ratio comes from
//! `texel-bench tradeoffs registration`, which runs both on the same pairs.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use criterion::{Criterion, criterion_group};
use texel_bench::tradeoffs::registration::data;
use texel_register::clock::process_cpu_time;
use texel_register::{
    AlignConfig, PyramidOptions, Registrar, RegistrationConfig, ScanPyramid, align_pair,
};

/// Per-iteration times of every `iter_custom` call, by benchmark name.
static TIMES: Mutex<BTreeMap<&'static str, Vec<f64>>> = Mutex::new(BTreeMap::new());

fn record(name: &'static str, total: Duration, iters: u64) {
    let per = total.as_secs_f64() * 1000.0 / iters.max(1) as f64;
    TIMES.lock().unwrap().entry(name).or_default().push(per);
}

/// CPU time so far (zero where the clock is not available: then every time is 0).
fn cpu() -> Duration {
    process_cpu_time().unwrap_or_default()
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn one_thread() -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
}

fn options(levels: u32) -> PyramidOptions {
    PyramidOptions {
        levels,
        eo_levels: 0,
        first_eo_level: 0,
    }
}

fn pairwise(c: &mut Criterion) {
    let scenes = repo().join("configs/scenes");
    let pair = data::perturbed_pairs(&scenes, "lab", 1, 3.0, 0.05, 11)
        .unwrap()
        .remove(0);
    let config = AlignConfig::default();
    let pool = one_thread();
    let levels = config.pyramid_levels;
    let target =
        ScanPyramid::build_with(Arc::clone(&pair.target), &pair.lidar, None, options(levels));
    let source =
        ScanPyramid::build_with(Arc::clone(&pair.source), &pair.lidar, None, options(levels));
    println!(
        "pair: {} and {} points",
        pair.target.vertex_count(),
        pair.source.vertex_count()
    );
    let mut group = c.benchmark_group("registration");
    group.sample_size(30);
    group.bench_function("baseline: pyramid build 128x128", |b| {
        b.iter_custom(|iters| {
            let start = cpu();
            pool.install(|| {
                for _ in 0..iters {
                    black_box(ScanPyramid::build_with(
                        Arc::clone(&pair.source),
                        &pair.lidar,
                        None,
                        options(levels),
                    ));
                }
            });
            let t = cpu().saturating_sub(start);
            record("baseline: pyramid build 128x128", t, iters);
            t
        })
    });
    group.bench_function("pairwise 16k: align", |b| {
        b.iter_custom(|iters| {
            let start = cpu();
            pool.install(|| {
                for _ in 0..iters {
                    black_box(align_pair(&source, &target, &pair.initial, &config));
                }
            });
            let t = cpu().saturating_sub(start);
            record("pairwise 16k: align", t, iters);
            t
        })
    });
    group.bench_function("pairwise 16k: both pyramids + align", |b| {
        b.iter_custom(|iters| {
            let start = cpu();
            pool.install(|| {
                for _ in 0..iters {
                    let t = ScanPyramid::build_with(
                        Arc::clone(&pair.target),
                        &pair.lidar,
                        None,
                        options(levels),
                    );
                    let s = ScanPyramid::build_with(
                        Arc::clone(&pair.source),
                        &pair.lidar,
                        None,
                        options(levels),
                    );
                    black_box(align_pair(&s, &t, &pair.initial, &config));
                }
            });
            let t = cpu().saturating_sub(start);
            record("pairwise 16k: both pyramids + align", t, iters);
            t
        })
    });
    group.finish();
}

fn per_scan(c: &mut Criterion) {
    let repo = repo();
    let sequence = data::sequence(
        &repo.join("configs/scenes"),
        &repo.join("target/tradeoffs-cache"),
        &data::SequenceSpec {
            scene: "lab-walk",
            frames: 24,
            seed: 1,
            orbit_period_frames: None,
        },
    )
    .unwrap();
    let pool = one_thread();
    let mut group = c.benchmark_group("registration");
    group.sample_size(20);
    group.bench_function("per scan: register (lab-walk 128x128)", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            let mut done = 0;
            pool.install(|| {
                while done < iters {
                    // A fresh registrar per pass over the sequence; the anchor scan
                    // does no registration and is not timed.
                    let mut reg = Registrar::new(RegistrationConfig::default());
                    reg.register(Arc::clone(&sequence.scans[0]), &sequence.sensor);
                    for scan in &sequence.scans[1..] {
                        if done == iters {
                            break;
                        }
                        let start = cpu();
                        black_box(reg.register(Arc::clone(scan), &sequence.sensor));
                        total += cpu().saturating_sub(start);
                        done += 1;
                    }
                }
            });
            record("per scan: register (lab-walk 128x128)", total, iters);
            total
        })
    });
    group.finish();
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s.get(s.len() / 2).copied().unwrap_or(f64::NAN)
}

criterion_group!(benches, pairwise, per_scan);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
    let times = TIMES.lock().unwrap();
    let Some(baseline) = times
        .get("baseline: pyramid build 128x128")
        .map(|v| median(v))
    else {
        return;
    };
    println!("\nmedian CPU times on one core, and their ratio to the baseline (pyramid build):");
    for (name, v) in times.iter() {
        let m = median(v);
        println!("  {name:<42} {m:>8.3} ms  {:>6.2} x baseline", m / baseline);
    }
}
