//! Frames are pure functions of (scene, options, seed, index).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use common::{load, small};

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

fn bits(f: &sims::SimFrame) -> (Vec<u32>, Vec<u8>) {
    (
        f.pair.range.ranges_m.iter().map(|r| r.to_bits()).collect(),
        f.pair.eo.rgb.clone(),
    )
}

#[test]
fn same_seed_gives_bit_identical_frames_with_one_and_two_threads_in_any_order() {
    let all = [
        "mixed_pixels",
        "dropouts",
        "range_noise",
        "range_quantisation",
        "lens_distortion",
        "specular",
        "motion_blur",
        "vignetting",
        "exposure",
        "sensor_noise",
    ];
    let sim = small(load("lab"), 42, Some(&all));
    let one = pool(1).install(|| bits(&sim.frame(2).unwrap()));
    let two = pool(2).install(|| bits(&sim.frame(2).unwrap()));
    assert_eq!(one, two);
    // Rendering other frames first changes nothing.
    let _ = sim.frame(0).unwrap();
    let _ = sim.frame(5).unwrap();
    assert_eq!(bits(&sim.frame(2).unwrap()), one);
    // A new simulator with the same seed agrees.
    let again = small(load("lab"), 42, Some(&all));
    assert_eq!(bits(&again.frame(2).unwrap()), one);
}

#[test]
fn different_seeds_differ_where_noise_is_on_and_not_where_it_is_off() {
    let noisy = ["range_noise", "sensor_noise"];
    let a = bits(&small(load("lab"), 1, Some(&noisy)).frame(0).unwrap());
    let b = bits(&small(load("lab"), 2, Some(&noisy)).frame(0).unwrap());
    let range_diff = a.0.iter().zip(&b.0).filter(|(x, y)| x != y).count();
    let eo_diff = a.1.iter().zip(&b.1).filter(|(x, y)| x != y).count();
    assert!(range_diff > a.0.len() * 9 / 10, "{range_diff}");
    assert!(eo_diff > a.1.len() / 2, "{eo_diff}");
    let clean_a = bits(&small(load("lab"), 1, Some(&[])).frame(0).unwrap());
    let clean_b = bits(&small(load("lab"), 2, Some(&[])).frame(0).unwrap());
    assert_eq!(clean_a, clean_b);
}

#[test]
fn frames_outside_the_trajectory_are_errors() {
    let sim = small(load("wall"), 0, None);
    assert_eq!(sim.frame_count(), 10);
    assert!(matches!(
        sim.frame(10),
        Err(sims::SimError::FrameOutOfRange {
            index: 10,
            frames: 10
        })
    ));
}
