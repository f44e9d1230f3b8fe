//! Levenberg-Marquardt for block-structured least squares in nalgebra, with the
//! parameter covariance at the solution.
//!
//! A problem is a parameter vector and residual **blocks**; each block reads a few
//! parameters (a view's pose and the shared intrinsics, say) and yields a few
//! residuals, already divided by their standard deviation. Jacobians are central
//! differences per block, so the normal equations `JᵀJ` (parameters × parameters,
//! dense) are accumulated without ever forming `J`. Steps solve
//! `(JᵀJ + λ·diag(JᵀJ)) δ = -Jᵀr` (Marquardt's scaling), λ adapted by the gain ratio.

use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

/// The residual function of a block: `(its parameters in block order, out)`.
pub type BlockFn<'a> = Box<dyn Fn(&[f64], &mut [f64]) + Send + Sync + 'a>;

/// A group of residuals that depends on a few parameters.
pub struct Block<'a> {
    /// Indices into the problem's parameter vector.
    pub params: Vec<usize>,
    pub residuals: usize,
    pub eval: BlockFn<'a>,
    /// Which residual class this block belongs to (for per-class statistics).
    pub class: usize,
}

/// A least-squares problem.
pub struct Problem<'a> {
    pub blocks: Vec<Block<'a>>,
    /// Typical magnitude of each parameter (sets the finite-difference step).
    pub scale: Vec<f64>,
    /// Parameters held constant.
    pub fixed: Vec<bool>,
}

/// Options of a solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmOptions {
    pub max_iterations: usize,
    /// Stop when the relative cost decrease of an accepted step is below this.
    pub cost_tolerance: f64,
    /// Stop when the step is below this relative to the parameters.
    pub step_tolerance: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            cost_tolerance: 1.0e-12,
            step_tolerance: 1.0e-12,
        }
    }
}

/// The outcome of a solve.
#[derive(Debug, Clone)]
pub struct LmResult {
    pub x: Vec<f64>,
    /// `½ Σ r²` at `x`.
    pub cost: f64,
    pub initial_cost: f64,
    pub iterations: usize,
    pub converged: bool,
    /// Number of residuals.
    pub residual_count: usize,
    /// Number of free parameters.
    pub free_count: usize,
    /// `JᵀJ` at the solution over all parameters (fixed ones have zero rows).
    pub jtj: DMatrix<f64>,
}

/// One block's contribution: its free parameter indices, `JᵀJ`, `Jᵀr` and cost.
type BlockNormal = (Vec<usize>, DMatrix<f64>, DVector<f64>, f64);

/// Relative finite-difference step (cube root of machine epsilon, for central
/// differences).
const FD_STEP: f64 = 6.0e-6;

/// Residual values larger than this are clamped: a block that cannot be evaluated
/// (a point behind a camera) yields a large finite residual, never NaN.
pub const RESIDUAL_CLAMP: f64 = 1.0e6;

fn sanitise(r: &mut [f64]) {
    for v in r {
        *v = if v.is_finite() {
            v.clamp(-RESIDUAL_CLAMP, RESIDUAL_CLAMP)
        } else {
            RESIDUAL_CLAMP
        };
    }
}

