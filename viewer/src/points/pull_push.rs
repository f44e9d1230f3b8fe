//! Pull-push interpolation (Marroquim et al. 2007, as Lechelek et al. 2019 §4 use it)
//! of a sparse image: the pull stage averages the valid pixels of each 2 x 2 block
//! into the next coarser level, up to 1 x 1; the push stage fills every invalid pixel
//! from the level above it. An image with no valid pixel stays without one; one valid
//! pixel fills the whole image with its value. Weights, not flags, travel up the
//! pyramid, so the result is a weighted mean and never a 0/0.

/// A sparse image: a value and a weight per pixel (weight 0: no value).
#[derive(Debug, Clone, PartialEq)]
pub struct Sparse {
    pub width: usize,
    pub height: usize,
    pub value: Vec<f32>,
    pub weight: Vec<f32>,
}

impl Sparse {
    /// `width × height` pixels without a value.
    pub fn empty(width: usize, height: usize) -> Self {
        let n = width.saturating_mul(height);
        Self {
            width,
            height,
            value: vec![0.0; n],
            weight: vec![0.0; n],
        }
    }

    /// Sets pixel `(x, y)`; out of the image or non-finite: ignored.
    pub fn set(&mut self, x: usize, y: usize, value: f32, weight: f32) {
        let usable = value.is_finite() && weight.is_finite() && weight > 0.0;
        if x >= self.width || y >= self.height || !usable {
            return;
        }
        let i = y * self.width + x;
        self.value[i] = value;
        self.weight[i] = weight.min(f32::MAX);
    }

    pub fn get(&self, x: usize, y: usize) -> Option<f32> {
        let i = y.checked_mul(self.width)?.checked_add(x)?;
        (x < self.width && *self.weight.get(i)? > 0.0).then(|| self.value[i])
    }

    fn valid(&self) -> usize {
        self.weight.iter().filter(|&&w| w > 0.0).count()
    }
}

/// The pull stage: the next coarser level, each pixel the weighted mean of the valid
/// pixels of its 2 x 2 block (weights summed, capped at 1 so a level's weights stay a
/// coverage, not a count).
fn pull(fine: &Sparse) -> Sparse {
    let (w, h) = (fine.width.div_ceil(2), fine.height.div_ceil(2));
    let mut coarse = Sparse::empty(w, h);
    for y in 0..h {
        for x in 0..w {
            let (mut sum, mut sum_w) = (0.0f64, 0.0f64);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (fx, fy) = (2 * x + dx, 2 * y + dy);
                if fx < fine.width && fy < fine.height {
                    let i = fy * fine.width + fx;
                    let wgt = f64::from(fine.weight[i]);
                    if wgt > 0.0 {
                        sum += wgt * f64::from(fine.value[i]);
                        sum_w += wgt;
                    }
                }
            }
            if sum_w > 0.0 {
                let i = y * w + x;
                coarse.value[i] = (sum / sum_w) as f32;
                coarse.weight[i] = sum_w.min(1.0) as f32;
            }
        }
    }
    coarse
}

/// Fills every invalid pixel of `image` by pull-push; valid pixels keep their value.
/// Returns the filled image (weight 1 where a value was interpolated) and how many
/// pixels were filled.
pub fn pull_push(image: &Sparse) -> (Sparse, usize) {
    // Pull: the pyramid up to 1 x 1 (or until nothing is missing).
    let mut levels = vec![image.clone()];
    while let Some(top) = levels.last() {
        if (top.width <= 1 && top.height <= 1) || top.valid() == top.width * top.height {
            break;
        }
        let next = pull(top);
        levels.push(next);
    }
    // Push: from the coarsest level down, each invalid pixel takes its parent's.
    let mut filled = 0;
    for l in (0..levels.len().saturating_sub(1)).rev() {
        let (upper, lower) = levels.split_at_mut(l + 1);
        let (fine, coarse) = (&mut upper[l], &lower[0]);
        for y in 0..fine.height {
            for x in 0..fine.width {
                let i = y * fine.width + x;
                if fine.weight[i] > 0.0 {
                    continue;
                }
                if let Some(v) = coarse.get(x / 2, y / 2) {
                    fine.value[i] = v;
                    fine.weight[i] = 1.0;
                    if l == 0 {
                        filled += 1;
                    }
                }
            }
        }
    }
    let out = levels.into_iter().next().unwrap_or_else(|| image.clone());
    (out, filled)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn an_empty_image_stays_empty_and_a_single_splat_fills_everything() {
        let empty = Sparse::empty(7, 5);
        let (out, filled) = pull_push(&empty);
        assert_eq!(filled, 0);
        assert!(out.weight.iter().all(|&w| w == 0.0));
        assert!(out.value.iter().all(|v| v.is_finite()));
        let mut one = Sparse::empty(7, 5);
        one.set(3, 2, 4.25, 1.0);
        let (out, filled) = pull_push(&one);
        assert_eq!(filled, 34);
        assert!(out.value.iter().all(|&v| v == 4.25), "{:?}", out.value);
        // Zero-size images are empty.
        let (out, filled) = pull_push(&Sparse::empty(0, 3));
        assert_eq!((out.value.len(), filled), (0, 0));
    }

    #[test]
    fn a_hole_takes_the_mean_of_its_neighbourhood() {
        let mut img = Sparse::empty(4, 4);
        for y in 0..4 {
            for x in 0..4 {
                if (x, y) != (1, 1) {
                    img.set(x, y, (x + y) as f32, 1.0);
                }
            }
        }
        let (out, filled) = pull_push(&img);
        assert_eq!(filled, 1);
        // The mean of the other three pixels of its 2 x 2 block: 0, 1 and 1.
        assert!((out.get(1, 1).unwrap() - 2.0 / 3.0).abs() < 1e-6);
        assert_eq!(out.get(3, 3), Some(6.0));
    }

    proptest! {
        /// Filled values lie within the range of the given ones; given values stay.
        #[test]
        fn filled_values_stay_within_the_given_range(
            w in 1usize..20,
            h in 1usize..20,
            given in prop::collection::vec((0usize..20, 0usize..20, -1e3f32..1e3), 0..30),
        ) {
            let mut img = Sparse::empty(w, h);
            for &(x, y, v) in &given {
                img.set(x % w, y % h, v, 1.0);
            }
            let (lo, hi) = img
                .value
                .iter()
                .zip(&img.weight)
                .filter(|(_, w)| **w > 0.0)
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), (v, _)| (lo.min(*v), hi.max(*v)));
            let (out, _) = pull_push(&img);
            for (i, (v, wgt)) in out.value.iter().zip(&out.weight).enumerate() {
                prop_assert!(v.is_finite());
                if img.weight[i] > 0.0 {
                    prop_assert_eq!(*v, img.value[i]);
                } else if lo <= hi {
                    prop_assert!(*wgt > 0.0 && *v >= lo - 1e-3 && *v <= hi + 1e-3, "{v} not in {lo}..{hi}");
                }
            }
        }
    }
}
