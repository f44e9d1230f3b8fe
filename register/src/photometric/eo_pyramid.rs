//! A scan's EO pyramid with the EO camera model: what the photometric term reads.
//! Each level holds the band-pass of log luminance: `ln Y` minus its local mean over
//! a `(2·BAND_RADIUS + 1)²` window of that level (a Laplacian pyramid of log
//! luminance). What changes smoothly across the image between two frames of the
//! same surface (vignetting, which stays with the camera while the scene moves
//! through it; shading under a moving light; the exposure and gain, which are
//! factors and so offsets in log) is an offset in the log image over a window and
//! is taken out; texture, which is what pins the motion, stays. Full resolution
//! (not the lidar-resolution colours of the texel points), because the texture that
//! slides past in a corridor is finer than the lidar grid; 16 bits per pixel.

use std::sync::Arc;

use nalgebra::{Matrix2x3, Vector2, Vector3};
use texel::{EoFrame, PinholeCamera};

/// Marks a pixel whose value is not a measurement: clipped at either end of the
/// sensor's range (a saturated highlight, a black background), or, at a coarse
/// level, a block holding one. Sampling near one gives nothing.
const INVALID: i16 = i16::MIN;
/// Luminance codes at or below this are clipped dark.
const DARK_CLIP: f32 = 1.5 / 255.0;
/// Fewest pixels a level has along each side: a smaller image holds too little
/// texture to pin anything and its few pixels would only pull the estimate about.
const MIN_LEVEL_SIDE: usize = 24;
/// Half-width of the window whose mean the band-pass takes out, level pixels.
const BAND_RADIUS: usize = 4;
/// Band values are stored as `round(value · BAND_SCALE)` in 16 bits.
const BAND_SCALE: f32 = 4096.0;
/// Points nearer the EO image plane than this (metres) do not project.
const MIN_DEPTH_M: f64 = 1.0e-6;
/// Step of the numerical derivative of the distortion, normalised coordinates.
const DISTORTION_STEP: f64 = 1.0e-6;

/// One level: band-pass log luminance, [`INVALID`] where clipped.
#[derive(Debug, Clone)]
pub struct GrayLevel {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<i16>,
}

impl GrayLevel {
    #[inline]
    fn at(&self, x: usize, y: usize) -> i16 {
        self.pixels[y * self.width + x]
    }
}

/// What a sample of the image gives: the band-pass log luminance and its gradient
/// per full-resolution pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EoSample {
    pub intensity: f64,
    pub gradient: Vector2<f64>,
}

/// A projection into the EO image: the full-resolution pixel and its derivative with
/// respect to the point (the camera's distortion included).
#[derive(Debug, Clone, Copy)]
pub struct EoProjection {
    pub pixel: Vector2<f64>,
    pub jacobian: Matrix2x3<f64>,
}

/// The band-pass pyramid and the camera it was taken with.
#[derive(Debug, Clone)]
pub struct EoPyramid {
    camera: Arc<PinholeCamera>,
    max_r2: f64,
    /// Finest first; levels below the first one built are empty.
    pub levels: Vec<GrayLevel>,
    /// Standard deviation of the full-resolution log luminance's noise, measured on
    /// the image itself.
    noise_sigma: f64,
}