impl Problem<'_> {
    pub fn parameter_count(&self) -> usize {
        self.scale.len()
    }

    pub fn residual_count(&self) -> usize {
        self.blocks.iter().map(|b| b.residuals).sum()
    }

    fn eval_block(&self, block: &Block<'_>, x: &[f64], out: &mut [f64]) {
        let local: Vec<f64> = block.params.iter().map(|&p| x[p]).collect();
        (block.eval)(&local, out);
        sanitise(out);
    }

    /// The residuals of every block at `x`, block by block.
    pub fn residuals(&self, x: &[f64]) -> Vec<Vec<f64>> {
        self.blocks
            .par_iter()
            .map(|b| {
                let mut r = vec![0.0; b.residuals];
                self.eval_block(b, x, &mut r);
                r
            })
            .collect()
    }

    /// `½ Σ r²` at `x`.
    pub fn cost(&self, x: &[f64]) -> f64 {
        self.residuals(x)
            .iter()
            .flat_map(|r| r.iter())
            .map(|v| 0.5 * v * v)
            .sum()
    }

    /// `(JᵀJ, Jᵀr, cost)` at `x`.
    pub fn normal_equations(&self, x: &[f64]) -> (DMatrix<f64>, DVector<f64>, f64) {
        let n = self.parameter_count();
        let partials: Vec<BlockNormal> = self
            .blocks
            .par_iter()
            .map(|b| {
                let m = b.residuals;
                let mut r0 = vec![0.0; m];
                self.eval_block(b, x, &mut r0);
                let free: Vec<usize> = b
                    .params
                    .iter()
                    .enumerate()
                    .filter(|&(_, &p)| !self.fixed[p])
                    .map(|(k, _)| k)
                    .collect();
                let mut local: Vec<f64> = b.params.iter().map(|&p| x[p]).collect();
                let mut jac = DMatrix::zeros(m, free.len());
                let mut rp = vec![0.0; m];
                let mut rm = vec![0.0; m];
                for (col, &k) in free.iter().enumerate() {
                    let p = b.params[k];
                    let h = FD_STEP * local[k].abs().max(self.scale[p]);
                    let orig = local[k];
                    local[k] = orig + h;
                    (b.eval)(&local, &mut rp);
                    sanitise(&mut rp);
                    local[k] = orig - h;
                    (b.eval)(&local, &mut rm);
                    sanitise(&mut rm);
                    local[k] = orig;
                    for row in 0..m {
                        jac[(row, col)] = (rp[row] - rm[row]) / (2.0 * h);
                    }
                }
                let r = DVector::from_vec(r0);
                let jtj = jac.transpose() * &jac;
                let jtr = jac.transpose() * &r;
                let cost = 0.5 * r.norm_squared();
                let idx: Vec<usize> = free.iter().map(|&k| b.params[k]).collect();
                (idx, jtj, jtr, cost)
            })
            .collect();
        let mut jtj = DMatrix::zeros(n, n);
        let mut jtr = DVector::zeros(n);
        let mut cost = 0.0;
        for (idx, bj, br, c) in partials {
            for (a, &pa) in idx.iter().enumerate() {
                jtr[pa] += br[a];
                for (b, &pb) in idx.iter().enumerate() {
                    jtj[(pa, pb)] += bj[(a, b)];
                }
            }
            cost += c;
        }
        (jtj, jtr, cost)
    }

    /// Minimises `½ Σ r²` from `x0`.
    pub fn solve(&self, x0: &[f64], options: &LmOptions) -> LmResult {
        let n = self.parameter_count();
        let mut x = x0.to_vec();
        let (mut jtj, mut jtr, mut cost) = self.normal_equations(&x);
        let initial_cost = cost;
        let mut lambda = 1.0e-3;
        let mut iterations = 0;
        let mut converged = false;
        while iterations < options.max_iterations {
            iterations += 1;
            let max_diag = (0..n).map(|i| jtj[(i, i)]).fold(0.0f64, f64::max);
            if !(max_diag > 0.0 && max_diag.is_finite()) {
                converged = true;
                break;
            }
            let mut accepted = false;
            for _ in 0..30 {
                let mut a = jtj.clone();
                for i in 0..n {
                    if self.fixed[i] {
                        a[(i, i)] = 1.0;
                        continue;
                    }
                    let d = jtj[(i, i)].max(1.0e-12 * max_diag);
                    a[(i, i)] += lambda * d;
                }
                let Some(chol) = a.cholesky() else {
                    lambda *= 10.0;
                    continue;
                };
                let delta = chol.solve(&(-&jtr));
                if !delta.iter().all(|v| v.is_finite()) {
                    lambda *= 10.0;
                    continue;
                }
                let candidate: Vec<f64> = x.iter().zip(delta.iter()).map(|(a, d)| a + d).collect();
                let new_cost = self.cost(&candidate);
                // Gain ratio: actual over predicted decrease.
                let predicted = -(delta.dot(&jtr) + 0.5 * delta.dot(&(&jtj * &delta)));
                if new_cost.is_finite() && new_cost < cost {
                    let rho = if predicted > 0.0 {
                        (cost - new_cost) / predicted
                    } else {
                        1.0
                    };
                    lambda *= if rho > 0.75 {
                        1.0 / 3.0
                    } else if rho < 0.25 {
                        2.0
                    } else {
                        1.0
                    };
                    lambda = lambda.max(1.0e-15);
                    let step_small = delta.norm()
                        <= options.step_tolerance
                            * (x.iter().map(|v| v * v).sum::<f64>().sqrt() + 1e-12);
                    let cost_small = cost - new_cost <= options.cost_tolerance * cost;
                    x = candidate;
                    let (j2, r2, c2) = self.normal_equations(&x);
                    jtj = j2;
                    jtr = r2;
                    cost = c2;
                    accepted = true;
                    if step_small || cost_small {
                        converged = true;
                    }
                    break;
                }
                lambda *= 4.0;
                if lambda > 1.0e16 {
                    break;
                }
            }
            if !accepted {
                // No step lowers the cost: a minimum to working precision.
                converged = true;
                break;
            }
            if converged {
                break;
            }
        }
        LmResult {
            x,
            cost,
            initial_cost,
            iterations,
            converged,
            residual_count: self.residual_count(),
            free_count: self.fixed.iter().filter(|f| !**f).count(),
            jtj,
        }
    }
}

