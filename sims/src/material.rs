//! Materials: a diffuse texture (constant colour, checkerboard, image, procedural
//! noise or bricks) giving linear reflectance per surface point, optional glossy parameters for
//! the `specular` effect, and the reflectivity the lidar sees.
//!
//! Textures are looked up with a **footprint**: the width in metres of the pixel's
//! cone on the surface. Checkerboards and bricks are box-filtered analytically over it,
//! images are mip-mapped (trilinear), noise drops the octaves finer than it. A clean render
//! at one ray per pixel is therefore free of texture aliasing, which the viewer's
//! PSNR/SSIM scoring against `texel-sims view` relies on.

use std::sync::Arc;

pub use crate::noise::NoiseTable;
use crate::noise::{LANES, fast_floor};
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
    /// Running-bond brickwork: courses of bricks `brick_m = [length, height]` (joint
    /// centre to joint centre) with mortar joints `mortar_m` wide, every other course
    /// shifted by half a brick; each brick takes a seeded colour of `palette`, its
    /// brightness scaled by a seeded factor in `[1 - variation, 1 + variation]`.
    Bricks(Bricks),
}

/// The parameters of [`Texture::Bricks`].
#[derive(Debug, Clone, PartialEq)]
pub struct Bricks {
    /// Length and height of one brick with its share of the joints, metres.
    pub brick_m: [f64; 2],
    /// Width of the mortar joints, metres (less than both sides of a brick).
    pub mortar_m: f64,
    pub palette: Vec<Rgb>,
    /// Relative brightness variation between bricks, in [0, 1].
    pub variation: f32,
    pub mortar: Rgb,
    pub seed: u64,
}

/// Footprints up to this many brick heights are box-filtered exactly, brick by brick.
const BRICKS_EXACT_HEIGHTS: f64 = 2.0;
/// Footprints from this many brick heights on take the wall's mean colour; between
/// the two the exact filter blends into the mean.
const BRICKS_MEAN_HEIGHTS: f64 = 4.0;