impl EoPyramid {
    /// Builds `levels` levels (fewer when a level would get smaller than
    /// [`MIN_LEVEL_SIDE`] pixels),
    /// the band-pass only from level `first` up (the finer ones are not read and
    /// cost memory); `None` when the frame does not match the camera's image size or
    /// has no pixels.
    pub fn build(
        frame: &EoFrame,
        camera: Arc<PinholeCamera>,
        levels: u32,
        first: u32,
    ) -> Option<Self> {
        let (w, h) = (frame.width as usize, frame.height as usize);
        if w == 0
            || h == 0
            || frame.width != camera.width
            || frame.height != camera.height
            || frame.rgb.len() != 3 * w * h
        {
            return None;
        }
        // Luminance (coded values in [0, 1], NaN where clipped), halved per level.
        let mut luminance: Vec<Luminance> = Vec::with_capacity(levels.max(1) as usize);
        luminance.push(Luminance {
            width: w,
            height: h,
            values: frame.rgb.chunks_exact(3).map(luminance_of).collect(),
        });
        while luminance.len() < levels.max(1) as usize {
            let Some(finer) = luminance.last() else { break };
            if finer.width / 2 < MIN_LEVEL_SIDE || finer.height / 2 < MIN_LEVEL_SIDE {
                break;
            }
            luminance.push(halve(finer));
        }
        let noise_sigma = luminance.first().map_or(0.0, log_noise_sigma);
        let out = luminance
            .iter()
            .enumerate()
            .map(|(k, l)| {
                if k < first as usize {
                    GrayLevel {
                        width: l.width,
                        height: l.height,
                        pixels: Vec::new(),
                    }
                } else {
                    band_pass(l)
                }
            })
            .collect();
        let max_r2 = camera.max_radius_squared().unwrap_or(f64::INFINITY);
        Some(Self {
            camera,
            max_r2,
            levels: out,
            noise_sigma,
        })
    }

    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// Noise standard deviation of the band values at `level`: the full
    /// resolution's, halved per level (a level pixel averages `4^level` pixels).
    pub fn noise_sigma(&self, level: usize) -> f64 {
        self.noise_sigma / f64::from(1u32 << level.min(16))
    }

    pub fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    pub fn heap_bytes(&self) -> usize {
        self.levels
            .iter()
            .map(|l| l.pixels.capacity() * std::mem::size_of::<i16>())
            .sum::<usize>()
            + self.levels.capacity() * std::mem::size_of::<GrayLevel>()
    }

    /// The full-resolution pixel of a point in the EO optical frame, with its
    /// Jacobian; `None` behind the camera, outside the distortion model's domain or
    /// not finite.
    #[inline]
    pub fn project(&self, p: &Vector3<f64>) -> Option<EoProjection> {
        if !(p.z >= MIN_DEPTH_M) {
            return None;
        }
        let inv_z = 1.0 / p.z;
        let n = Vector2::new(p.x * inv_z, p.y * inv_z);
        if !(n.norm_squared() < self.max_r2) {
            return None;
        }
        let pixel = self.camera.normalized_to_pixel(n);
        // d pixel / d normalised: the distortion's derivative, by forward differences
        // (the model is smooth inside its domain).
        let dx = (self
            .camera
            .normalized_to_pixel(n + Vector2::new(DISTORTION_STEP, 0.0))
            - pixel)
            / DISTORTION_STEP;
        let dy = (self
            .camera
            .normalized_to_pixel(n + Vector2::new(0.0, DISTORTION_STEP))
            - pixel)
            / DISTORTION_STEP;
        // d normalised / d p = [[1/z, 0, -x/z²], [0, 1/z, -y/z²]].
        let dn = Matrix2x3::new(inv_z, 0.0, -n.x * inv_z, 0.0, inv_z, -n.y * inv_z);
        let dd = nalgebra::Matrix2::from_columns(&[dx, dy]);
        let jacobian = dd * dn;
        (pixel.iter().all(|c| c.is_finite()) && jacobian.iter().all(|c| c.is_finite()))
            .then_some(EoProjection { pixel, jacobian })
    }

    /// Bilinear intensity and central-difference gradient at a full-resolution pixel
    /// position, read from `level`; `None` off the image (with a one-pixel margin for
    /// the differences) or where any pixel read is clipped.
    #[inline]
    pub fn sample(&self, level: usize, pixel: &Vector2<f64>) -> Option<EoSample> {
        let l = self.levels.get(level).filter(|l| !l.pixels.is_empty())?;
        let scale = f64::from(1u32 << level.min(16));
        // Full-resolution pixel centres at integers; level pixel centres at
        // `scale·(u + 0.5) - 0.5`.
        let x = (pixel.x + 0.5) / scale - 0.5;
        let y = (pixel.y + 0.5) / scale - 0.5;
        // The 4x4 neighbourhood x0-1..=x0+2 must be on the image (comparisons refuse
        // NaN).
        if !(x >= 1.0 && y >= 1.0 && x < (l.width as f64 - 2.0) && y < (l.height as f64 - 2.0)) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let mut v = [[0.0f64; 4]; 4];
        for (j, row) in v.iter_mut().enumerate() {
            for (i, c) in row.iter_mut().enumerate() {
                let code = l.at(x0 + i - 1, y0 + j - 1);
                if code == INVALID {
                    return None;
                }
                *c = f64::from(code) / f64::from(BAND_SCALE);
            }
        }
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let bilinear = |f: &dyn Fn(usize, usize) -> f64| {
            lerp(lerp(f(1, 1), f(2, 1), fx), lerp(f(1, 2), f(2, 2), fx), fy)
        };
        let intensity = bilinear(&|i, j| v[j][i]);
        let gx = bilinear(&|i, j| 0.5 * (v[j][i + 1] - v[j][i - 1]));
        let gy = bilinear(&|i, j| 0.5 * (v[j + 1][i] - v[j - 1][i]));
        Some(EoSample {
            intensity,
            gradient: Vector2::new(gx, gy) / scale,
        })
    }
}

