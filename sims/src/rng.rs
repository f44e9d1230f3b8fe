//! Counter-based randomness: every random number is a pure function of
//! `(seed, frame index, pixel, stream, draw)`, so a frame's noise never depends on the
//! thread count, on scheduling, or on which frames were rendered before.
//!
//! The mixer is SplitMix64's finaliser (Steele, Lea & Flood 2014), applied once per
//! key component; it passes BigCrush as a stream generator and is cheap enough to call
//! per pixel.
//!
//! Gaussian numbers for the effects come from [`PixelRng::gaussian`], a ziggurat
//! (Marsaglia & Tsang 2000, with Doornik's 2005 independent layer bits): one 64-bit
//! draw and a table lookup for ~99% of the numbers, no logarithm or sine. It samples
//! the normal distribution itself (rejection, not an approximation); its only error is
//! the 32-bit resolution of the uniform it scales. [`PixelRng::normal_pair`]
//! (Box-Muller) stays as the textbook reference the tests compare it with.

use std::sync::OnceLock;

pub mod normal_table;

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

/// The part of [`PixelRng`]'s key shared by every pixel of one frame and stream,
/// computed once per frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRng {
    key: u64,
}

impl FrameRng {
    #[inline]
    pub fn new(seed: u64, frame: u64, stream: Stream) -> Self {
        let mut k = mix64(seed ^ GOLDEN);
        k = mix64(k ^ frame.wrapping_mul(GOLDEN));
        k = mix64(k ^ (stream as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93));
        Self { key: k }
    }

    /// The random numbers of `pixel` (the same as [`PixelRng::new`]).
    #[inline]
    pub fn pixel(&self, pixel: u64) -> PixelRng {
        PixelRng {
            key: mix64(self.key ^ pixel.wrapping_mul(0xA076_1D64_78BD_642F)),
        }
    }
}

/// The key of one pixel's random numbers in one frame and stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelRng {
    key: u64,
}

