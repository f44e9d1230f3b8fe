//! The controller against a synthetic cost model, and the pacer's decisions.

use proptest::prelude::*;

use super::*;

/// Frame time of a frame at `scale` under the cost model `a + b s²` ms.
fn cost(a: f64, b: f64, scale: f64) -> f64 {
    a + b * scale * scale
}

/// Runs the controller for `steps` frames; returns the last scale and frame time.
fn run(c: &mut ScaleController, a: f64, b: f64, steps: usize) -> (f64, f64) {
    let mut t = cost(a, b, c.scale());
    for _ in 0..steps {
        c.observe(t);
        t = cost(a, b, c.scale());
    }
    (c.scale(), t)
}

#[test]
fn converges_to_the_target_on_a_software_rasteriser_cost() {
    // About lavapipe at 1280x800: 12 ms fixed, 600 ms for every pixel.
    let mut c = ScaleController::new(66.0);
    let target = c.target_ms();
    assert!(target < 66.0);
    let (scale, t) = run(&mut c, 12.0, 600.0, 30);
    assert!(
        (t - target).abs() < 0.02 * target,
        "{t} ms at scale {scale}"
    );
    let expected = ((target - 12.0) / 600.0_f64).sqrt();
    assert!(
        (scale - expected).abs() < 0.01,
        "{scale} against {expected}"
    );
}

#[test]
fn a_cheap_frame_goes_to_full_resolution_and_an_impossible_one_to_the_floor() {
    let mut c = ScaleController::new(66.0);
    assert_eq!(run(&mut c, 2.0, 20.0, 30).0, 1.0);
    let mut c = ScaleController::new(66.0);
    // The fixed part alone is over budget: the smallest frame is the best it can do.
    assert_eq!(run(&mut c, 80.0, 600.0, 60).0, c.min_scale);
}

#[test]
fn one_slow_frame_does_not_move_the_scale() {
    let mut c = ScaleController::new(66.0);
    run(&mut c, 12.0, 600.0, 30);
    let before = c.scale();
    c.observe(2000.0);
    assert!((c.scale() - before).abs() < 0.01 * before);
}

#[test]
fn non_finite_times_are_ignored() {
    let mut c = ScaleController::new(66.0);
    let s = c.scale();
    assert_eq!(c.observe(f64::NAN), s);
    assert_eq!(c.observe(f64::INFINITY), s);
    assert_eq!(c.observe(-1.0), s);
    assert!(ScaleController::new(f64::NAN).budget_ms().is_finite());
    assert!(c.observe(0.0).is_finite());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// With any fixed part up to 60 % of the target (the budget less its headroom) and ±5 % noise on every
    /// measurement: the frame time ends within 8 % of the target where a scale in range
    /// reaches it, else the scale ends at the bound nearest to it.
    #[test]
    fn converges_on_any_affine_cost(
        a_share in 0.0f64..0.6,
        b in 1.0f64..5000.0,
        budget in 20.0f64..200.0,
        noise_seed in 0u64..1000,
    ) {
        let mut c = ScaleController::new(budget);
        // The fixed part (overlay, upscale, present) is at most 60 % of the target.
        let target = c.target_ms();
        let a = a_share * target;
        // A little deterministic noise (±5 %): the machine is shared.
        let mut t = cost(a, b, c.scale());
        let mut x = noise_seed;
        for _ in 0..80 {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let jitter = 1.0 + 0.05 * (((x >> 33) as f64 / (1u64 << 31) as f64) - 0.5) * 2.0;
            c.observe(t * jitter);
            t = cost(a, b, c.scale());
        }
        let low = cost(a, b, c.min_scale);
        let high = cost(a, b, c.max_scale);
        let at_floor = (c.scale() - c.min_scale).abs() < 1e-9;
        let at_top = (c.scale() - c.max_scale).abs() < 1e-9;
        // Within the measurement noise (±5 %) and a little more.
        let near = (t - target).abs() <= 0.08 * target;
        prop_assert!(
            near || (at_floor && low > target) || (at_top && high < target),
            "{} ms for {} ms at scale {}", t, target, c.scale()
        );
        // Clearly out of reach: the bound.
        if target * 1.08 < low {
            prop_assert!(at_floor);
        }
        if target > high * 1.08 {
            prop_assert!(at_top);
        }
    }
}

#[test]
fn scaled_sizes_stay_inside_the_window() {
    assert_eq!(scaled_size(1280, 800, 0.5), (640, 400));
    assert_eq!(scaled_size(1280, 800, 0.0), (1, 1));
    assert_eq!(scaled_size(1280, 800, f64::NAN), (1280, 800));
    assert_eq!(scaled_size(1280, 800, 7.0), (1280, 800));
}

#[test]
fn the_pacer_draws_moves_cheaply_then_refines_once_then_idles() {
    let t0 = Instant::now();
    let ms = |n: u64| t0 + Duration::from_millis(n);
    let mut p = FramePacer::new(true);
    // The first frame: nothing moved yet, so full quality.
    assert_eq!(p.decide(false, t0), Decision::Draw(Quality::Full));
    p.drawn(Quality::Full);
    assert_eq!(p.decide(false, ms(10)), Decision::Idle);
    // A drag: interactive frames.
    assert_eq!(p.decide(true, ms(20)), Decision::Draw(Quality::Interactive));
    p.drawn(Quality::Interactive);
    assert_eq!(p.decide(true, ms(90)), Decision::Draw(Quality::Interactive));
    p.drawn(Quality::Interactive);
    // Released: wait for the settle time, then the full frame once.
    assert_eq!(p.decide(false, ms(100)), Decision::WaitUntil(ms(240)));
    assert_eq!(p.decide(false, ms(240)), Decision::Draw(Quality::Full));
    p.drawn(Quality::Full);
    for n in 0..200 {
        assert_eq!(p.decide(false, ms(250 + 10 * n)), Decision::Idle);
    }
    // Without adaptive quality every change is drawn in full.
    let mut p = FramePacer::new(false);
    assert_eq!(p.decide(true, t0), Decision::Draw(Quality::Full));
}

#[test]
fn interactive_settings_are_cheap_and_keep_diagnostic_modes() {
    let full = RenderSettings::with_mode(Mode::Blended);
    let s = interactive_settings(&full, Mode::Painter);
    assert_eq!((s.composite.mode, s.composite.k), (Mode::Painter, 1));
    let s = interactive_settings(&RenderSettings::with_mode(Mode::ScanColour), Mode::Painter);
    assert_eq!(s.composite.mode, Mode::ScanColour);
}
