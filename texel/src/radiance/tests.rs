//! The merge's degenerate cases and its recovery of known radiance.

use proptest::prelude::*;

use super::*;
use crate::frames::EoExposure;

fn frame(values: &[[u8; 3]], exposure_time_s: f64, gain: f64) -> EoFrame {
    EoFrame {
        width: values.len() as u32,
        height: 1,
        rgb: values.iter().flatten().copied().collect(),
        timestamp_ns: 1,
        exposure: Some(EoExposure {
            exposure_time_s,
            gain,
        }),
    }
}

/// A camera whose response is `z = 255 · min(1, E·Δt)^(1/2.2)`, rounded.
fn gamma_response() -> EoResponse {
    EoResponse::from_linear(|v| v.powf(2.2))
}

fn expose(radiance: f64, scale: f64) -> u8 {
    (255.0 * (radiance * scale).clamp(0.0, 1.0).powf(1.0 / 2.2)).round() as u8
}

#[test]
fn all_saturated_gives_the_bound_of_the_shortest_exposure() {
    let r = gamma_response();
    let a = frame(&[[255; 3]], 0.01, 1.0);
    let b = frame(&[[255; 3]], 0.002, 2.0);
    let m = merge_exposures(&[&a, &b], &r).unwrap();
    // Saturation (g(255) = ln 1 = 0) at the smaller scale 0.004: at least 250.
    for c in 0..3 {
        assert!((f64::from(m.rgb[0][c]) - 250.0).abs() < 1e-3, "{:?}", m.rgb);
        assert_eq!(m.weight[0][c], 0.0);
    }
    assert_eq!(m.unmeasured_share(), 1.0);
}

#[test]
fn all_black_gives_zero_without_a_log_of_zero() {
    let r = gamma_response();
    let a = frame(&[[0; 3], [0, 0, 0]], 0.01, 1.0);
    let b = frame(&[[0; 3], [0, 0, 0]], 0.04, 1.0);
    let m = merge_exposures(&[&a, &b], &r).unwrap();
    assert_eq!(m.rgb, vec![[0.0; 3]; 2]);
    assert_eq!(m.weight, vec![[0.0; 3]; 2]);
}

#[test]
fn a_single_exposure_is_its_own_radiance_where_it_measured() {
    let r = gamma_response();
    let radiance = [3.0, 20.0, 60.0];
    let z = radiance.map(|e| expose(e, 0.01));
    let m = merge_exposures(&[&frame(&[z], 0.01, 1.0)], &r).unwrap();
    for c in 0..3 {
        let got = f64::from(m.rgb[0][c]);
        // One 8-bit step of the gamma curve is about 2.2/z of the value.
        let tolerance = 2.2 / f64::from(z[c]) * radiance[c];
        assert!((got - radiance[c]).abs() < tolerance, "{c}: {got}");
        assert_eq!(f64::from(m.weight[0][c]), hat_weight(z[c]));
    }
}

#[test]
fn equal_exposure_times_average_in_log() {
    let r = gamma_response();
    let a = frame(&[[100; 3]], 0.01, 1.0);
    let b = frame(&[[110; 3]], 0.01, 1.0);
    let m = merge_exposures(&[&a, &b], &r).unwrap();
    let (wa, wb) = (hat_weight(100), hat_weight(110));
    let want = ((wa * (r.log_exposure(0, 100) - 0.01f64.ln())
        + wb * (r.log_exposure(0, 110) - 0.01f64.ln()))
        / (wa + wb))
        .exp();
    assert!((f64::from(m.rgb[0][0]) / want - 1.0).abs() < 1e-6);
    assert_eq!(f64::from(m.weight[0][0]), wa + wb);
}

#[test]
fn a_bracket_recovers_radiance_over_a_range_no_exposure_holds() {
    let r = gamma_response();
    let scales = [0.0025, 0.01, 0.04];
    // Twelve stops of radiance, 0.05 to 200.
    let radiances: Vec<f64> = (0..=48).map(|i| 0.05 * 2f64.powf(i as f64 / 4.0)).collect();
    let frames: Vec<EoFrame> = scales
        .iter()
        .map(|&s| {
            let values: Vec<[u8; 3]> = radiances.iter().map(|&e| [expose(e, s); 3]).collect();
            frame(&values, s, 1.0)
        })
        .collect();
    let refs: Vec<&EoFrame> = frames.iter().collect();
    let m = merge_exposures(&refs, &r).unwrap();
    let mut errors: Vec<f64> = m
        .rgb
        .iter()
        .zip(&radiances)
        .map(|(got, want)| (f64::from(got[1]) / want).ln().abs())
        .collect();
    // The darkest values are a few 8-bit steps in every exposure: their error is
    // that quantisation's; the median is far below it.
    errors.sort_by(f64::total_cmp);
    assert!(errors[errors.len() - 1] < 0.1, "{errors:?}");
    assert!(errors[errors.len() / 2] < 0.01, "{errors:?}");
    // The longest exposure alone saturates a quarter of that range; merged, nothing is
    // unmeasured.
    let single = merge_exposures(&[&frames[2]], &r).unwrap();
    assert!(
        single.unmeasured_share() > 0.25,
        "{}",
        single.unmeasured_share()
    );
    assert_eq!(m.unmeasured_share(), 0.0);
}

