//! Exposure brackets: frames cycle through the bracket, each records the exposure it
//! was taken with, and its pixels are the radiance truth scaled by that exposure,
//! clipped and encoded; scenes that do not list `exposure` record none.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use common::load;
use sims::{Effect, SimOptions, Simulator};
use texel::capture::{TexelItem, open_texel_frames};

fn effect(name: &str, params: &str) -> Effect {
    let table: toml::Table = toml::from_str(params).unwrap();
    Effect::from_name_and_params(name, table).unwrap()
}

fn hdr_sim(effects: Vec<Effect>, frames: usize) -> Simulator {
    Simulator::with_options(
        load("courtyard-hdr"),
        &SimOptions {
            seed: 3,
            frames: Some(frames),
            effects: Some(effects),
            lidar_size: Some([16, 16]),
            eo_size: Some([80, 60]),
            ..SimOptions::default()
        },
    )
    .unwrap()
}

#[test]
fn bracketed_frames_are_the_radiance_truth_scaled_by_their_recorded_exposure() {
    let bracket = effect(
        "exposure",
        "ev = -1.0\nresponse = \"linear\"\nbracket_ev = [-2.0, 0.0, 2.0]\nexposure_time_s = 0.008",
    );
    let sim = hdr_sim(vec![bracket], 6);
    let (mut saturated, mut dark) = (0usize, 0usize);
    for i in 0..6 {
        let frame = sim.frame(i).unwrap();
        let exposure = frame
            .pair
            .eo
            .exposure
            .expect("a bracketed frame's exposure");
        let ev = -1.0 + [-2.0, 0.0, 2.0][i % 3];
        assert!(
            (exposure.exposure_time_s - 0.008 * 2f64.powf(ev)).abs() < 1e-15,
            "frame {i}: {exposure:?}"
        );
        assert_eq!(exposure.gain, 1.0);
        let truth = sim.clean_radiance_at(&frame.world_from_eo);
        let scale = exposure.scale() / 0.008;
        for (k, l) in truth.iter().enumerate() {
            for (c, value) in l.iter().enumerate() {
                let want = (255.0 * (f64::from(*value) * scale).min(1.0)).round();
                let got = f64::from(frame.pair.eo.rgb[3 * k + c]);
                assert!(
                    (got - want).abs() <= 1.0,
                    "frame {i} pixel {k} channel {c}: {got} vs {want} (radiance {value})"
                );
                saturated += usize::from(got >= 255.0);
                dark += usize::from(got <= 2.0);
            }
        }
    }
    // The scene's range is real: some of its values saturate and some are near black.
    assert!(
        saturated > 0 && dark > 0,
        "{saturated} saturated, {dark} dark"
    );
}

#[test]
fn without_the_effect_or_a_bracket_frames_say_what_they_were_exposed_with() {
    // No `exposure` effect: pixels are colours, no exposure is recorded.
    let sim = hdr_sim(vec![], 2);
    assert_eq!(sim.frame(1).unwrap().pair.eo.exposure, None);
    assert_eq!(
        sim.clean_eo_at(&sim.true_pose(0), 0).exposure,
        None,
        "the clean image has no exposure"
    );
    // The effect without a bracket: every frame at `ev`.
    let sim = hdr_sim(vec![effect("exposure", "ev = 1.0")], 3);
    for i in 0..3 {
        let e = sim.frame(i).unwrap().pair.eo.exposure.unwrap();
        assert_eq!(e.exposure_time_s, 0.02, "frame {i}");
    }
}

#[test]
fn bad_brackets_are_refused_by_name() {
    for (params, needle) in [
        ("bracket_ev = [0.0, 11.0]", "bracket_ev[1] = 11"),
        (
            "ev = 15.0\nbracket_ev = [0.0, 8.0]",
            "ev + bracket_ev[1] = 23",
        ),
        ("exposure_time_s = 0.0", "exposure_time_s = 0"),
        (
            "bracket_ev = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]",
            "17 exposures",
        ),
    ] {
        let table: toml::Table = toml::from_str(params).unwrap();
        let e = Effect::from_name_and_params("exposure", table).unwrap_err();
        assert!(e.contains(needle), "{params}: {e}");
    }
}

#[test]
fn a_bracketed_capture_records_every_frames_exposure() {
    let sim = hdr_sim(vec![effect("exposure", "bracket_ev = [-2.0, 0.0, 2.0]")], 4);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("hdr.mcap");
    sims::render_capture(
        &sim,
        &path,
        &sims::CaptureOptions::default(),
        &mut |_, _| {},
    )
    .unwrap();
    let mut times = Vec::new();
    for item in open_texel_frames(&path).unwrap() {
        if let TexelItem::Pair { pair, .. } = item.unwrap() {
            times.push(pair.eo.exposure.unwrap().exposure_time_s);
        }
    }
    let base = 0.01 * 2f64.powf(0.5);
    let want: Vec<f64> = [-2.0, 0.0, 2.0, -2.0]
        .iter()
        .map(|b: &f64| base * 2f64.powf(*b))
        .collect();
    assert_eq!(times.len(), 4);
    for (t, w) in times.iter().zip(&want) {
        assert!((t - w).abs() < 1e-15, "{t} vs {w}");
    }
}

#[test]
fn a_bracket_merged_with_the_true_response_recovers_the_radiance_truth() {
    use texel::radiance::merge_exposures;
    let sim = hdr_sim(
        vec![
            effect("exposure", "ev = -0.5\nbracket_ev = [-2.0, 0.0, 2.0]"),
            effect("sensor_noise", ""),
        ],
        3,
    );
    let pose = sim.true_pose(1);
    // The bracket at one pose: noise frames 0, 1, 2 take the bracket's three places.
    let frames: Vec<texel::EoFrame> = (0..3).map(|k| sim.render_at(&pose, k, 0).eo).collect();
    let response = sim
        .effects()
        .exposure
        .as_ref()
        .unwrap()
        .true_response()
        .unwrap();
    let refs: Vec<&texel::EoFrame> = frames.iter().collect();
    let merged = merge_exposures(&refs, &response).unwrap();
    let truth = sim.clean_radiance_at(&pose);
    let mut errors = Vec::new();
    for ((got, w), want) in merged.rgb.iter().zip(&merged.weight).zip(&truth) {
        for c in 0..3 {
            assert!(got[c].is_finite() && got[c] >= 0.0);
            if w[c] > 0.0 && want[c] > 0.0 {
                errors.push((f64::from(got[c]) / f64::from(want[c])).ln().abs());
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    let p95 = errors[errors.len() * 95 / 100];
    eprintln!(
        "merged: median ln error {median:.4}, p95 {p95:.4}, {:.4} unmeasured",
        merged.unmeasured_share()
    );
    for f in &frames {
        let single = merge_exposures(&[f], &response).unwrap();
        eprintln!(
            "single {:?}: {:.4} unmeasured",
            f.exposure,
            single.unmeasured_share()
        );
        assert!(single.unmeasured_share() >= merged.unmeasured_share());
    }
    assert!(median < 0.03 && p95 < 0.12, "median {median}, p95 {p95}");
}