/// The covariance of the free parameters at a solution, `s² (JᵀJ)⁻¹` with
/// `s² = 2·cost / (m - n)` (the a-posteriori variance factor), through a
/// symmetric eigen-decomposition: directions with eigenvalues below `1e-12` of the
/// largest are unconstrained and get infinite variance. Fixed parameters get 0.
pub fn covariance(result: &LmResult, fixed: &[bool]) -> DMatrix<f64> {
    let free: Vec<usize> = (0..fixed.len()).filter(|&i| !fixed[i]).collect();
    let k = free.len();
    let mut out = DMatrix::zeros(fixed.len(), fixed.len());
    if k == 0 {
        return out;
    }
    let mut a = DMatrix::zeros(k, k);
    for (r, &i) in free.iter().enumerate() {
        for (c, &j) in free.iter().enumerate() {
            a[(r, c)] = result.jtj[(i, j)];
        }
    }
    // Scale to unit diagonal so the eigenvalue cut is unit-free.
    let d: Vec<f64> = (0..k)
        .map(|i| {
            let v = a[(i, i)];
            if v > 0.0 && v.is_finite() {
                1.0 / v.sqrt()
            } else {
                0.0
            }
        })
        .collect();
    for r in 0..k {
        for c in 0..k {
            a[(r, c)] *= d[r] * d[c];
        }
    }
    let dof = result
        .residual_count
        .saturating_sub(result.free_count)
        .max(1) as f64;
    let s2 = 2.0 * result.cost / dof;
    let eig = a.symmetric_eigen();
    let max_eig = eig.eigenvalues.iter().copied().fold(0.0f64, f64::max);
    let mut inv = DMatrix::zeros(k, k);
    let mut singular = vec![false; k];
    for (e, col) in eig.eigenvalues.iter().zip(eig.eigenvectors.column_iter()) {
        if *e > 1.0e-12 * max_eig && *e > 0.0 {
            inv += (col * col.transpose()) / *e;
        } else {
            for (i, v) in col.iter().enumerate() {
                if v.abs() > 1.0e-3 {
                    singular[i] = true;
                }
            }
        }
    }
    for r in 0..k {
        for c in 0..k {
            let v = if singular[r] || singular[c] || d[r] == 0.0 || d[c] == 0.0 {
                if r == c { f64::INFINITY } else { 0.0 }
            } else {
                inv[(r, c)] * d[r] * d[c] * s2
            };
            out[(free[r], free[c])] = v;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fits_an_exponential_and_reports_its_uncertainty() {
        // y = a exp(b t) with known noise-free data: the fit recovers (a, b).
        let ts: Vec<f64> = (0..20).map(|i| f64::from(i) * 0.1).collect();
        let ys: Vec<f64> = ts.iter().map(|t| 2.0 * (-1.3 * t).exp()).collect();
        let blocks = ts
            .iter()
            .zip(&ys)
            .map(|(&t, &y)| Block {
                params: vec![0, 1],
                residuals: 1,
                eval: Box::new(move |p: &[f64], r: &mut [f64]| r[0] = p[0] * (p[1] * t).exp() - y),
                class: 0,
            })
            .collect();
        let problem = Problem {
            blocks,
            scale: vec![1.0, 1.0],
            fixed: vec![false, false],
        };
        let result = problem.solve(&[1.0, 0.0], &LmOptions::default());
        assert!(result.converged);
        assert!((result.x[0] - 2.0).abs() < 1e-8 && (result.x[1] + 1.3).abs() < 1e-8);
        let cov = covariance(&result, &problem.fixed);
        assert!(cov[(0, 0)].is_finite() && cov[(0, 0)] >= 0.0);
    }

    #[test]
    fn an_unconstrained_parameter_gets_infinite_variance() {
        // r = p0 + p1 - 1: only the sum is fixed by the data.
        let blocks = (0..5)
            .map(|_| Block {
                params: vec![0, 1],
                residuals: 1,
                eval: Box::new(|p: &[f64], r: &mut [f64]| r[0] = p[0] + p[1] - 1.0),
                class: 0,
            })
            .collect();
        let problem = Problem {
            blocks,
            scale: vec![1.0, 1.0],
            fixed: vec![false, false],
        };
        let result = problem.solve(&[0.0, 0.0], &LmOptions::default());
        let cov = covariance(&result, &problem.fixed);
        assert!(cov[(0, 0)].is_infinite() && cov[(1, 1)].is_infinite());
    }
}
