//! Materials: a diffuse texture (constant colour, checkerboard, image, or procedural
//! noise) giving linear reflectance per surface point, optional glossy parameters for
//! the `specular` effect, and the reflectivity the lidar sees.
//!
//! Textures are looked up with a **footprint**: the width in metres of the pixel's
//! cone on the surface. Checkerboards are box-filtered analytically over it, images
//! are mip-mapped (trilinear), noise drops the octaves finer than it. A clean render
//! at one ray per pixel is therefore free of texture aliasing, which the viewer's
//! PSNR/SSIM scoring against `texel-sims view` relies on.

use std::sync::Arc;

use crate::rng::mix64;

/// Linear RGB in [0, 1].
pub type Rgb = [f32; 3];

/// What a surface's diffuse reflectance comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum Texture {
    Constant(Rgb),
    /// Squares of `square_m` alternating between `colors`; with `squares`, a board of
    /// that many squares centred on the uv origin, `border` colour outside it.
    Checker {
        colors: [Rgb; 2],
        square_m: f64,
        squares: Option<[u32; 2]>,
        border: Rgb,
    },
    /// An image repeated every `size_m` metres, centred on the uv origin, +v up.
    Image {
        image: Arc<MipImage>,
        size_m: [f64; 2],
    },
    /// Band-limited value-noise fBm mapped through a colour ramp.
    Noise {
        palette: Vec<Rgb>,
        scale_m: f64,
        octaves: u32,
        table: Arc<NoiseTable>,
    },
}

/// A surface material.
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    pub name: String,
    pub texture: Texture,
    /// Blinn-Phong specular reflectance (used only by the `specular` effect).
    pub specular: f32,
    /// Blinn-Phong exponent.
    pub shininess: f32,
    /// Reflectivity at the lidar's wavelength; `None` takes the diffuse luminance.
    pub lidar_reflectivity: Option<f32>,
}

impl Material {
    /// Diffuse reflectance at `uv_m` for a footprint `footprint_m` metres wide.
    #[inline]
    pub fn albedo(&self, uv_m: [f64; 2], footprint_m: f64) -> Rgb {
        self.texture.sample(uv_m, footprint_m)
    }

    /// Reflectivity the lidar sees at `uv_m`, in [0, 1].
    pub fn lidar_albedo(&self, uv_m: [f64; 2], footprint_m: f64) -> f32 {
        match self.lidar_reflectivity {
            Some(r) => r,
            None => luminance(self.albedo(uv_m, footprint_m)),
        }
    }
}

/// Rec. 709 luminance of linear RGB.
#[inline]
pub fn luminance(c: Rgb) -> f32 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

