//! Order statistics of measurements: the one definition of a quantile that every
//! report and status figure of the project uses.

/// The `p`-quantile (`p` in 0..=1, clamped; NaN counts as 0) of the finite `values`
/// by the nearest-rank method: the smallest value with at least a fraction `p` of the
/// values at or below it. Non-finite values are left out; 0 when none is left.
pub fn quantile(values: &[f64], p: f64) -> f64 {
    let mut sorted: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    if sorted.is_empty() {
        return 0.0;
    }
    sorted.sort_by(f64::total_cmp);
    let p = if p.is_nan() { 0.0 } else { p.clamp(0.0, 1.0) };
    let rank = (p * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn nearest_rank_on_small_sets() {
        assert_eq!(quantile(&[3.0, 1.0, 2.0], 0.5), 2.0);
        assert_eq!(quantile(&[1.0, 2.0, 3.0, 4.0], 0.5), 2.0);
        assert_eq!(quantile(&[1.0, 2.0, 3.0, 4.0], 0.51), 3.0);
        assert_eq!(quantile(&[7.0], 0.99), 7.0);
        let hundred: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(quantile(&hundred, 0.5), 50.0);
        assert_eq!(quantile(&hundred, 0.99), 99.0);
        assert_eq!(quantile(&hundred, 0.0), 1.0);
        assert_eq!(quantile(&hundred, 1.0), 100.0);
    }

    #[test]
    fn degenerate_inputs() {
        assert_eq!(quantile(&[], 0.5), 0.0);
        assert_eq!(quantile(&[f64::NAN, f64::INFINITY], 0.5), 0.0);
        assert_eq!(quantile(&[1.0, f64::NAN, 5.0], 1.0), 5.0);
        assert_eq!(quantile(&[1.0, 5.0], f64::NAN), 1.0);
        assert_eq!(quantile(&[1.0, 5.0], -3.0), 1.0);
        assert_eq!(quantile(&[1.0, 5.0], 7.0), 5.0);
    }

    proptest! {
        #[test]
        fn a_quantile_is_a_member_with_the_right_share_below(
            values in proptest::collection::vec(-1e6f64..1e6, 1..60),
            p in 0.0f64..=1.0,
        ) {
            let q = quantile(&values, p);
            prop_assert!(values.contains(&q));
            let at_or_below = values.iter().filter(|&&v| v <= q).count() as f64;
            let below = values.iter().filter(|&&v| v < q).count() as f64;
            let n = values.len() as f64;
            prop_assert!(at_or_below >= p * n - 1e-9);
            prop_assert!(below < (p * n).max(1.0) + 1e-9);
        }
    }
}