impl Bricks {
    /// The colour of brick `k` of course `j`.
    fn brick_colour(&self, j: i64, k: i64) -> Rgb {
        let h = mix64(
            mix64(self.seed ^ 0x6272_6963_6b73_0000)
                ^ (j as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let h = mix64(h ^ (k as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93));
        let n = self.palette.len().max(1);
        let base = self
            .palette
            .get((h % n as u64) as usize)
            .copied()
            .unwrap_or([0.5; 3]);
        // The top 24 bits as a uniform in [0, 1).
        let u = ((h >> 40) as f32) / (1u64 << 24) as f32;
        let f = 1.0 + self.variation * (2.0 * u - 1.0);
        base.map(|c| (c * f).clamp(0.0, 1.0))
    }

    /// The mean colour of a large piece of wall: bricks (the palette's mean) over the
    /// fraction of the area they cover, mortar over the rest.
    pub fn mean(&self) -> Rgb {
        let [l, h] = self.brick_m;
        let body = ((l - self.mortar_m) * (h - self.mortar_m) / (l * h)) as f32;
        let n = self.palette.len().max(1) as f32;
        let mut mean = [0.0f32; 3];
        for c in &self.palette {
            for k in 0..3 {
                mean[k] += c[k] / n;
            }
        }
        std::array::from_fn(|k| body * mean[k] + (1.0 - body) * self.mortar[k])
    }

    /// The colour at `uv`, box-filtered over a square `w` metres wide.
    fn sample(&self, uv: [f64; 2], w: f64) -> Rgb {
        let s = w / self.brick_m[1];
        // A NaN footprint is refused by `sane_footprint` before this; NaN coordinates take
        // the mean too.
        let in_range = s < BRICKS_MEAN_HEIGHTS;
        if !(in_range && uv[0].is_finite() && uv[1].is_finite()) {
            return self.mean();
        }
        let exact = if w < 1.0e-9 {
            self.point(uv)
        } else {
            self.box_filtered(uv, w)
        };
        if s <= BRICKS_EXACT_HEIGHTS {
            return exact;
        }
        let t = ((s - BRICKS_EXACT_HEIGHTS) / (BRICKS_MEAN_HEIGHTS - BRICKS_EXACT_HEIGHTS)) as f32;
        lerp(exact, self.mean(), t)
    }

    /// The course of `v` and the brick of `u` in it, with `u`, `v` within the cell.
    #[inline]
    fn cell(&self, uv: [f64; 2]) -> (i64, i64, f64, f64) {
        let [l, h] = self.brick_m;
        let j = fast_floor(uv[1] / h);
        let shift = if (j as i64).rem_euclid(2) == 1 {
            0.5 * l
        } else {
            0.0
        };
        let x = uv[0] - shift;
        let k = fast_floor(x / l);
        (j as i64, k as i64, x - k * l, uv[1] - j * h)
    }

    /// The colour at one point.
    fn point(&self, uv: [f64; 2]) -> Rgb {
        let (j, k, x, y) = self.cell(uv);
        let [l, h] = self.brick_m;
        let m = 0.5 * self.mortar_m;
        if x < m || x >= l - m || y < m || y >= h - m {
            self.mortar
        } else {
            self.brick_colour(j, k)
        }
    }

    /// The exact mean over the square `[u - w/2, u + w/2] x [v - w/2, v + w/2]`: every
    /// brick it overlaps weighs by the area it covers, the mortar takes the rest.
    fn box_filtered(&self, uv: [f64; 2], w: f64) -> Rgb {
        let [l, h] = self.brick_m;
        let m = 0.5 * self.mortar_m;
        let (u0, u1) = (uv[0] - 0.5 * w, uv[0] + 0.5 * w);
        let (v0, v1) = (uv[1] - 0.5 * w, uv[1] + 0.5 * w);
        let overlap = |a0: f64, a1: f64, b0: f64, b1: f64| (a1.min(b1) - a0.max(b0)).max(0.0);
        let mut acc = [0.0f64; 3];
        let mut covered = 0.0f64;
        let (j0, j1) = (fast_floor(v0 / h) as i64, fast_floor(v1 / h) as i64);
        for j in j0..=j1 {
            let row = j as f64 * h;
            let dv = overlap(v0, v1, row + m, row + h - m);
            if dv <= 0.0 {
                continue;
            }
            let shift = if j.rem_euclid(2) == 1 { 0.5 * l } else { 0.0 };
            let (k0, k1) = (
                fast_floor((u0 - shift) / l) as i64,
                fast_floor((u1 - shift) / l) as i64,
            );
            for k in k0..=k1 {
                let left = shift + k as f64 * l;
                let du = overlap(u0, u1, left + m, left + l - m);
                if du <= 0.0 {
                    continue;
                }
                let a = du * dv;
                let c = self.brick_colour(j, k);
                for (acc, c) in acc.iter_mut().zip(c) {
                    *acc += a * f64::from(c);
                }
                covered += a;
            }
        }
        let area = w * w;
        let rest = (area - covered).max(0.0);
        std::array::from_fn(|i| ((acc[i] + rest * f64::from(self.mortar[i])) / area) as f32)
    }
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
        let footprint_m = sane_footprint(footprint_m);
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
            Self::Bricks(bricks) => bricks.sample(uv, footprint_m),
        }
    }

    /// True for a noise texture, whose lookups are cheaper [`LANES`] at a time
    /// ([`Self::sample_lanes`]).
    pub fn is_noise(&self) -> bool {
        matches!(self, Self::Noise { .. })
    }

    /// [`Self::sample`] at [`LANES`] points, bit for bit the same colours: a noise
    /// texture evaluates its fBm for all of them at once
    /// ([`NoiseTable::fbm_fixed_lanes`]), the others sample one at a time.
    pub fn sample_lanes(&self, uv: &[[f64; 2]; LANES], footprint_m: &[f64; LANES]) -> [Rgb; LANES] {
        let Self::Noise {
            palette,
            scale_m,
            octaves,
            table,
        } = self
        else {
            return std::array::from_fn(|l| self.sample(uv[l], footprint_m[l]));
        };
        let footprint: [f64; LANES] =
            std::array::from_fn(|l| sane_footprint(footprint_m[l]) / scale_m);
        let x = std::array::from_fn(|l| uv[l][0] / scale_m);
        let y = std::array::from_fn(|l| uv[l][1] / scale_m);
        let v = table.fbm_fixed_lanes(&x, &y, &footprint, *octaves);
        std::array::from_fn(|l| ramp(palette, v[l]))
    }
}