/// A level's luminance before the band-pass.
struct Luminance {
    width: usize,
    height: usize,
    /// Coded luminance in [0, 1]; NaN where clipped.
    values: Vec<f32>,
}

/// Rec. 709 luminance of an sRGB-coded pixel in [0, 1]; NaN when a channel is
/// clipped white or the pixel is clipped black.
#[inline]
fn luminance_of(rgb: &[u8]) -> f32 {
    if rgb.contains(&u8::MAX) {
        return f32::NAN;
    }
    let y = (0.2126 * f32::from(rgb[0]) + 0.7152 * f32::from(rgb[1]) + 0.0722 * f32::from(rgb[2]))
        / 255.0;
    if y <= DARK_CLIP { f32::NAN } else { y }
}

/// 2x2 box average; a block holding a clipped pixel is clipped (NaN propagates).
fn halve(finer: &Luminance) -> Luminance {
    let (w, h) = (finer.width / 2, finer.height / 2);
    let at = |x: usize, y: usize| finer.values[y * finer.width + x];
    let mut values = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            values.push(
                0.25 * (at(2 * x, 2 * y)
                    + at(2 * x + 1, 2 * y)
                    + at(2 * x, 2 * y + 1)
                    + at(2 * x + 1, 2 * y + 1)),
            );
        }
    }
    Luminance {
        width: w,
        height: h,
        values,
    }
}

/// Side of the blocks the noise estimate is taken over, pixels.
const NOISE_BLOCK: usize = 16;
/// The noise is the spread of the blocks at this quantile: the flatter blocks,
/// where texture adds least to it.
const NOISE_BLOCK_QUANTILE: f64 = 0.25;
/// Every this many blocks along each axis are read: a ninth of the image is plenty
/// for a quantile of their spreads, at a ninth of the cost.
const NOISE_BLOCK_STEP: usize = 3;

/// The noise of `ln Y` at full resolution (Immerkær 1996, made robust): the
/// response to the mask `[1 -2 1; -2 4 -2; 1 -2 1]`, which cancels locally linear
/// structure and has standard deviation `6σ` for independent noise of deviation
/// `σ`, relative to the pixel (so in log units to first order); its robust spread
/// (MAD) per block, and the spread of the flatter blocks, since texture only adds.
fn log_noise_sigma(level: &Luminance) -> f64 {
    let (w, h) = (level.width, level.height);
    let at = |x: usize, y: usize| level.values[y * w + x];
    let mut block_sigmas = Vec::new();
    let mut responses: Vec<f32> = Vec::with_capacity(NOISE_BLOCK * NOISE_BLOCK);
    for by in (1..h.saturating_sub(NOISE_BLOCK)).step_by(NOISE_BLOCK * NOISE_BLOCK_STEP) {
        for bx in (1..w.saturating_sub(NOISE_BLOCK)).step_by(NOISE_BLOCK * NOISE_BLOCK_STEP) {
            responses.clear();
            for y in by..(by + NOISE_BLOCK).min(h - 1) {
                for x in bx..(bx + NOISE_BLOCK).min(w - 1) {
                    let c = at(x, y);
                    let edges = at(x - 1, y) + at(x + 1, y) + at(x, y - 1) + at(x, y + 1);
                    let corners =
                        at(x - 1, y - 1) + at(x + 1, y - 1) + at(x - 1, y + 1) + at(x + 1, y + 1);
                    // NaN (a clipped pixel) fails `is_finite`.
                    let r = (4.0 * c - 2.0 * edges + corners) / c;
                    if r.is_finite() {
                        responses.push(r.abs());
                    }
                }
            }
            if responses.len() < NOISE_BLOCK * NOISE_BLOCK / 2 {
                continue;
            }
            let mid = responses.len() / 2;
            let (_, median, _) = responses.select_nth_unstable_by(mid, f32::total_cmp);
            block_sigmas.push(1.4826 * f64::from(*median) / 6.0);
        }
    }
    if block_sigmas.is_empty() {
        return 0.0;
    }
    let k = ((block_sigmas.len() - 1) as f64 * NOISE_BLOCK_QUANTILE) as usize;
    let (_, sigma, _) = block_sigmas.select_nth_unstable_by(k, f64::total_cmp);
    if sigma.is_finite() { *sigma } else { 0.0 }
}