#[inline]
fn lerp(a: Rgb, b: Rgb, t: f32) -> Rgb {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// `x.floor()` without a libm call on targets without SSE4.1 (finite inputs within
/// ±2⁶³; others saturate, which only shifts a texture pattern).
#[inline]
fn fast_floor(x: f64) -> f64 {
    let i = x as i64;
    let f = i as f64;
    if f > x { f - 1.0 } else { f }
}

/// Integral of the unit square wave (0 on [0,1), 1 on [1,2), period 2) from 0 to x.
#[inline]
fn square_wave_integral(x: f64) -> f64 {
    let half = fast_floor(x * 0.5);
    half + (x - 2.0 * half - 1.0).max(0.0)
}

/// The square wave box-filtered over `[x - w/2, x + w/2]`.
#[inline]
fn filtered_square_wave(x: f64, w: f64) -> f64 {
    if w < 1.0e-4 {
        let half = fast_floor(x * 0.5);
        return if x - 2.0 * half >= 1.0 { 1.0 } else { 0.0 };
    }
    (square_wave_integral(x + 0.5 * w) - square_wave_integral(x - 0.5 * w)) / w
}

impl Texture {
    pub fn sample(&self, uv: [f64; 2], footprint_m: f64) -> Rgb {
        let footprint_m = if footprint_m.is_finite() {
            footprint_m.max(0.0)
        } else {
            0.0
        };
        match self {
            Self::Constant(c) => *c,
            Self::Checker {
                colors,
                square_m,
                squares,
                border,
            } => {
                let (mut x, mut y) = (uv[0] / square_m, uv[1] / square_m);
                if let Some([nx, ny]) = squares {
                    let (hx, hy) = (f64::from(*nx) * 0.5, f64::from(*ny) * 0.5);
                    if x.abs() > hx || y.abs() > hy {
                        return *border;
                    }
                    x += hx;
                    y += hy;
                }
                let w = footprint_m / square_m;
                let fx = filtered_square_wave(x, w);
                let fy = filtered_square_wave(y, w);
                // Exclusive or of the two square waves, filtered per axis.
                let t = fx + fy - 2.0 * fx * fy;
                lerp(colors[0], colors[1], t as f32)
            }
            Self::Image { image, size_m } => {
                let s = uv[0] / size_m[0] + 0.5;
                let t = 0.5 - uv[1] / size_m[1];
                let texels = footprint_m / size_m[0] * f64::from(image.width());
                image.sample(s, t, texels)
            }
            Self::Noise {
                palette,
                scale_m,
                octaves,
                table,
            } => {
                let v = table.fbm_fixed(
                    uv[0] / scale_m,
                    uv[1] / scale_m,
                    footprint_m / scale_m,
                    *octaves,
                );
                ramp(palette, v)
            }
        }
    }
}

/// Colour ramp through evenly spaced palette entries; `t` in [0, 1].
pub fn ramp(palette: &[Rgb], t: f32) -> Rgb {
    match palette.len() {
        0 => [0.5; 3],
        1 => palette[0],
        n => {
            let x = t.clamp(0.0, 1.0) * (n - 1) as f32;
            // x is in [0, n - 1] (0 for NaN): one conversion instruction through i32,
            // where a cast to usize saturates.
            let i = (x as i32).max(0) as usize;
            let i = i.min(n - 2);
            lerp(palette[i], palette[i + 1], x - i as f32)
        }
    }
}

/// Side of the lattice of random values behind value noise; the noise repeats every
/// `NOISE_PERIOD` lattice cells (per octave, with octaves offset from each other, so
/// repeats are not visible).
const NOISE_PERIOD: usize = 256;

/// Random lattice values of one seed, looked up instead of hashed per sample.
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseTable {
    /// Row-major, `NOISE_PERIOD` by `NOISE_PERIOD`: a lattice index is 16 bits, so
    /// looking one up needs no bounds check.
    values: Box<[f32; LATTICE_LEN]>,
}

/// Values in a noise lattice.
const LATTICE_LEN: usize = NOISE_PERIOD * NOISE_PERIOD;

impl NoiseTable {
    pub fn new(seed: u64) -> Self {
        let mut values = Box::new([0.0f32; LATTICE_LEN]);
        for (i, v) in values.iter_mut().enumerate() {
            *v = (mix64(seed ^ mix64(i as u64 + 1)) >> 40) as f32 / (1u64 << 24) as f32;
        }
        Self { values }
    }

    #[inline]
    fn lattice(&self, ix: i64, iy: i64) -> f32 {
        let m = NOISE_PERIOD as i64 - 1;
        self.values[((iy & m) as usize) * NOISE_PERIOD + (ix & m) as usize]
    }

    /// Smooth value noise in [0, 1].
    #[inline]
    fn value_noise(&self, x: f64, y: f64) -> f32 {
        let (fx, fy) = (fast_floor(x), fast_floor(y));
        let (ix, iy) = (fx as i64, fy as i64);
        let (tx, ty) = ((x - fx) as f32, (y - fy) as f32);
        let sx = tx * tx * (3.0 - 2.0 * tx);
        let sy = ty * ty * (3.0 - 2.0 * ty);
        let a = self.lattice(ix, iy);
        let b = self.lattice(ix + 1, iy);
        let c = self.lattice(ix, iy + 1);
        let d = self.lattice(ix + 1, iy + 1);
        let top = a + (b - a) * sx;
        let bottom = c + (d - c) * sx;
        top + (bottom - top) * sy
    }

    /// Fractional Brownian motion of value noise in [0, 1]; octaves whose period is
    /// below about two footprints fade out (band limiting) towards their mean.
    pub fn fbm(&self, x: f64, y: f64, footprint: f64, octaves: u32) -> f64 {
        let mut sum = 0.0f32;
        let mut norm = 0.0f32;
        let mut freq = 1.0f64;
        let mut amp = 1.0f32;
        for o in 0..octaves.min(16) {
            norm += amp;
            // Fraction of this octave that survives the footprint's low-pass.
            let keep = (1.0 - (freq * footprint - 0.25) * 2.0).clamp(0.0, 1.0) as f32;
            if keep <= 0.0 {
                // Every finer octave is gone too: they add their mean.
                sum += 0.5 * amp;
                let mut a = amp * 0.5;
                for _ in o + 1..octaves.min(16) {
                    sum += 0.5 * a;
                    norm += a;
                    a *= 0.5;
                }
                break;
            }
            let shift = f64::from(o) * 37.7;
            let n = self.value_noise(x * freq + shift, y * freq - shift * 0.61);
            sum += amp * (0.5 + (n - 0.5) * keep);
            freq *= 2.0;
            amp *= 0.5;
        }
        if norm > 0.0 {
            f64::from(sum / norm)
        } else {
            0.5
        }
    }
}

/// Fractional bits of the fixed-point lattice coordinates of [`NoiseTable::fbm_fixed`].
const FIXED_BITS: u32 = 24;
/// One lattice period in fixed point: coordinates wrap modulo this.
const FIXED_PERIOD: u64 = (NOISE_PERIOD as u64) << FIXED_BITS;
// `fbm_fixed` wraps coordinates in u32 and indexes the lattice with 16 bits.
const _: () = assert!(NOISE_PERIOD == 256 && FIXED_PERIOD == 1 << 32);

impl NoiseTable {
    /// [`Self::fbm`] evaluated the fast way, to within 1e-5 of it: the base
    /// coordinates are reduced modulo the lattice period (which every octave's period
    /// divides) and turned into fixed point with 24 fractional bits once, so each
    /// octave's cell and fraction are a shift and a mask instead of a float floor. The
    /// renderer samples noise textures through this.
    pub fn fbm_fixed(&self, x: f64, y: f64, footprint: f64, octaves: u32) -> f32 {
        // One lattice period is exactly 2^32 in fixed point, so u32 arithmetic wraps
        // the coordinates modulo the period for free.
        let to_fixed = |v: f64| -> u32 {
            let period = NOISE_PERIOD as f64;
            let wrapped = v - period * fast_floor(v / period);
            // In [0, period] for finite v; anything else (NaN, huge) lands at 0.
            (wrapped * f64::from(1u32 << FIXED_BITS)) as u64 as u32
        };
        let (fx, fy) = (to_fixed(x), to_fixed(y));
        let octaves = octaves.min(16);
        let mut sum = 0.0f32;
        let mut norm = 0.0f32;
        let mut freq = 1.0f64;
        let mut amp = 1.0f32;
        // A footprint below a quarter of the finest octave's cell keeps every octave
        // whole (keep = 1 exactly, below, as freq · footprint only grows with the
        // octave, by exact doublings): the common case, without the filter's
        // arithmetic.
        let finest = f64::from(1u32 << octaves.saturating_sub(1));
        if octaves > 0 && finest * footprint <= 0.25 {
            for (o, &(sx, sy)) in OCTAVE_SHIFTS.iter().enumerate().take(octaves as usize) {
                norm += amp;
                let n =
                    self.value_noise_fixed((fx << o).wrapping_add(sx), (fy << o).wrapping_add(sy));
                // (n - 0.5) · 1 is n - 0.5 exactly: the same sum as the loop below.
                sum += amp * (0.5 + (n - 0.5));
                amp *= 0.5;
            }
            return if norm > 0.0 { sum / norm } else { 0.5 };
        }
        for (o, &(sx, sy)) in OCTAVE_SHIFTS.iter().enumerate().take(octaves as usize) {
            norm += amp;
            let keep = (1.0 - (freq * footprint - 0.25) * 2.0).clamp(0.0, 1.0) as f32;
            if keep <= 0.0 {
                // Every finer octave is gone too: they add their mean.
                sum += 0.5 * amp;
                let mut a = amp * 0.5;
                for _ in o + 1..octaves as usize {
                    sum += 0.5 * a;
                    norm += a;
                    a *= 0.5;
                }
                break;
            }
            // The octave's coordinates: base × 2^o plus its offset (as in `fbm`).
            let ox = (fx << o).wrapping_add(sx);
            let oy = (fy << o).wrapping_add(sy);
            let n = self.value_noise_fixed(ox, oy);
            sum += amp * (0.5 + (n - 0.5) * keep);
            freq *= 2.0;
            amp *= 0.5;
        }
        if norm > 0.0 { sum / norm } else { 0.5 }
    }

    /// [`Self::value_noise`] at fixed-point coordinates (wrapping).
    #[inline]
    fn value_noise_fixed(&self, x: u32, y: u32) -> f32 {
        const CELL: u32 = FIXED_BITS;
        let (ix, iy) = (x >> CELL, y >> CELL);
        let fraction = |v: u32| (v & ((1 << CELL) - 1)) as f32 * (1.0 / (1u32 << CELL) as f32);
        let (tx, ty) = (fraction(x), fraction(y));
        let sx = tx * tx * (3.0 - 2.0 * tx);
        let sy = ty * ty * (3.0 - 2.0 * ty);
        // 8-bit cell coordinates wrap at the period; (row << 8 | column) is 16 bits.
        let (row0, row1) = (iy << 8, ((iy + 1) & 0xFF) << 8);
        let ix1 = (ix + 1) & 0xFF;
        let at = |i: u32| self.values[i as u16 as usize];
        let (a, b) = (at(row0 | ix), at(row0 | ix1));
        let (c, d) = (at(row1 | ix), at(row1 | ix1));
        let top = a + (b - a) * sx;
        let bottom = c + (d - c) * sx;
        top + (bottom - top) * sy
    }
}

/// The per-octave offsets of [`NoiseTable::fbm`] (`+37.7 o`, `-37.7 · 0.61 o` lattice
/// cells) in fixed point, modulo the lattice period.
const OCTAVE_SHIFTS: [(u32, u32); 16] = {
    let mut out = [(0u32, 0u32); 16];
    let mut o = 0;
    while o < 16 {
        let sx = 37.7 * o as f64;
        let sy = -37.7 * 0.61 * o as f64;
        let period = NOISE_PERIOD as f64;
        // Wrap into [0, period) without a float floor (not const): whole periods.
        let wx = sx - period * ((sx / period) as i64 as f64);
        let mut wy = sy - period * ((sy / period) as i64 as f64);
        if wy < 0.0 {
            wy += period;
        }
        let scale = (1u64 << FIXED_BITS) as f64;
        out[o] = (
            ((wx * scale) as u64 % FIXED_PERIOD) as u32,
            ((wy * scale) as u64 % FIXED_PERIOD) as u32,
        );
        o += 1;
    }
    out
};

/// An image in linear RGB with its mip pyramid, repeating at its edges.
#[derive(Debug, Clone, PartialEq)]
pub struct MipImage {
    /// Level 0 first; each level halves both sides (at least 1).
    levels: Vec<Level>,
}

#[derive(Debug, Clone, PartialEq)]
struct Level {
    width: usize,
    height: usize,
    texels: Vec<Rgb>,
}

impl Level {
    #[inline]
    fn fetch(&self, x: i64, y: i64) -> Rgb {
        let xi = x.rem_euclid(self.width as i64) as usize;
        let yi = y.rem_euclid(self.height as i64) as usize;
        self.texels[yi * self.width + xi]
    }

    /// Bilinear lookup at normalised (s, t), repeating.
    fn bilinear(&self, s: f64, t: f64) -> Rgb {
        let x = s * self.width as f64 - 0.5;
        let y = t * self.height as f64 - 0.5;
        if !(x.is_finite() && y.is_finite()) {
            return self.texels[0];
        }
        let (fx, fy) = (fast_floor(x), fast_floor(y));
        let (ax, ay) = ((x - fx) as f32, (y - fy) as f32);
        let (ix, iy) = (fx as i64, fy as i64);
        let top = lerp(self.fetch(ix, iy), self.fetch(ix + 1, iy), ax);
        let bottom = lerp(self.fetch(ix, iy + 1), self.fetch(ix + 1, iy + 1), ax);
        lerp(top, bottom, ay)
    }
}

impl MipImage {
    /// From linear RGB texels, row-major, row 0 at the top. `None` for an empty or
    /// inconsistent buffer.
    pub fn new(width: usize, height: usize, texels: Vec<Rgb>) -> Option<Self> {
        if width == 0 || height == 0 || texels.len() != width * height {
            return None;
        }
        let mut levels = vec![Level {
            width,
            height,
            texels,
        }];
        while let Some(last) = levels.last() {
            if last.width == 1 && last.height == 1 {
                break;
            }
            let (w, h) = ((last.width / 2).max(1), (last.height / 2).max(1));
            let mut texels = Vec::with_capacity(w * h);
            for y in 0..h {
                for x in 0..w {
                    let mut acc = [0.0f32; 3];
                    for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        let c = last.fetch((2 * x + dx) as i64, (2 * y + dy) as i64);
                        for k in 0..3 {
                            acc[k] += 0.25 * c[k];
                        }
                    }
                    texels.push(acc);
                }
            }
            levels.push(Level {
                width: w,
                height: h,
                texels,
            });
        }
        Some(Self { levels })
    }

    /// From an 8-bit sRGB image.
    pub fn from_srgb8(width: usize, height: usize, rgb: &[u8]) -> Option<Self> {
        if rgb.len() != 3 * width * height {
            return None;
        }
        let texels = rgb
            .chunks_exact(3)
            .map(|p| {
                [
                    srgb_to_linear(p[0]),
                    srgb_to_linear(p[1]),
                    srgb_to_linear(p[2]),
                ]
            })
            .collect();
        Self::new(width, height, texels)
    }

    pub fn width(&self) -> u32 {
        self.levels.first().map_or(1, |l| l.width as u32)
    }

    pub fn height(&self) -> u32 {
        self.levels.first().map_or(1, |l| l.height as u32)
    }

    /// Trilinear lookup at normalised (s, t) for a footprint of `texels` level-0
    /// texels.
    pub fn sample(&self, s: f64, t: f64, texels: f64) -> Rgb {
        let lod = if texels > 1.0 && texels.is_finite() {
            texels.log2()
        } else {
            0.0
        };
        let max = (self.levels.len() - 1) as f64;
        let lod = lod.clamp(0.0, max);
        let lo = lod.floor() as usize;
        let a = self.levels[lo].bilinear(s, t);
        if lo as f64 == max {
            return a;
        }
        let b = self.levels[lo + 1].bilinear(s, t);
        lerp(a, b, (lod - lo as f64) as f32)
    }
}

