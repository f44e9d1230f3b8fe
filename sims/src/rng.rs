//! Counter-based randomness: every random number is a pure function of
//! `(seed, frame index, pixel, stream, draw)`, so a frame's noise never depends on the
//! thread count, on scheduling, or on which frames were rendered before.
//!
//! The mixer is SplitMix64's finaliser (Steele, Lea & Flood 2014), applied once per
//! key component; it passes BigCrush as a stream generator and is cheap enough to call
//! per pixel.

/// Independent random streams: each effect draws from its own, so adding an effect to
/// a scene does not change the noise of the others.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u64)]
pub enum Stream {
    RangeNoise = 1,
    Dropouts = 2,
    SensorNoise = 3,
    MixedPixels = 4,
    Trajectory = 5,
    Texture = 6,
}

const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// SplitMix64's output function: a bijective 64-bit mixer.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The key of one pixel's random numbers in one frame and stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelRng {
    key: u64,
}

impl PixelRng {
    #[inline]
    pub fn new(seed: u64, frame: u64, pixel: u64, stream: Stream) -> Self {
        let mut k = mix64(seed ^ GOLDEN);
        k = mix64(k ^ frame.wrapping_mul(GOLDEN));
        k = mix64(k ^ (stream as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93));
        k = mix64(k ^ pixel.wrapping_mul(0xA076_1D64_78BD_642F));
        Self { key: k }
    }

    /// The `draw`-th 64-bit value of this pixel's sequence.
    #[inline]
    pub fn bits(&self, draw: u64) -> u64 {
        mix64(
            self.key
                .wrapping_add(draw.wrapping_add(1).wrapping_mul(GOLDEN)),
        )
    }

    /// A uniform number in [0, 1) with 53 random bits.
    #[inline]
    pub fn uniform(&self, draw: u64) -> f64 {
        (self.bits(draw) >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// A uniform number in (0, 1]: safe to take the logarithm of.
    #[inline]
    pub fn uniform_open0(&self, draw: u64) -> f64 {
        ((self.bits(draw) >> 11) as f64 + 1.0) * (1.0 / (1u64 << 53) as f64)
    }

    /// Two independent standard normal numbers (Box-Muller) from draws `2k`, `2k + 1`.
    #[inline]
    pub fn normal_pair(&self, k: u64) -> (f64, f64) {
        let u1 = self.uniform_open0(2 * k);
        let u2 = self.uniform(2 * k + 1);
        // u1 in (0, 1], so ln(u1) <= 0 and finite.
        let radius = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (std::f64::consts::TAU * u2).sin_cos();
        (radius * c, radius * s)
    }

    /// One standard normal number.
    #[inline]
    pub fn normal(&self, k: u64) -> f64 {
        self.normal_pair(k).0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_differ_per_component_and_repeat_exactly() {
        let a = PixelRng::new(1, 2, 3, Stream::RangeNoise);
        assert_eq!(a, PixelRng::new(1, 2, 3, Stream::RangeNoise));
        assert_ne!(a, PixelRng::new(2, 2, 3, Stream::RangeNoise));
        assert_ne!(a, PixelRng::new(1, 3, 3, Stream::RangeNoise));
        assert_ne!(a, PixelRng::new(1, 2, 4, Stream::RangeNoise));
        assert_ne!(a, PixelRng::new(1, 2, 3, Stream::Dropouts));
    }

    #[test]
    fn normals_have_unit_variance() {
        let n = 200_000;
        let (mut sum, mut sum2) = (0.0, 0.0);
        for p in 0..n {
            let x = PixelRng::new(9, 0, p, Stream::SensorNoise).normal(0);
            sum += x;
            sum2 += x * x;
        }
        let mean = sum / n as f64;
        let var = sum2 / n as f64 - mean * mean;
        // Standard errors: 1/sqrt(n) = 0.0022 for the mean, sqrt(2/n) = 0.0032 for var.
        assert!(mean.abs() < 0.012, "{mean}");
        assert!((var - 1.0).abs() < 0.016, "{var}");
    }
}