/// `ln Y` minus its mean over the valid pixels of the window around each pixel
/// (separable running sums of the logs and of the valid count: each output is a sum
/// of at most 81 values, which f32 holds to far below the noise).
fn band_pass(level: &Luminance) -> GrayLevel {
    let (w, h) = (level.width, level.height);
    let logs: Vec<f32> = level
        .values
        .iter()
        .map(|&y| if y.is_finite() { y.ln() } else { f32::NAN })
        .collect();
    // Horizontal window sums, then vertical ones.
    let mut row_sum = vec![0.0f32; w * h];
    let mut row_count = vec![0.0f32; w * h];
    for y in 0..h {
        let line = &logs[y * w..(y + 1) * w];
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(BAND_RADIUS), (x + BAND_RADIUS + 1).min(w));
            let (mut sum, mut count) = (0.0f32, 0.0f32);
            for &v in &line[x0..x1] {
                if v.is_finite() {
                    sum += v;
                    count += 1.0;
                }
            }
            row_sum[y * w + x] = sum;
            row_count[y * w + x] = count;
        }
    }
    let mut pixels = Vec::with_capacity(w * h);
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(BAND_RADIUS), (y + BAND_RADIUS + 1).min(h));
        for x in 0..w {
            let v = logs[y * w + x];
            if !v.is_finite() {
                pixels.push(INVALID);
                continue;
            }
            let (mut sum, mut count) = (0.0f32, 0.0f32);
            for yy in y0..y1 {
                sum += row_sum[yy * w + x];
                count += row_count[yy * w + x];
            }
            // count >= 1: the pixel itself is valid.
            let mean = sum / count.max(1.0);
            let band = ((v - mean) * BAND_SCALE)
                .round()
                .clamp(f32::from(i16::MIN + 1), f32::from(i16::MAX));
            pixels.push(band as i16);
        }
    }
    GrayLevel {
        width: w,
        height: h,
        pixels,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn frame(width: u32, height: u32, f: impl Fn(u32, u32) -> u8) -> EoFrame {
        let mut rgb = Vec::new();
        for y in 0..height {
            for x in 0..width {
                let c = f(x, y);
                rgb.extend([c, c, c]);
            }
        }
        EoFrame {
            width,
            height,
            rgb,
            timestamp_ns: 0,
            exposure: None,
        }
    }

    fn camera(width: u32, height: u32) -> Arc<PinholeCamera> {
        Arc::new(PinholeCamera::from_vertical_fov(width, height, 50.0).unwrap())
    }

    /// `0.4 + 0.1·sin(2πx / 9)`: one period per band window.
    fn wave(x: f64) -> f64 {
        0.4 + 0.1 * (std::f64::consts::TAU * x / 9.0).sin()
    }

    #[test]
    fn texture_keeps_its_log_gradient_in_the_band() {
        let f = frame(128, 96, |x, _| (255.0 * wave(f64::from(x))).round() as u8);
        let eo = EoPyramid::build(&f, camera(128, 96), 3, 0).unwrap();
        assert_eq!(eo.level_count(), 3);
        for x in [60.0, 61.5, 63.25] {
            let s = eo.sample(0, &Vector2::new(x, 40.7)).unwrap();
            // d/dx ln(wave), by central differences over one pixel as the sampler.
            let expected = 0.5 * (wave(x + 1.0).ln() - wave(x - 1.0).ln());
            assert!(
                (s.gradient.x - expected).abs() < 0.15 * expected.abs() + 0.004,
                "{x}: {s:?} vs {expected}"
            );
            assert!(s.gradient.y.abs() < 1e-9);
        }
    }

    #[test]
    fn a_smooth_brightness_field_leaves_the_band_nearly_unchanged() {
        // Vignetting-like: 35 % darker at the corners, and a global exposure change.
        let texture = |x: u32, y: u32| wave(f64::from(x)) + 0.1 * wave(f64::from(y) * 1.3);
        let plain = frame(160, 120, |x, y| (255.0 * texture(x, y)).round() as u8);
        let shaded = frame(160, 120, |x, y| {
            let r2 = ((f64::from(x) - 80.0).powi(2) + (f64::from(y) - 60.0).powi(2)) / 10000.0;
            (255.0 * 1.2 * texture(x, y) * (1.0 - 0.35 * r2)).round() as u8
        });
        let a = EoPyramid::build(&plain, camera(160, 120), 1, 0).unwrap();
        let b = EoPyramid::build(&shaded, camera(160, 120), 1, 0).unwrap();
        let mut worst: f64 = 0.0;
        let mut contrast: f64 = 0.0;
        for (x, y) in [(20.3, 20.8), (80.0, 60.0), (140.6, 100.1), (30.0, 90.0)] {
            let p = Vector2::new(x, y);
            let (sa, sb) = (a.sample(0, &p).unwrap(), b.sample(0, &p).unwrap());
            worst = worst.max((sa.intensity - sb.intensity).abs());
            contrast = contrast.max(sa.intensity.abs());
        }
        // The band's texture is ~0.2 in log units; the field changes it by < 0.02
        // (the raw luminance differs by up to 35 %).
        assert!(contrast > 0.1, "{contrast}");
        assert!(worst < 0.02, "{worst}");
    }

    #[test]
    fn clipped_pixels_and_edges_give_nothing() {
        let f = frame(64, 64, |x, _| if x == 30 { 255 } else { 100 });
        let eo = EoPyramid::build(&f, camera(64, 64), 2, 0).unwrap();
        assert!(eo.sample(0, &Vector2::new(30.2, 20.0)).is_none());
        assert!(eo.sample(0, &Vector2::new(10.0, 20.0)).is_some());
        assert!(eo.sample(1, &Vector2::new(30.0, 20.0)).is_none());
        assert!(eo.sample(0, &Vector2::new(0.2, 20.0)).is_none());
        assert!(eo.sample(0, &Vector2::new(f64::NAN, 20.0)).is_none());
        let black = frame(64, 64, |_, _| 0);
        let eo = EoPyramid::build(&black, camera(64, 64), 1, 0).unwrap();
        assert!(eo.sample(0, &Vector2::new(30.0, 30.0)).is_none());
    }

    #[test]
    fn the_projection_jacobian_matches_finite_differences() {
        let mut cam = PinholeCamera::from_vertical_fov(640, 480, 50.0).unwrap();
        cam.distortion = texel::camera::Distortion::PlumbBob(texel::distortion::PlumbBob {
            k1: -0.05,
            k2: 0.01,
            p1: 0.0005,
            p2: -0.0003,
            k3: 0.0,
        });
        let eo = EoPyramid::build(&frame(640, 480, |_, _| 9), Arc::new(cam), 1, 0).unwrap();
        let p = Vector3::new(0.4, -0.3, 2.0);
        let proj = eo.project(&p).unwrap();
        for axis in 0..3 {
            let mut q = p;
            q[axis] += 1e-6;
            let numeric = (eo.project(&q).unwrap().pixel - proj.pixel) / 1e-6;
            let analytic = proj.jacobian.column(axis);
            assert!((numeric - analytic).norm() < 1e-3, "{axis}");
        }
        assert!(eo.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn a_frame_of_the_wrong_size_is_refused() {
        assert!(EoPyramid::build(&frame(64, 64, |_, _| 9), camera(64, 48), 1, 0).is_none());
    }
}
