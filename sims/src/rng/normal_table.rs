//! Table-driven standard normal numbers for per-pixel noise: one 32-bit uniform per
//! number, no rejection loop in the body, so a pixel's three sensor-noise numbers cost
//! two hashes and three table lookups.
//!
//! Method: the unit interval is cut into [`SEGMENTS`] segments of equal probability.
//! The top 12 bits of the uniform pick a segment, the other 20 place the number
//! linearly between the segment's quantiles `Φ⁻¹(i / 4096)` and `Φ⁻¹((i + 1) / 4096)`.
//! Every segment thus carries exactly its probability; only the density's shape inside
//! a segment is flattened, which moves the CDF by less than 2e-5 anywhere
//! (`tests::cdf_stays_within_its_bound`). The two outermost segments, beyond
//! `|z| = 3.49`, are the normal tail itself, sampled exactly by Marsaglia's (1964)
//! method, so the extremes are not cut off.

use std::sync::OnceLock;

/// Equal-probability segments of the table.
pub const SEGMENTS: usize = 4096;
const SEGMENT_BITS: u32 = 12;
const FRACTION_BITS: u32 = 32 - SEGMENT_BITS;

/// The quantiles `Φ⁻¹(i / SEGMENTS)` for `i = 0..=SEGMENTS`; the two ends (±∞) are
/// never read and hold the neighbouring finite value.
pub struct NormalTable {
    quantile: [f32; SEGMENTS + 1],
    /// `-quantile[1]`: where the exactly sampled tails start.
    tail_start: f64,
}

/// The standard normal CDF, from `erfc` (accurate to a few ulps everywhere).
pub fn normal_cdf(z: f64) -> f64 {
    0.5 * libm::erfc(-z * std::f64::consts::FRAC_1_SQRT_2)
}

fn normal_density(z: f64) -> f64 {
    (-0.5 * z * z).exp()
        * (0.5 * std::f64::consts::FRAC_2_SQRT_PI * std::f64::consts::FRAC_1_SQRT_2)
}

/// `Φ⁻¹(p)` for `p` in (0, 0.5], by Newton's method from `start` (the previous,
/// nearby quantile), falling back to bisection on [-40, 0] if a step leaves it.
fn lower_quantile(p: f64, start: f64) -> f64 {
    let (mut lo, mut hi) = (-40.0f64, 0.0f64);
    let mut z = start.clamp(lo, hi);
    for _ in 0..100 {
        let g = normal_cdf(z) - p;
        if g == 0.0 {
            break;
        }
        if g < 0.0 {
            lo = z;
        } else {
            hi = z;
        }
        let slope = normal_density(z);
        let next = if slope > 0.0 { z - g / slope } else { f64::NAN };
        let next = if next > lo && next < hi {
            next
        } else {
            0.5 * (lo + hi)
        };
        if (next - z).abs() <= 1e-15 * (1.0 + z.abs()) {
            z = next;
            break;
        }
        z = next;
    }
    z
}

/// The table, computed once (in f64, deterministically, symmetric by construction).
pub fn normal_table() -> &'static NormalTable {
    static TABLE: OnceLock<NormalTable> = OnceLock::new();
    TABLE.get_or_init(|| {
        let mut quantile = [0.0f32; SEGMENTS + 1];
        let half = SEGMENTS / 2;
        let mut z = 0.0;
        // From the middle outwards, each Newton solve starting at its neighbour.
        for i in (1..half).rev() {
            z = lower_quantile(i as f64 / SEGMENTS as f64, z);
            quantile[i] = z as f32;
            quantile[SEGMENTS - i] = -z as f32;
        }
        quantile[0] = quantile[1];
        quantile[SEGMENTS] = quantile[SEGMENTS - 1];
        let tail_start = -f64::from(quantile[1]);
        NormalTable {
            quantile,
            tail_start,
        }
    })
}

impl NormalTable {
    /// The standard normal number of the uniform `u`; `tail` draws an exact tail
    /// number beyond its argument (used for 2 in 4096 inputs).
    #[inline]
    pub fn sample(&self, u: u32, tail: impl FnOnce(f64) -> f64) -> f32 {
        let segment = (u >> FRACTION_BITS) as usize;
        if segment == 0 {
            return -tail(self.tail_start) as f32;
        }
        if segment == SEGMENTS - 1 {
            return tail(self.tail_start) as f32;
        }
        let fraction = ((u & ((1 << FRACTION_BITS) - 1)) as f32 + 0.5)
            * (1.0 / (1u32 << FRACTION_BITS) as f32);
        match (self.quantile.get(segment), self.quantile.get(segment + 1)) {
            (Some(&a), Some(&b)) => a + (b - a) * fraction,
            _ => 0.0,
        }
    }

    /// Where the exact tails start (`Φ⁻¹(1 − 1/4096)` ≈ 3.49).
    pub fn tail_start(&self) -> f64 {
        self.tail_start
    }

    /// The quantile at the start of segment `i` (for tests).
    pub fn quantile(&self, i: usize) -> f32 {
        self.quantile.get(i).copied().unwrap_or(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_invert_the_cdf() {
        let t = normal_table();
        for i in 1..SEGMENTS {
            let p = i as f64 / SEGMENTS as f64;
            let z = f64::from(t.quantile(i));
            // f32 quantiles: the CDF at the stored value is within the density times
            // half an f32 ulp of z of the exact probability.
            let tolerance = normal_density(z) * (z.abs() * 6.0e-8 + 1e-12) + 1e-15;
            assert!((normal_cdf(z) - p).abs() <= tolerance, "{i}: {z}");
        }
        assert!((t.tail_start() - 3.4871).abs() < 1e-3, "{}", t.tail_start());
        assert_eq!(t.quantile(SEGMENTS / 2), 0.0);
    }

    /// The sampler's CDF against Φ: at every segment's inside, the piecewise-linear
    /// CDF of the sampler (exact at the knots) differs from Φ by at most 2e-5.
    #[test]
    fn cdf_stays_within_its_bound() {
        let t = normal_table();
        let mut worst = 0.0f64;
        for i in 1..SEGMENTS - 1 {
            let (a, b) = (f64::from(t.quantile(i)), f64::from(t.quantile(i + 1)));
            for k in 1..16 {
                let z = a + (b - a) * f64::from(k) / 16.0;
                let sampler = (i as f64 + f64::from(k) / 16.0) / SEGMENTS as f64;
                worst = worst.max((sampler - normal_cdf(z)).abs());
            }
        }
        assert!(worst < 2e-5, "{worst}");
    }

    #[test]
    fn the_ends_of_the_uniform_go_to_the_tails_and_the_middle_to_zero() {
        let t = normal_table();
        assert_eq!(t.sample(0, |r| r + 1.0), -(t.tail_start() + 1.0) as f32);
        assert_eq!(
            t.sample(u32::MAX, |r| r + 1.0),
            (t.tail_start() + 1.0) as f32
        );
        let middle = t.sample(1 << 31, |_| f64::NAN);
        assert!(middle.abs() < 1e-3, "{middle}");
        // Monotone in u over the body.
        let mut last = f32::NEG_INFINITY;
        for u in (1u32 << FRACTION_BITS..(SEGMENTS as u32 - 1) << FRACTION_BITS).step_by(4099) {
            let z = t.sample(u, |_| f64::NAN);
            assert!(z >= last, "{u}");
            last = z;
        }
    }
}