impl PixelRng {
    #[inline]
    pub fn new(seed: u64, frame: u64, pixel: u64, stream: Stream) -> Self {
        FrameRng::new(seed, frame, stream).pixel(pixel)
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

    /// One standard normal number (Box-Muller).
    #[inline]
    pub fn normal(&self, k: u64) -> f64 {
        self.normal_pair(k).0
    }

    /// The `k`-th standard normal number of this pixel's sequence, by the ziggurat
    /// (see the module documentation). Attempt `a` of number `k` uses draws
    /// `64 k + 2 a` and `64 k + 2 a + 1`; the base layer's tail uses draws from
    /// `64 k + 32` on, so every number is a pure function of the key and `k`. After 16
    /// rejected attempts (probability below 1e-30) it returns 0.
    #[inline]
    pub fn gaussian(&self, k: u64) -> f32 {
        let z = ziggurat();
        let base = k.wrapping_mul(64);
        for attempt in 0..16u64 {
            let bits = self.bits(base + 2 * attempt);
            let layer = (bits & 0xFF) as usize;
            // A uniform in (-1, 1) from the top 32 bits, never 0 or ±1.
            let u = ((bits >> 32) as i32 as f64 + 0.5) * (1.0 / 2_147_483_648.0);
            let (Some(&ratio), Some(&x_outer)) = (z.ratio.get(layer), z.x.get(layer)) else {
                return 0.0;
            };
            if u.abs() < ratio {
                // Inside the layer's rectangle that lies under the curve: ~99%.
                return (u * x_outer) as f32;
            }
            let wedge = self.bits(base + 2 * attempt + 1);
            if layer == 0 {
                return self.gaussian_tail(base + 32, u < 0.0) as f32;
            }
            let x = u * x_outer;
            let x_inner = z.x.get(layer + 1).copied().unwrap_or(0.0);
            let f_outer = (-0.5 * (x_outer * x_outer - x * x)).exp();
            let f_inner = (-0.5 * (x_inner * x_inner - x * x)).exp();
            if f_inner + unit(wedge) * (f_outer - f_inner) < 1.0 {
                return x as f32;
            }
        }
        0.0
    }

    /// A normal number beyond the base layer's edge `R` (Marsaglia 1964), with draws
    /// from `first_draw` on; signed by `negative`.
    fn gaussian_tail(&self, first_draw: u64, negative: bool) -> f64 {
        let x = self.tail_beyond(first_draw, ZIGGURAT_R);
        if negative { -x } else { x }
    }

    /// Three standard normal numbers from the table sampler (`table` is
    /// [`normal_table::normal_table`]): draws 0 and 1 give the three 32-bit uniforms;
    /// a number in a tail (2 in 4096) uses draws from `8 + 32 k` on.
    #[inline]
    pub fn normals3(&self, table: &normal_table::NormalTable) -> [f32; 3] {
        let (a, b) = (self.bits(0), self.bits(1));
        let uniforms = [(a >> 32) as u32, a as u32, (b >> 32) as u32];
        let mut out = [0.0f32; 3];
        for (k, (o, &u)) in out.iter_mut().zip(&uniforms).enumerate() {
            *o = table.sample(u, |r| self.tail_beyond(8 + 32 * k as u64, r));
        }
        out
    }

    /// A normal number conditioned on exceeding `r > 0` (Marsaglia 1964), with draws
    /// from `first_draw` on. After 32 rejected attempts (probability below 1e-30) it
    /// returns `r`.
    fn tail_beyond(&self, first_draw: u64, r: f64) -> f64 {
        for t in 0..32u64 {
            let bits = self.bits(first_draw + t);
            // Two uniforms in (0, 1) from the two halves: safe to take logarithms of.
            let u1 = ((bits >> 32) as f64 + 0.5) * (1.0 / 4_294_967_296.0);
            let u2 = ((bits & 0xFFFF_FFFF) as f64 + 0.5) * (1.0 / 4_294_967_296.0);
            let x = u1.ln() / r;
            let y = u2.ln();
            if -2.0 * y >= x * x {
                return r - x;
            }
        }
        r
    }
}

/// A uniform number in [0, 1) with 53 random bits.
#[inline]
fn unit(bits: u64) -> f64 {
    (bits >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Layers of the ziggurat.
const ZIGGURAT_LAYERS: usize = 256;
/// Right edge of the base layer for 256 layers (Marsaglia & Tsang 2000).
const ZIGGURAT_R: f64 = 3.654_152_885_361_009;
/// Area of every layer (the base layer's includes the tail beyond `R`).
const ZIGGURAT_V: f64 = 4.928_673_233_99e-3;

/// The ziggurat's layer edges `x[i]` (`x[0] = V / f(R)`, the base layer's equivalent
/// width; `x[1] = R`; `x[256] = 0`) and `ratio[i] = x[i + 1] / x[i]`, the part of
/// layer `i` under the curve.
struct Ziggurat {
    x: [f64; ZIGGURAT_LAYERS + 1],
    ratio: [f64; ZIGGURAT_LAYERS],
}

/// The table, computed once (in f64, deterministically).
fn ziggurat() -> &'static Ziggurat {
    static TABLE: OnceLock<Ziggurat> = OnceLock::new();
    TABLE.get_or_init(|| {
        let density = |x: f64| (-0.5 * x * x).exp();
        let mut x = [0.0; ZIGGURAT_LAYERS + 1];
        x[0] = ZIGGURAT_V / density(ZIGGURAT_R);
        x[1] = ZIGGURAT_R;
        for i in 2..ZIGGURAT_LAYERS {
            // The next edge: equal area V per layer. The argument of ln is below 1
            // for every layer but the last, which ends at 0.
            let arg = ZIGGURAT_V / x[i - 1] + density(x[i - 1]);
            x[i] = if arg < 1.0 {
                (-2.0 * arg.ln()).sqrt()
            } else {
                0.0
            };
        }
        x[ZIGGURAT_LAYERS] = 0.0;
        let mut ratio = [0.0; ZIGGURAT_LAYERS];
        for i in 0..ZIGGURAT_LAYERS {
            ratio[i] = x[i + 1] / x[i];
        }
        Ziggurat { x, ratio }
    })
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

    /// Mean, variance, and the fraction beyond 1, 2, 3 and 4 sigma of `numbers`
    /// against the standard normal distribution (each within 4 standard errors).
    fn assert_standard_normal(numbers: &[f64]) {
        let nf = numbers.len() as f64;
        let mean = numbers.iter().sum::<f64>() / nf;
        let var = numbers.iter().map(|x| x * x).sum::<f64>() / nf - mean * mean;
        assert!(mean.abs() < 4.0 / nf.sqrt(), "{mean}");
        assert!((var - 1.0).abs() < 4.0 * (2.0 / nf).sqrt(), "{var}");
        // P(|x| > k) = erfc(k / sqrt 2).
        let exact = [
            0.317_310_507_9,
            0.045_500_263_9,
            0.002_699_796_1,
            0.000_063_342_5,
        ];
        for (k, &p) in exact.iter().enumerate() {
            let beyond = numbers.iter().filter(|x| x.abs() > (k + 1) as f64).count();
            let f = beyond as f64 / nf;
            let se = (p * (1.0 - p) / nf).sqrt();
            assert!(
                (f - p).abs() < 4.0 * se,
                "beyond {} sigma: {f} vs {p}",
                k + 1
            );
        }
    }

    /// The ziggurat's numbers against the normal distribution, and the sequence of a
    /// key repeats exactly.
    #[test]
    fn ziggurat_numbers_are_standard_normal() {
        let z = ziggurat();
        // The layers close: the last edge before 0 is small and positive.
        assert!(z.x[255] > 0.0 && z.x[255] < 0.3, "{}", z.x[255]);
        assert!(z.ratio.iter().all(|r| (0.0..1.0).contains(r)));
        let numbers: Vec<f64> = (0..400_000u64)
            .map(|p| {
                let rng = PixelRng::new(3, 1, p, Stream::SensorNoise);
                let x = f64::from(rng.gaussian(p % 3));
                assert_eq!(x.to_bits(), f64::from(rng.gaussian(p % 3)).to_bits());
                x
            })
            .collect();
        assert_standard_normal(&numbers);
    }

    /// The table sampler's three numbers per pixel against the normal distribution,
    /// each channel alone and all together, and the tails beyond the table (|z| >
    /// 3.49) as often as the normal has them, with their conditional mean.
    #[test]
    fn table_normals_are_standard_normal() {
        let triples: Vec<[f32; 3]> = (0..400_000u64)
            .map(|p| {
                PixelRng::new(5, 2, p, Stream::SensorNoise).normals3(normal_table::normal_table())
            })
            .collect();
        let mut all = Vec::new();
        for k in 0..3 {
            let channel: Vec<f64> = triples.iter().map(|t| f64::from(t[k])).collect();
            assert_standard_normal(&channel);
            all.extend(channel);
        }
        assert_standard_normal(&all);
        // The channels are uncorrelated.
        for (a, b) in [(0, 1), (0, 2), (1, 2)] {
            let r = triples
                .iter()
                .map(|t| f64::from(t[a]) * f64::from(t[b]))
                .sum::<f64>()
                / triples.len() as f64;
            assert!(r.abs() < 4.0 / (triples.len() as f64).sqrt(), "{a}{b}: {r}");
        }
        let r = normal_table::normal_table().tail_start();
        let tail: Vec<f64> = all.iter().map(|x| x.abs()).filter(|&x| x > r).collect();
        let p = 2.0 / normal_table::SEGMENTS as f64;
        let f = tail.len() as f64 / all.len() as f64;
        assert!(
            (f - p).abs() < 4.0 * (p / all.len() as f64).sqrt(),
            "{f} vs {p}"
        );
        // E[Z | Z > r] = φ(r) / (1 − Φ(r)); the tail's spread is about 0.26, so the
        // ~590 tail numbers give a standard error near 0.011.
        let expected = (-0.5 * r * r).exp() / (2.0 * std::f64::consts::PI).sqrt() / (p / 2.0);
        let mean = tail.iter().sum::<f64>() / tail.len() as f64;
        assert!((mean - expected).abs() < 0.045, "{mean} vs {expected}");
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
