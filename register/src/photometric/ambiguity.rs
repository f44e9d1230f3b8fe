//! Whether a photometric fix is unique: the photometric cost sampled along the
//! direction it constrained, on both sides of the estimate. A periodic texture
//! (bricks, tiles, railings) whose period is shorter than the motion's uncertainty
//! has a second minimum as deep as the one found: the image cannot tell which
//! period the camera moved by, and the direction must keep the prior's uncertainty
//! rather than a confident wrong pose.

/// A rival minimum counts when its cost rises above the estimate's by less than
/// this fraction of the profile's typical rise (its median over the estimate's).
const RIVAL_FRACTION: f64 = 0.35;
/// ... and is a separate valley: between it and the estimate the cost rises by at
/// least this fraction of the typical rise (noise in one broad valley is no rival).
const BARRIER_FRACTION: f64 = 0.6;
/// Samples on each side of the estimate.
pub const SIDE_SAMPLES: usize = 24;

/// The outcome of the check along one direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Verdict {
    /// One clear minimum at the estimate.
    Unique,
    /// Another minimum, `offset_m` away (scaled coordinates), is as plausible.
    Rival { offset_m: f64 },
    /// The profile has no contrast (or too few samples): nothing to tell positions
    /// apart.
    Flat,
}

/// Judges a cost profile: `costs[i]` at `offsets_m[i]`, the estimate at offset 0 in
/// the middle; non-finite costs are samples without data and break no tie.
pub fn judge(offsets_m: &[f64], costs: &[f64]) -> Verdict {
    let n = costs.len().min(offsets_m.len());
    if n < 5 {
        return Verdict::Flat;
    }
    let centre = n / 2;
    let c0 = costs[centre];
    let mut finite: Vec<f64> = costs[..n]
        .iter()
        .copied()
        .filter(|c| c.is_finite())
        .collect();
    if !c0.is_finite() || finite.len() < 5 {
        return Verdict::Flat;
    }
    let mid = finite.len() / 2;
    let (_, reference, _) = finite.select_nth_unstable_by(mid, f64::total_cmp);
    let depth = *reference - c0;
    if !(depth > 1.0e-9 * reference.abs().max(1.0e-12)) {
        return Verdict::Flat;
    }
    let mut best: Option<(f64, f64)> = None;
    for k in 1..n - 1 {
        if k.abs_diff(centre) < 2 {
            continue;
        }
        let (before, here, after) = (costs[k - 1], costs[k], costs[k + 1]);
        if !here.is_finite() {
            continue;
        }
        // A local minimum (a missing neighbour does not disqualify it).
        let lower = |x: f64| !x.is_finite() || here <= x;
        if !(lower(before) && lower(after)) {
            continue;
        }
        let rise = here - c0;
        let (lo, hi) = (k.min(centre), k.max(centre));
        let barrier = costs[lo..=hi]
            .iter()
            .copied()
            .filter(|c| c.is_finite())
            .fold(f64::NEG_INFINITY, f64::max);
        if barrier - c0 < BARRIER_FRACTION * depth {
            continue;
        }
        if rise < RIVAL_FRACTION * depth && best.is_none_or(|(r, _)| rise < r) {
            best = Some((rise, offsets_m[k]));
        }
    }
    match best {
        Some((_, offset_m)) => Verdict::Rival { offset_m },
        None => Verdict::Unique,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn offsets() -> Vec<f64> {
        (0..=2 * SIDE_SAMPLES)
            .map(|i| (i as f64 - SIDE_SAMPLES as f64) * 0.02)
            .collect()
    }

    #[test]
    fn a_single_valley_is_unique() {
        let o = offsets();
        let costs: Vec<f64> = o
            .iter()
            .map(|x| 1.0 - (-(x * x) / 0.002).exp() + 0.02 * (40.0 * x).sin().abs())
            .collect();
        assert_eq!(judge(&o, &costs), Verdict::Unique);
    }

    #[test]
    fn a_periodic_profile_has_a_rival() {
        let o = offsets();
        // Period 0.12 m: minima at 0, ±0.12, ±0.24.
        let costs: Vec<f64> = o
            .iter()
            .map(|x| 1.0 - (std::f64::consts::TAU * x / 0.12).cos() + 0.05 * x.abs())
            .collect();
        match judge(&o, &costs) {
            Verdict::Rival { offset_m } => assert!((offset_m.abs() - 0.12).abs() < 0.021),
            v => panic!("{v:?}"),
        }
    }

    #[test]
    fn flat_or_empty_profiles_are_flat() {
        let o = offsets();
        assert_eq!(judge(&o, &vec![0.3; o.len()]), Verdict::Flat);
        assert_eq!(judge(&o, &vec![f64::NAN; o.len()]), Verdict::Flat);
        assert_eq!(judge(&[], &[]), Verdict::Flat);
    }
}
