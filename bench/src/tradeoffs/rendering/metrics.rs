//! Image quality against ground truth over a mask of pixels: PSNR over the RGB
//! channels and SSIM (Wang et al. 2004) on luma with an 11x11 Gaussian window
//! (sigma 1.5) whose weights are restricted to masked pixels, so pixels the model
//! does not cover influence neither the score nor their neighbours' statistics.

/// A rendered image against the truth over `mask` (row-major, width x height).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Score {
    /// Mean squared error over the masked pixels' RGB values (0..255 scale).
    pub mse: f64,
    /// Mean SSIM over the masked pixels.
    pub ssim: f64,
    /// Masked pixels scored.
    pub pixels: usize,
}

impl Score {
    /// PSNR in dB; 99 dB stands for identical images.
    pub fn psnr_db(&self) -> f64 {
        psnr_db(self.mse)
    }
}

pub fn psnr_db(mse: f64) -> f64 {
    if mse <= 1e-10 {
        99.0
    } else {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    }
}

/// Scores `image` (RGB8) against `truth` (RGB8) on the pixels where `mask` is set.
/// `None` when the sizes differ or the mask is empty.
pub fn score(
    image: &[u8],
    truth: &[u8],
    mask: &[bool],
    width: usize,
    height: usize,
) -> Option<Score> {
    let n = width * height;
    if image.len() != 3 * n || truth.len() != 3 * n || mask.len() != n {
        return None;
    }
    let mut sq = 0.0f64;
    let mut count = 0usize;
    for i in 0..n {
        if !mask[i] {
            continue;
        }
        for c in 0..3 {
            let d = f64::from(image[3 * i + c]) - f64::from(truth[3 * i + c]);
            sq += d * d;
        }
        count += 1;
    }
    if count == 0 {
        return None;
    }
    let ssim = masked_ssim(&luma(image), &luma(truth), mask, width, height)?;
    Some(Score {
        mse: sq / (3.0 * count as f64),
        ssim,
        pixels: count,
    })
}

/// BT.601 luma of RGB8 pixels, 0..255.
pub fn luma(rgb: &[u8]) -> Vec<f64> {
    rgb.chunks_exact(3)
        .map(|p| 0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2]))
        .collect()
}

/// Mean SSIM over masked pixels whose window is at least half masked (by weight).
pub fn masked_ssim(
    a: &[f64],
    b: &[f64],
    mask: &[bool],
    width: usize,
    height: usize,
) -> Option<f64> {
    const RADIUS: i64 = 5;
    const SIGMA: f64 = 1.5;
    let c1 = (0.01f64 * 255.0).powi(2);
    let c2 = (0.03f64 * 255.0).powi(2);
    let kernel: Vec<f64> = (-RADIUS..=RADIUS)
        .map(|d| (-((d * d) as f64) / (2.0 * SIGMA * SIGMA)).exp())
        .collect();
    let full: f64 = kernel.iter().sum::<f64>().powi(2);
    let (w, h) = (width as i64, height as i64);
    let mut total = 0.0f64;
    let mut count = 0usize;
    for y in 0..h {
        for x in 0..w {
            if !mask[(y * w + x) as usize] {
                continue;
            }
            let (mut sw, mut sa, mut sb, mut saa, mut sbb, mut sab) =
                (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0);
            for dy in -RADIUS..=RADIUS {
                let yy = y + dy;
                if yy < 0 || yy >= h {
                    continue;
                }
                let ky = kernel[(dy + RADIUS) as usize];
                for dx in -RADIUS..=RADIUS {
                    let xx = x + dx;
                    if xx < 0 || xx >= w {
                        continue;
                    }
                    let i = (yy * w + xx) as usize;
                    if !mask[i] {
                        continue;
                    }
                    let k = ky * kernel[(dx + RADIUS) as usize];
                    sw += k;
                    sa += k * a[i];
                    sb += k * b[i];
                    saa += k * a[i] * a[i];
                    sbb += k * b[i] * b[i];
                    sab += k * a[i] * b[i];
                }
            }
            if sw < 0.5 * full {
                continue;
            }
            let (ma, mb) = (sa / sw, sb / sw);
            let va = (saa / sw - ma * ma).max(0.0);
            let vb = (sbb / sw - mb * mb).max(0.0);
            let cov = sab / sw - ma * mb;
            let s = ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                / ((ma * ma + mb * mb + c1) * (va + vb + c2));
            total += s;
            count += 1;
        }
    }
    (count > 0).then(|| total / count as f64)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn noise_image(w: usize, h: usize, seed: u32) -> Vec<u8> {
        let mut s = seed.wrapping_mul(2654435761).max(1);
        (0..3 * w * h)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 17;
                s ^= s << 5;
                (s & 0xff) as u8
            })
            .collect()
    }

    #[test]
    fn identical_images_score_perfectly_and_known_errors_give_known_psnr() {
        let (w, h) = (32, 24);
        let a = noise_image(w, h, 3);
        let mask = vec![true; w * h];
        let s = score(&a, &a, &mask, w, h).unwrap();
        assert_eq!(s.psnr_db(), 99.0);
        assert!((s.ssim - 1.0).abs() < 1e-12);
        // Every channel off by 5: MSE 25, PSNR 20 log10(255 / 5).
        let b: Vec<u8> = a
            .iter()
            .map(|v| v.saturating_add(5).clamp(5, 250))
            .collect();
        let a2: Vec<u8> = b.iter().map(|v| v - 5).collect();
        let s = score(&a2, &b, &mask, w, h).unwrap();
        assert!((s.psnr_db() - 20.0 * (255.0f64 / 5.0).log10()).abs() < 1e-9);
        assert!(s.ssim < 1.0 && s.ssim > 0.9);
    }

    #[test]
    fn unmasked_pixels_do_not_count() {
        let (w, h) = (32, 24);
        let a = noise_image(w, h, 5);
        let mut b = a.clone();
        let mut mask = vec![true; w * h];
        // Ruin the right half and mask it out.
        for y in 0..h {
            for x in w / 2..w {
                mask[y * w + x] = false;
                for c in 0..3 {
                    b[3 * (y * w + x) + c] = 255 - a[3 * (y * w + x) + c];
                }
            }
        }
        let s = score(&b, &a, &mask, w, h).unwrap();
        assert_eq!(s.pixels, w * h / 2);
        assert_eq!(s.psnr_db(), 99.0);
        assert!((s.ssim - 1.0).abs() < 1e-12);
        assert!(score(&b, &a, &vec![false; w * h], w, h).is_none());
        // A noisy copy scores lower in SSIM than the exact one.
        let c = noise_image(w, h, 9);
        let s = score(&c, &a, &vec![true; w * h], w, h).unwrap();
        assert!(s.ssim < 0.2, "{}", s.ssim);
    }
}
