//! Response recovery against known curves: the sRGB curve and gamma curves encode a
//! bracket of synthetic radiances, and the recovered `g` must match the true inverse
//! log response; degenerate brackets are refused by name.
#![allow(clippy::unwrap_used)] // tests panic on failure by design

use proptest::prelude::*;

use super::*;

fn srgb_encode(x: f64) -> f64 {
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

fn srgb_decode(v: f64) -> f64 {
    if v <= 0.040_45 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

const TIMES_S: [f64; 4] = [0.125, 0.5, 2.0, 8.0];

/// Radiances spread evenly in log over three and a half decades.
fn radiances(n: usize) -> Vec<f64> {
    let (lo, hi) = (0.002f64.ln(), 6.0f64.ln());
    (0..n)
        .map(|i| (lo + (hi - lo) * i as f64 / (n - 1) as f64).exp())
        .collect()
}

/// The bracket a camera with response `encode` records of `radiances`.
fn bracket(radiances: &[f64], encode: impl Fn(f64) -> f64) -> Vec<Vec<u8>> {
    radiances
        .iter()
        .map(|e| {
            TIMES_S
                .iter()
                .map(|t| (encode((e * t).clamp(0.0, 1.0)) * 255.0).round() as u8)
                .collect()
        })
        .collect()
}

/// The largest difference over `zs` between the recovered curve and the true one
/// (`decode` from codes to linear), both taken relative to their value at 128.
fn worst_error(
    curve: &ResponseCurve,
    decode: impl Fn(f64) -> f64,
    zs: std::ops::RangeInclusive<usize>,
) -> f64 {
    let truth = |z: usize| decode(z as f64 / 255.0).ln();
    zs.map(|z| ((curve.log_exposure[z] - curve.log_exposure[128]) - (truth(z) - truth(128))).abs())
        .fold(0.0, f64::max)
}

#[test]
fn the_srgb_curve_is_recovered_from_a_bracket() {
    let samples = bracket(&radiances(80), srgb_encode);
    let curve = recover_response(&samples, &TIMES_S, 50.0).unwrap();
    // The scale is one row of the least squares: met to rounding.
    assert!(
        curve.log_exposure[128].abs() < 1e-6,
        "{}",
        curve.log_exposure[128]
    );
    let worst = worst_error(&curve, srgb_decode, 16..=240);
    println!("sRGB: worst error in ln exposure over 16..=240: {worst:.4}");
    assert!(worst < 0.05, "{worst}");
    // Monotonic where it was observed: a brighter code is a larger exposure.
    assert!(curve.log_exposure[16..=240].windows(2).all(|w| w[1] > w[0]));
}

#[test]
fn a_pixels_bracket_merges_to_its_radiance_and_saturation_carries_no_weight() {
    let e = radiances(80);
    let samples = bracket(&e, srgb_encode);
    let curve = recover_response(&samples, &TIMES_S, 50.0).unwrap();
    // The curve's scale: g(128) = 0 where the truth has ln(decode(128/255)).
    let offset = srgb_decode(128.0 / 255.0).ln();
    let mut worst: f64 = 0.0;
    // Pixels with a value away from both ends: one 8-bit step near black is a large
    // step in log exposure (a pixel whose brightest value is 34 is 6 % off), which no
    // merge can undo.
    for (radiance, values) in e
        .iter()
        .zip(&samples)
        .filter(|(_, v)| v.iter().any(|&z| (64..=223).contains(&z)))
    {
        let merged = curve.log_radiance(values, &TIMES_S).unwrap();
        worst = worst.max((merged + offset - radiance.ln()).abs());
    }
    println!("merged log radiance: worst error {worst:.4}");
    assert!(worst < 0.05, "{worst}");
    // All saturated, all black: only bounded, so no value (and no log of zero).
    assert_eq!(curve.log_radiance(&[255; 4], &TIMES_S), None);
    assert_eq!(curve.log_radiance(&[0; 4], &TIMES_S), None);
    // One value in range is enough.
    let one = curve.log_radiance(&[0, 0, 128, 255], &TIMES_S).unwrap();
    assert!((one - (curve.log_exposure[128] - 2.0f64.ln())).abs() < 1e-12);
    assert!(one.is_finite());
}

#[test]
fn degenerate_brackets_are_refused_by_name() {
    let samples = bracket(&radiances(40), srgb_encode);
    let mut ragged = samples.clone();
    ragged[3].pop();
    assert_eq!(
        recover_response(&ragged, &TIMES_S, 50.0).unwrap_err(),
        ResponseError::RaggedSample {
            sample: 3,
            got: 3,
            expected: 4
        }
    );
    let single: Vec<Vec<u8>> = samples.iter().map(|s| vec![s[1]]).collect();
    assert_eq!(
        recover_response(&single, &[0.5], 50.0).unwrap_err(),
        ResponseError::TooFewExposures { distinct: 1 }
    );
    assert_eq!(
        recover_response(&samples, &[1.0; 4], 50.0).unwrap_err(),
        ResponseError::TooFewExposures { distinct: 1 }
    );
    let e = recover_response(&samples, &[0.125, 0.0, 2.0, 8.0], 50.0).unwrap_err();
    assert!(e.to_string().contains("exposure time 1"), "{e}");
    assert!(recover_response(&samples, &[0.125, f64::NAN, 2.0, 8.0], 50.0).is_err());
    assert!(recover_response(&samples, &TIMES_S, 0.0).is_err());
    assert!(recover_response(&samples, &TIMES_S, f64::INFINITY).is_err());
    let saturated = vec![vec![255u8; 4]; 20];
    assert_eq!(
        recover_response(&saturated, &TIMES_S, 50.0).unwrap_err(),
        ResponseError::NoInformation
    );
    let black = vec![vec![0u8; 4]; 20];
    assert_eq!(
        recover_response(&black, &TIMES_S, 50.0).unwrap_err(),
        ResponseError::NoInformation
    );
    let times: Vec<f64> = (0..=MAX_EXPOSURES).map(|k| 2f64.powi(k as i32)).collect();
    assert_eq!(
        recover_response(&[], &times, 50.0).unwrap_err(),
        ResponseError::TooManyExposures(MAX_EXPOSURES + 1)
    );
    let too_many = vec![vec![100u8, 120, 140, 160]; MAX_SAMPLES + 1];
    assert!(matches!(
        recover_response(&too_many, &TIMES_S, 50.0),
        Err(ResponseError::TooManySamples(_))
    ));
}

#[test]
fn each_channel_of_an_image_bracket_is_recovered() {
    // A radiance ramp across the image, each channel at its own level, so the three
    // curves are recovered from different pixels.
    let (w, h) = (96usize, 64usize);
    let radiance = |x: usize, y: usize, c: usize| {
        let t = (x + w * y) as f64 / (w * h) as f64;
        (0.002f64.ln() + t * (6.0f64 / 0.002).ln()).exp() * [1.0, 0.7, 0.45][c]
    };
    let images: Vec<Vec<u8>> = TIMES_S
        .iter()
        .map(|t| {
            (0..w * h)
                .flat_map(|p| {
                    (0..3).map(move |c| {
                        let e = radiance(p % w, p / w, c) * t;
                        (srgb_encode(e.clamp(0.0, 1.0)) * 255.0).round() as u8
                    })
                })
                .collect()
        })
        .collect();
    let refs: Vec<&[u8]> = images.iter().map(Vec::as_slice).collect();
    let curves = recover_rgb_response(&refs, &TIMES_S, 100, 50.0).unwrap();
    for (c, curve) in curves.iter().enumerate() {
        let worst = worst_error(curve, srgb_decode, 16..=240);
        println!("channel {c}: worst error {worst:.4}");
        assert!(worst < 0.05, "channel {c}: {worst}");
    }
    // Images of unequal size are refused.
    let short = &images[1][..30];
    let e =
        recover_rgb_response(&[refs[0], short, refs[2], refs[3]], &TIMES_S, 100, 50.0).unwrap_err();
    assert!(e.to_string().contains("image 1 is 30 bytes"), "{e}");
    let e = recover_rgb_response(&refs[..2], &TIMES_S, 100, 50.0).unwrap_err();
    assert!(
        e.to_string().contains("2 images for 4 exposure times"),
        "{e}"
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 8, ..ProptestConfig::default() })]

    /// Any gamma curve is recovered, and the curve is always finite.
    #[test]
    fn gamma_curves_are_recovered(gamma in 1.5f64..3.0, n in 50usize..90) {
        let samples = bracket(&radiances(n), |x| x.powf(1.0 / gamma));
        let curve = recover_response(&samples, &TIMES_S, 50.0).unwrap();
        prop_assert!(curve.log_exposure.iter().all(|g| g.is_finite()));
        let worst = worst_error(&curve, |v| v.powf(gamma), 24..=240);
        prop_assert!(worst < 0.06, "gamma {gamma}: {worst}");
    }
}