/// A footprint width as texture lookups take it: negative and non-finite widths are 0.
#[inline]
fn sane_footprint(footprint_m: f64) -> f64 {
    if footprint_m.is_finite() {
        footprint_m.max(0.0)
    } else {
        0.0
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

    fn bricks() -> Bricks {
        Bricks {
            brick_m: [0.24, 0.08],
            mortar_m: 0.01,
            palette: vec![[0.6, 0.2, 0.1], [0.5, 0.25, 0.15], [0.7, 0.3, 0.2]],
            variation: 0.1,
            mortar: [0.8, 0.8, 0.75],
            seed: 7,
        }
    }

    #[test]
    fn bricks_and_mortar_lie_where_the_bond_puts_them() {
        let b = bricks();
        let t = Texture::Bricks(b.clone());
        let is_mortar = |c: Rgb| c == [0.8, 0.8, 0.75];
        let is_brick = |c: Rgb| c[0] > 0.4 && c[0] < 0.8 && c[1] < 0.35;
        // Course 0: joints at u = 0, 0.24, ...; bed joints at v = 0, 0.08, ...
        assert!(is_brick(t.sample([0.12, 0.04], 0.0)));
        assert!(is_mortar(t.sample([0.002, 0.04], 0.0)));
        assert!(is_mortar(t.sample([0.239, 0.04], 0.0)));
        assert!(is_mortar(t.sample([0.12, 0.078], 0.0)));
        assert!(is_mortar(t.sample([0.12, -0.003], 0.0)));
        // Course 1 is shifted by half a brick: its head joint is at u = 0.12.
        assert!(is_mortar(t.sample([0.12, 0.12], 0.0)));
        assert!(is_brick(t.sample([0.0, 0.12], 0.0)));
        assert!(is_brick(t.sample([-0.1, -0.04], 0.0)));
        // One brick has one colour; its neighbours (mostly) others.
        assert_eq!(t.sample([0.03, 0.03], 0.0), t.sample([0.2, 0.05], 0.0));
        let colours: std::collections::BTreeSet<[u32; 3]> = (0..40)
            .map(|k| {
                t.sample([0.12 + 0.24 * f64::from(k), 0.04], 0.0)
                    .map(f32::to_bits)
            })
            .collect();
        assert!(colours.len() > 20, "{}", colours.len());
        // Small footprints inside a brick see the brick alone.
        assert_eq!(t.sample([0.12, 0.04], 0.01), t.sample([0.12, 0.04], 0.0));
        // Another seed, other colours.
        let other = Texture::Bricks(Bricks { seed: 8, ..b });
        assert!((0..20).any(|k| {
            let uv = [0.12 + 0.24 * f64::from(k), 0.04];
            other.sample(uv, 0.0) != t.sample(uv, 0.0)
        }));
    }

    #[test]
    fn bricks_filter_to_the_mean_and_match_supersampling() {
        let b = bricks();
        let t = Texture::Bricks(b.clone());
        let mean = b.mean();
        // Footprints of many bricks take the mean exactly; over 1.5 m of wall the exact
        // box filter lands close to it.
        assert_eq!(t.sample([3.21, -7.7], 1.0), mean);
        let near = b.box_filtered([0.3, 0.2], 1.5);
        for k in 0..3 {
            assert!((near[k] - mean[k]).abs() < 0.01, "{near:?} {mean:?}");
        }
        // The exact filter against a brute-force average of point samples.
        for (uv, w) in [
            ([0.11, 0.07], 0.03),
            ([-0.5, 0.33], 0.12),
            ([1.0, 1.0], 0.15),
        ] {
            let n = 200;
            let mut acc = [0.0f64; 3];
            for a in 0..n {
                for c in 0..n {
                    let p = [
                        uv[0] + w * ((f64::from(a) + 0.5) / f64::from(n) - 0.5),
                        uv[1] + w * ((f64::from(c) + 0.5) / f64::from(n) - 0.5),
                    ];
                    let col = b.point(p);
                    for k in 0..3 {
                        acc[k] += f64::from(col[k]) / f64::from(n * n);
                    }
                }
            }
            let f = t.sample(uv, w);
            for k in 0..3 {
                assert!(
                    (f64::from(f[k]) - acc[k]).abs() < 0.01,
                    "{uv:?} {w}: {f:?} {acc:?}"
                );
            }
        }
        // The blend from exact to mean is continuous in the footprint.
        let a = t.sample([0.4, 0.5], 0.32 - 1e-9);
        let c = t.sample([0.4, 0.5], 0.32 + 1e-9);
        assert!((a[0] - c[0]).abs() < 1e-5);
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
