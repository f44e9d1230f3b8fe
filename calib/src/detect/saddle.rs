//! X-corner candidates of a checkerboard image: saddle points of the smoothed image
//! (Hessian determinant), kept where a ring around them alternates dark-light-dark-
//! light, then refined to sub-pixel precision by gradient orthogonality.

use nalgebra::{Matrix2, Vector2};

use crate::gray::GrayImage;

/// One X-corner candidate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    pub p: Vector2<f64>,
    /// Saddle strength (`Ixy² - Ixx·Iyy` of the smoothed image).
    pub response: f32,
    /// Dark-to-light contrast on the ring around it.
    pub contrast: f32,
}

/// Samples on the ring test.
const RING_SAMPLES: usize = 24;

/// Smallest ring contrast of a corner, in image units ([0, 1]).
const MIN_RING_CONTRAST: f32 = 0.03;

/// Candidates weaker than this fraction of the strongest saddle are not considered.
const MIN_RELATIVE_RESPONSE: f32 = 0.004;

/// The saddle-response image of a smoothed image (0 on the 1-pixel border).
fn saddle_response(b: &GrayImage) -> Vec<f32> {
    let (w, h) = (b.width, b.height);
    let mut out = vec![0.0f32; w * h];
    if w < 3 || h < 3 {
        return out;
    }
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let c = b.at(x, y);
            let ixx = b.at(x + 1, y) - 2.0 * c + b.at(x - 1, y);
            let iyy = b.at(x, y + 1) - 2.0 * c + b.at(x, y - 1);
            let ixy = 0.25
                * (b.at(x + 1, y + 1) - b.at(x + 1, y - 1) - b.at(x - 1, y + 1)
                    + b.at(x - 1, y - 1));
            out[y * w + x] = ixy * ixy - ixx * iyy;
        }
    }
    out
}

/// The ring test: `Some(contrast)` when the ring of radius `radius` around `p` changes
/// between dark and light exactly four times with opposite arcs alike (an X-corner).
pub fn ring_contrast(image: &GrayImage, p: Vector2<f64>, radius: f64) -> Option<f32> {
    let mut v = [0.0f32; RING_SAMPLES];
    for (k, s) in v.iter_mut().enumerate() {
        let a = k as f64 * std::f64::consts::TAU / RING_SAMPLES as f64;
        *s = image.sample(p.x + radius * a.cos(), p.y + radius * a.sin());
    }
    let (lo, hi) = v
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &s| {
            (lo.min(s), hi.max(s))
        });
    let contrast = hi - lo;
    if !(contrast >= MIN_RING_CONTRAST) {
        return None;
    }
    let mid = 0.5 * (lo + hi);
    let sign: Vec<bool> = v.iter().map(|&s| s > mid).collect();
    let changes = (0..RING_SAMPLES)
        .filter(|&k| sign[k] != sign[(k + 1) % RING_SAMPLES])
        .count();
    if changes != 4 {
        return None;
    }
    let half = RING_SAMPLES / 2;
    let alike = (0..half).filter(|&k| sign[k] == sign[k + half]).count();
    (alike * 4 >= half * 3).then_some(contrast)
}