#[test]
fn bad_brackets_are_named() {
    let r = EoResponse::srgb();
    let good = frame(&[[9; 3]], 0.01, 1.0);
    assert_eq!(merge_exposures(&[], &r).unwrap_err(), MergeError::Empty);
    let mut none = good.clone();
    none.exposure = None;
    let e = merge_exposures(&[&good, &none], &r).unwrap_err();
    assert!(e.to_string().contains("EO frame 1"), "{e}");
    let mut bad = good.clone();
    bad.exposure = Some(EoExposure {
        exposure_time_s: 0.0,
        gain: 1.0,
    });
    let e = merge_exposures(&[&bad], &r).unwrap_err();
    assert!(e.to_string().contains("exposure_time_s 0"), "{e}");
    let wide = frame(&[[9; 3], [9; 3]], 0.01, 1.0);
    let e = merge_exposures(&[&good, &wide], &r).unwrap_err();
    assert!(e.to_string().contains("is 2x1, the first is 1x1"), "{e}");
    let mut short = good.clone();
    short.rgb.pop();
    let e = merge_exposures(&[&short], &r).unwrap_err();
    assert!(e.to_string().contains("2 bytes"), "{e}");
    let many: Vec<&EoFrame> = std::iter::repeat_n(&good, 33).collect();
    assert!(matches!(
        merge_exposures(&many, &r),
        Err(MergeError::TooMany { count: 33 })
    ));
}

#[test]
fn curves_are_checked_and_round_trip_through_json() {
    let srgb = EoResponse::srgb();
    let json = serde_json::to_string(&srgb).unwrap();
    let back: EoResponse = serde_json::from_str(&json).unwrap();
    assert_eq!(back, srgb);
    // sRGB: value 255 is exposure 1, value 0 takes value 1's log.
    assert!(srgb.log_exposure(1, 255).abs() < 1e-12);
    assert_eq!(srgb.log_exposure(2, 0), srgb.log_exposure(2, 1));
    let short = vec![0.0; 10];
    let flat = vec![0.0; LEVELS];
    let e = EoResponse::new([flat.clone(), short, flat.clone()]).unwrap_err();
    assert!(e.to_string().contains("eo_response.g has 10 values"), "{e}");
    let mut nan = flat.clone();
    nan[7] = f64::NAN;
    let e = EoResponse::new([flat.clone(), flat.clone(), nan]).unwrap_err();
    assert!(e.to_string().contains("eo_response.b[7]"), "{e}");
    let falling: Vec<f64> = (0..LEVELS).map(|z| -(z as f64)).collect();
    let e = EoResponse::new([falling, flat.clone(), flat]).unwrap_err();
    assert!(e.to_string().contains("never decreases"), "{e}");
}

proptest! {
    /// Any values and any valid exposures merge into finite, non-negative radiance;
    /// a value measured in some exposure lies between what the darkest and the
    /// brightest of its measurements say.
    #[test]
    fn radiance_is_finite_non_negative_and_between_its_measurements(
        values in prop::collection::vec(any::<u8>(), 1..6),
        log2_scales in prop::collection::vec(-30.0f64..20.0, 6),
        gains in prop::collection::vec(0.01f64..1000.0, 6),
    ) {
        let r = EoResponse::srgb();
        let frames: Vec<EoFrame> = values
            .iter()
            .zip(&log2_scales)
            .zip(&gains)
            .map(|((&z, &l), &g)| frame(&[[z, 255 - z, z / 2]], 2f64.powf(l).min(3600.0), g))
            .collect();
        let refs: Vec<&EoFrame> = frames.iter().collect();
        let m = merge_exposures(&refs, &r).unwrap();
        for c in 0..3 {
            let e = m.rgb[0][c];
            prop_assert!(e.is_finite() && e >= 0.0, "{e}");
            let single: Vec<f64> = frames
                .iter()
                .filter(|f| hat_weight(f.rgb[c]) > 0.0)
                .map(|f| f64::from(merge_exposures(&[f], &r).unwrap().rgb[0][c]))
                .collect();
            if let (Some(lo), Some(hi)) = (
                single.iter().copied().reduce(f64::min),
                single.iter().copied().reduce(f64::max),
            ) {
                let e = f64::from(e);
                prop_assert!(e >= lo * (1.0 - 1e-5) && e <= hi * (1.0 + 1e-5), "{lo} {e} {hi}");
            }
        }
    }
}

proptest! {
    /// The one-exposure table gives exactly what the general rule gives.
    #[test]
    fn the_single_exposure_table_is_the_general_rule(
        values in prop::collection::vec(any::<u8>(), 3..30),
        log2_scale in -20.0f64..10.0,
    ) {
        let r = EoResponse::srgb();
        let n = values.len() / 3;
        let pixels: Vec<[u8; 3]> = values.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
        let f = frame(&pixels, 2f64.powf(log2_scale), 1.0);
        let fast = merge_exposures(&[&f], &r).unwrap();
        // The general path: the same frame twice at the same exposure merges to the
        // same radiance with twice the weight.
        let slow = merge_exposures(&[&f, &f], &r).unwrap();
        for p in 0..n {
            for c in 0..3 {
                let (a, b) = (fast.rgb[p][c], slow.rgb[p][c]);
                prop_assert!((a - b).abs() <= 1e-6 * a.abs().max(1e-30), "{a} vs {b}");
                prop_assert_eq!(2.0 * fast.weight[p][c], slow.weight[p][c]);
            }
        }
    }
}