/// sRGB-encoded 8-bit value to linear.
pub fn srgb_to_linear(v: u8) -> f32 {
    let c = f32::from(v) / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear value to sRGB encoding, both in [0, 1] (input clamped).
pub fn linear_to_srgb(c: f32) -> f32 {
    let c = if c.is_finite() {
        c.clamp(0.0, 1.0)
    } else {
        0.0
    };
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checker_alternates_and_filters_to_the_mean() {
        let t = Texture::Checker {
            colors: [[0.0; 3], [1.0; 3]],
            square_m: 0.1,
            squares: None,
            border: [1.0; 3],
        };
        assert_eq!(t.sample([0.05, 0.05], 0.0), [0.0; 3]);
        assert_eq!(t.sample([0.15, 0.05], 0.0), [1.0; 3]);
        assert_eq!(t.sample([0.15, 0.15], 0.0), [0.0; 3]);
        // A footprint of many squares averages to grey.
        let g = t.sample([0.123, 0.456], 2.0);
        assert!((g[0] - 0.5).abs() < 0.03, "{g:?}");
    }

    #[test]
    fn bounded_checker_has_a_border() {
        let t = Texture::Checker {
            colors: [[0.0; 3], [1.0; 3]],
            square_m: 0.1,
            squares: Some([4, 3]),
            border: [0.5; 3],
        };
        assert_eq!(t.sample([0.25, 0.0], 0.0), [0.5; 3]);
        // The bottom-left square (x in [0,1), y in [0,1) after shifting) is colour 0.
        assert_eq!(t.sample([-0.19, -0.14], 0.0), [0.0; 3]);
    }

    /// The renderer's fixed-point fBm against the f64 reference (which also makes the
    /// committed mural): within 1e-5 everywhere, at any footprint, including negative
    /// and far-away coordinates.
    #[test]
    fn fixed_point_fbm_matches_the_reference() {
        let table = NoiseTable::new(11);
        let mut s = 5u64;
        let mut next = || {
            s = mix64(s);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut worst = 0.0f64;
        for _ in 0..20_000 {
            let x = (next() - 0.5) * 2000.0;
            let y = (next() - 0.5) * 2000.0;
            let footprint = next() * next() * 0.2;
            let octaves = 1 + (next() * 7.0) as u32;
            let reference = table.fbm(x, y, footprint, octaves);
            let fast = f64::from(table.fbm_fixed(x, y, footprint, octaves));
            worst = worst.max((reference - fast).abs());
        }
        assert!(worst < 1e-5, "{worst}");
    }

    #[test]
    fn mip_levels_preserve_the_mean() {
        let texels: Vec<Rgb> = (0..64).map(|i| [(i % 2) as f32, 0.0, 1.0]).collect();
        let m = MipImage::new(8, 8, texels).unwrap();
        let coarse = m.sample(0.3, 0.7, 1000.0);
        assert!((coarse[0] - 0.5).abs() < 1e-6 && coarse[2] == 1.0);
    }

    #[test]
    fn srgb_round_trips() {
        for v in [0u8, 1, 10, 128, 200, 255] {
            let back = (linear_to_srgb(srgb_to_linear(v)) * 255.0).round() as u8;
            assert_eq!(back, v);
        }
    }
}