/// Refines a corner by gradient orthogonality: the corner `c` minimises
/// `Σ w_q (g_qᵀ (q - c))²` over the window, since every gradient near an X-corner is
/// orthogonal to the line from the corner. `None` when the system is singular or the
/// point wanders further than `max_shift`.
pub fn refine(
    gx: &GrayImage,
    gy: &GrayImage,
    start: Vector2<f64>,
    half_window: usize,
    max_shift: f64,
) -> Option<Vector2<f64>> {
    let mut c = start;
    let hw = half_window as isize;
    let sigma = (half_window as f64 * 0.6).max(0.8);
    for _ in 0..20 {
        let (cx, cy) = (c.x.round() as isize, c.y.round() as isize);
        let mut a = Matrix2::zeros();
        let mut rhs = Vector2::zeros();
        for dy in -hw..=hw {
            for dx in -hw..=hw {
                let (x, y) = (cx + dx, cy + dy);
                if x < 1 || y < 1 || x >= gx.width as isize - 1 || y >= gx.height as isize - 1 {
                    continue;
                }
                let q = Vector2::new(x as f64, y as f64);
                let d2 = (q - c).norm_squared();
                let w = (-d2 / (2.0 * sigma * sigma)).exp();
                let g = Vector2::new(
                    f64::from(gx.at(x as usize, y as usize)),
                    f64::from(gy.at(x as usize, y as usize)),
                );
                let ggt = g * g.transpose() * w;
                a += ggt;
                rhs += ggt * q;
            }
        }
        let det = a.determinant();
        let trace = a.trace();
        // A well-conditioned corner has two strong gradient directions.
        if !(det.is_finite() && trace > 0.0 && det > 1.0e-4 * trace * trace) {
            return None;
        }
        let next = a.try_inverse()? * rhs;
        if !(next.x.is_finite() && next.y.is_finite()) || (next - start).norm() > max_shift {
            return None;
        }
        let step = (next - c).norm();
        c = next;
        if step < 1.0e-3 {
            break;
        }
    }
    Some(c)
}

/// Central-difference gradients of an image.
pub fn gradients(b: &GrayImage) -> (GrayImage, GrayImage) {
    let (w, h) = (b.width, b.height);
    let mut gx = vec![0.0f32; w * h];
    let mut gy = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (xi, yi) = (x as isize, y as isize);
            gx[y * w + x] = 0.5 * (b.at_clamped(xi + 1, yi) - b.at_clamped(xi - 1, yi));
            gy[y * w + x] = 0.5 * (b.at_clamped(xi, yi + 1) - b.at_clamped(xi, yi - 1));
        }
    }
    (
        GrayImage {
            width: w,
            height: h,
            data: gx,
        },
        GrayImage {
            width: w,
            height: h,
            data: gy,
        },
    )
}

/// Every X-corner candidate of a smoothed image `b`, strongest first.
pub fn candidates(
    b: &GrayImage,
    gx: &GrayImage,
    gy: &GrayImage,
    ring_radius: f64,
    half_window: usize,
) -> Vec<Candidate> {
    let response = saddle_response(b);
    let max = response.iter().copied().fold(0.0f32, f32::max);
    if !(max > 0.0) {
        return Vec::new();
    }
    let threshold = max * MIN_RELATIVE_RESPONSE;
    let nms = (ring_radius * 0.5).round().max(1.0) as isize;
    let (w, h) = (b.width as isize, b.height as isize);
    let mut out = Vec::new();
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let r = response[(y * w + x) as usize];
            if r <= threshold {
                continue;
            }
            let mut is_max = true;
            'win: for dy in -nms..=nms {
                for dx in -nms..=nms {
                    let (xx, yy) = (x + dx, y + dy);
                    if (dx, dy) == (0, 0) || xx < 0 || yy < 0 || xx >= w || yy >= h {
                        continue;
                    }
                    let o = response[(yy * w + xx) as usize];
                    // Ties go to the first in scan order.
                    if o > r || (o == r && (dy, dx) < (0, 0)) {
                        is_max = false;
                        break 'win;
                    }
                }
            }
            if !is_max {
                continue;
            }
            let p0 = Vector2::new(x as f64, y as f64);
            let Some(p) = refine(gx, gy, p0, half_window, ring_radius) else {
                continue;
            };
            let Some(contrast) = ring_contrast(b, p, ring_radius) else {
                continue;
            };
            out.push(Candidate {
                p,
                response: r,
                contrast,
            });
        }
    }
    // Two maxima that refine to the same corner: keep the stronger.
    out.sort_by(|a, b| b.response.total_cmp(&a.response));
    let mut kept: Vec<Candidate> = Vec::with_capacity(out.len());
    let min_sep2 = (0.5 * ring_radius).powi(2);
    for c in out {
        if kept.iter().all(|k| (k.p - c.p).norm_squared() > min_sep2) {
            kept.push(c);
        }
    }
    kept
}
