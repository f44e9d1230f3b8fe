//! A symmetric positive definite matrix stored by its lower envelope (each row from
//! its first non-zero column to the diagonal) and its Cholesky factorisation in place
//! (George & Liu 1981, "Computer Solution of Large Sparse Positive Definite
//! Systems", Ch. 4). The factor's non-zeros stay inside the envelope, so the pose
//! graph in time order costs O(Σ rows · overlap) instead of a dense O(n³): a chain of
//! scans linked a few back is banded, and a loop edge widens only the rows after it.

/// Lower envelope storage: row `r` holds columns `start[r]..=r`.
#[derive(Debug, Clone)]
pub struct Envelope {
    start: Vec<usize>,
    /// Offset of row `r`'s first stored entry in `values`.
    offset: Vec<usize>,
    values: Vec<f64>,
}

impl Envelope {
    /// Zeros with the given row starts (`start[r] <= r`; larger values are clamped).
    pub fn zeros(start: Vec<usize>) -> Self {
        let start: Vec<usize> = start
            .into_iter()
            .enumerate()
            .map(|(r, s)| s.min(r))
            .collect();
        let mut offset = Vec::with_capacity(start.len() + 1);
        let mut total = 0usize;
        for (r, &s) in start.iter().enumerate() {
            offset.push(total);
            total += r - s + 1;
        }
        offset.push(total);
        Self {
            start,
            offset,
            values: vec![0.0; total],
        }
    }

    pub fn dim(&self) -> usize {
        self.start.len()
    }

    /// Stored entries.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Adds `v` at `(r, c)` of the symmetric matrix (either triangle); `false` if the
    /// entry lies outside the envelope (then nothing is added).
    pub fn add(&mut self, r: usize, c: usize, v: f64) -> bool {
        let (r, c) = if c > r { (c, r) } else { (r, c) };
        match self.start.get(r) {
            Some(&s) if c >= s => {
                self.values[self.offset[r] + c - s] += v;
                true
            }
            _ => false,
        }
    }

    pub fn get(&self, r: usize, c: usize) -> f64 {
        let (r, c) = if c > r { (c, r) } else { (r, c) };
        match self.start.get(r) {
            Some(&s) if c >= s => self.values[self.offset[r] + c - s],
            _ => 0.0,
        }
    }

    /// Factors `A = L Lᵀ` in place (row by row); `None` if a pivot is not positive
    /// and finite (the matrix is not positive definite).
    pub fn cholesky(mut self) -> Option<Self> {
        let n = self.dim();
        for r in 0..n {
            let (sr, or) = (self.start[r], self.offset[r]);
            for c in sr..=r {
                let (sc, oc) = (self.start[c], self.offset[c]);
                let k0 = sr.max(sc);
                // Σ_k L[r][k] L[c][k] over the rows' common columns before c.
                let row_r = &self.values[or + (k0 - sr)..or + (c - sr)];
                let row_c = &self.values[oc + (k0 - sc)..oc + (c - sc)];
                let dot: f64 = row_r.iter().zip(row_c).map(|(a, b)| a * b).sum();
                let a = self.values[or + c - sr] - dot;
                let v = if c == r {
                    if !(a > 0.0) || !a.is_finite() {
                        return None;
                    }
                    a.sqrt()
                } else {
                    a / self.values[oc + c - sc]
                };
                self.values[or + c - sr] = v;
            }
        }
        Some(self)
    }

    /// Solves `L Lᵀ x = b` with a factor from [`Self::cholesky`].
    pub fn solve(&self, b: &[f64]) -> Vec<f64> {
        let n = self.dim();
        let mut y: Vec<f64> = b
            .iter()
            .copied()
            .chain(std::iter::repeat(0.0))
            .take(n)
            .collect();
        // L y = b, row by row.
        for r in 0..n {
            let (s, o) = (self.start[r], self.offset[r]);
            let row = &self.values[o..o + (r - s)];
            let dot: f64 = row.iter().zip(&y[s..r]).map(|(a, b)| a * b).sum();
            y[r] = (y[r] - dot) / self.values[o + r - s];
        }
        // Lᵀ x = y, column by column from the last row up.
        for r in (0..n).rev() {
            let (s, o) = (self.start[r], self.offset[r]);
            y[r] /= self.values[o + r - s];
            let x = y[r];
            for (k, l) in (s..r).zip(&self.values[o..o + (r - s)]) {
                y[k] -= l * x;
            }
        }
        y
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::{DMatrix, DVector};
    use proptest::prelude::*;

    proptest! {
        /// Random banded-plus-border SPD systems are solved like nalgebra's dense
        /// Cholesky solves them.
        #[test]
        fn solves_like_a_dense_cholesky(n in 2usize..30, band in 1usize..5, seed in 0u64..1000) {
            let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
            let mut next = || {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
            };
            // A = M Mᵀ + n I with M lower-banded, plus a "loop" entry (n-1, 0).
            let mut m = DMatrix::<f64>::zeros(n, n);
            for r in 0..n {
                for c in r.saturating_sub(band)..=r {
                    m[(r, c)] = next();
                }
            }
            m[(n - 1, 0)] = next();
            let a = &m * m.transpose() + DMatrix::identity(n, n) * n as f64;
            let start: Vec<usize> = (0..n)
                .map(|r| (0..=r).find(|&c| a[(r, c)] != 0.0).unwrap_or(r))
                .collect();
            let mut env = Envelope::zeros(start);
            for r in 0..n {
                for c in 0..=r {
                    if a[(r, c)] != 0.0 {
                        prop_assert!(env.add(r, c, a[(r, c)]));
                    }
                }
            }
            let b: Vec<f64> = (0..n).map(|_| next()).collect();
            let x = env.cholesky().unwrap().solve(&b);
            let dense = a.clone().cholesky().unwrap().solve(&DVector::from_column_slice(&b));
            for (u, v) in x.iter().zip(dense.iter()) {
                prop_assert!((u - v).abs() < 1e-9 * (1.0 + v.abs()), "{u} vs {v}");
            }
        }
    }

    #[test]
    fn indefinite_matrices_are_refused() {
        let mut env = Envelope::zeros(vec![0, 0]);
        env.add(0, 0, 1.0);
        env.add(1, 0, 2.0);
        env.add(1, 1, 1.0);
        assert!(env.cholesky().is_none());
        assert!(!Envelope::zeros(vec![0, 1]).add(1, 0, 1.0));
    }
}
