//! Single-channel f32 images for detection: conversion from EO frames and lidar
//! intensity, separable Gaussian smoothing, and bilinear sampling.

use texel::{EoFrame, RangeFrame};

/// A row-major single-channel image, values nominally in [0, 1].
#[derive(Debug, Clone, PartialEq)]
pub struct GrayImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl GrayImage {
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Option<Self> {
        (width > 0 && height > 0 && data.len() == width * height).then_some(Self {
            width,
            height,
            data,
        })
    }

    /// Rec. 601 luma of an EO frame in [0, 1]; `None` for an inconsistent frame.
    pub fn from_eo(frame: &EoFrame) -> Option<Self> {
        if !frame.is_consistent() {
            return None;
        }
        let data = frame
            .rgb
            .chunks_exact(3)
            .map(|p| {
                (0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]))
                    / 255.0
            })
            .collect();
        Self::new(frame.width as usize, frame.height as usize, data)
    }

    /// The lidar intensity image scaled so its 99th percentile is 1 (0 where there is
    /// no return); `None` without intensity.
    pub fn from_intensity(frame: &RangeFrame) -> Option<Self> {
        let values = frame.intensity.as_ref()?;
        if !frame.is_consistent() {
            return None;
        }
        Self::from_intensity_values(frame.width as usize, frame.height as usize, values)
    }

    /// [`Self::from_intensity`] of a row-major `width` x `height` intensity buffer;
    /// `None` when its length does not match or nothing returned.
    pub fn from_intensity_values(width: usize, height: usize, values: &[f32]) -> Option<Self> {
        if values.len() != width * height {
            return None;
        }
        let mut finite: Vec<f32> = values
            .iter()
            .copied()
            .filter(|v| v.is_finite() && *v > 0.0)
            .collect();
        if finite.is_empty() {
            return None;
        }
        let k = (finite.len() * 99 / 100).min(finite.len() - 1);
        let (_, p99, _) = finite.select_nth_unstable_by(k, f32::total_cmp);
        let scale = if *p99 > 0.0 { 1.0 / *p99 } else { 1.0 };
        let data = values
            .iter()
            .map(|&v| {
                if v.is_finite() && v > 0.0 {
                    (v * scale).min(1.5)
                } else {
                    0.0
                }
            })
            .collect();
        Self::new(width, height, data)
    }

    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Value at integer coordinates clamped to the image.
    #[inline]
    pub fn at_clamped(&self, x: isize, y: isize) -> f32 {
        let xc = x.clamp(0, self.width as isize - 1) as usize;
        let yc = y.clamp(0, self.height as isize - 1) as usize;
        self.data[yc * self.width + xc]
    }

    /// Bilinear value at a pixel-centre coordinate (clamped at the borders); 0 for a
    /// non-finite coordinate.
    pub fn sample(&self, x: f64, y: f64) -> f32 {
        if !(x.is_finite() && y.is_finite()) {
            return 0.0;
        }
        let x = x.clamp(0.0, (self.width - 1) as f64);
        let y = y.clamp(0.0, (self.height - 1) as f64);
        let (x0, y0) = (x.floor() as isize, y.floor() as isize);
        let (ax, ay) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let a = self.at_clamped(x0, y0);
        let b = self.at_clamped(x0 + 1, y0);
        let c = self.at_clamped(x0, y0 + 1);
        let d = self.at_clamped(x0 + 1, y0 + 1);
        let top = a + (b - a) * ax;
        let bottom = c + (d - c) * ax;
        top + (bottom - top) * ay
    }

    /// True when `(x, y)` lies at least `margin` pixels inside the image.
    pub fn inside(&self, x: f64, y: f64, margin: f64) -> bool {
        x >= margin
            && y >= margin
            && x <= self.width as f64 - 1.0 - margin
            && y <= self.height as f64 - 1.0 - margin
    }

    /// Separable Gaussian blur with standard deviation `sigma` pixels (borders
    /// clamped); `sigma <= 0` returns a copy.
    pub fn blurred(&self, sigma: f64) -> Self {
        if !(sigma.is_finite() && sigma > 0.0) {
            return self.clone();
        }
        let radius = (3.0 * sigma).ceil() as isize;
        let kernel: Vec<f32> = (-radius..=radius)
            .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
            .collect();
        let sum: f32 = kernel.iter().sum();
        let kernel: Vec<f32> = kernel.iter().map(|k| k / sum).collect();
        let (w, h) = (self.width, self.height);
        let mut tmp = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (k, kv) in kernel.iter().enumerate() {
                    acc += kv * self.at_clamped(x as isize + k as isize - radius, y as isize);
                }
                tmp[y * w + x] = acc;
            }
        }
        let tmp = Self {
            width: w,
            height: h,
            data: tmp,
        };
        let mut out = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (k, kv) in kernel.iter().enumerate() {
                    acc += kv * tmp.at_clamped(x as isize, y as isize + k as isize - radius);
                }
                out[y * w + x] = acc;
            }
        }
        Self {
            width: w,
            height: h,
            data: out,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blur_keeps_the_mean_and_sample_interpolates() {
        let data: Vec<f32> = (0..64).map(|i| (i % 8) as f32 / 7.0).collect();
        let g = GrayImage::new(8, 8, data).unwrap();
        let b = g.blurred(1.0);
        let mean_a: f32 = g.data.iter().sum::<f32>() / 64.0;
        let mean_b: f32 = b.data.iter().sum::<f32>() / 64.0;
        assert!((mean_a - mean_b).abs() < 0.02);
        assert!((g.sample(2.5, 3.0) - 2.5 / 7.0).abs() < 1e-6);
        assert_eq!(g.sample(f64::NAN, 1.0), 0.0);
    }
}
