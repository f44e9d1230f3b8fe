//! The 6x6 normal equations of a step, reduced in a fixed order, and their solution
//! with degeneracy analysis and solution remapping (Zhang, Kaess & Singh 2016).

use nalgebra::{DMatrix, DVector, Matrix6, SymmetricEigen, Vector6};
use rayon::prelude::*;
use serde::Serialize;

/// Items per reduction chunk. Fixed, so the chunk boundaries (and with them every
/// floating-point sum) do not depend on how many threads run.
pub const CHUNK: usize = 512;

/// Maps fixed-size chunks of `items` and combines the results in chunk order,
/// on the rayon pool or on this thread: bit-identical either way.
pub fn map_chunks<T, A, F>(items: &[T], parallel: bool, map: F) -> Vec<A>
where
    T: Sync,
    A: Send,
    F: Fn(&[T]) -> A + Sync + Send,
{
    if parallel && items.len() > CHUNK {
        items.par_chunks(CHUNK).map(map).collect()
    } else {
        items.chunks(CHUNK).map(map).collect()
    }
}

/// Maps every item (chunk results, already fixed in number and order) and returns
/// the results in item order, on the rayon pool or on this thread.
pub fn map_each<T, A, F>(items: &[T], parallel: bool, map: F) -> Vec<A>
where
    T: Sync,
    A: Send,
    F: Fn(&T) -> A + Sync + Send,
{
    if parallel && items.len() > 1 {
        items.par_iter().map(map).collect()
    } else {
        items.iter().map(map).collect()
    }
}

/// `Σ w JᵀJ` (upper triangle), `Σ w Jᵀr`, and the robust cost, accumulated
/// sequentially.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NormalEquations {
    /// Upper triangle, row by row.
    pub h: [f64; 21],
    pub g: [f64; 6],
    pub cost: f64,
    pub count: usize,
}

impl Default for NormalEquations {
    fn default() -> Self {
        Self {
            h: [0.0; 21],
            g: [0.0; 6],
            cost: 0.0,
            count: 0,
        }
    }
}

impl NormalEquations {
    /// Adds one residual `r` with Jacobian row `j` and weight `w`.
    #[inline]
    pub fn add(&mut self, j: &[f64; 6], r: f64, w: f64, cost: f64) {
        let mut k = 0;
        for a in 0..6 {
            let wa = w * j[a];
            for jb in &j[a..] {
                self.h[k] += wa * jb;
                k += 1;
            }
            self.g[a] += wa * r;
        }
        self.cost += cost;
        self.count += 1;
    }

    /// Adds another accumulation (used in chunk order only).
    pub fn merge(&mut self, other: &Self) {
        for (a, b) in self.h.iter_mut().zip(other.h.iter()) {
            *a += b;
        }
        for (a, b) in self.g.iter_mut().zip(other.g.iter()) {
            *a += b;
        }
        self.cost += other.cost;
        self.count += other.count;
    }

    pub fn hessian(&self) -> Matrix6<f64> {
        let mut m = Matrix6::zeros();
        let mut k = 0;
        for a in 0..6 {
            for b in a..6 {
                m[(a, b)] = self.h[k];
                m[(b, a)] = self.h[k];
                k += 1;
            }
        }
        m
    }

    pub fn gradient(&self) -> Vector6<f64> {
        Vector6::from_column_slice(&self.g)
    }
}

/// A direction of the pose the data cannot fix.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DegenerateDirection {
    /// Unit vector in scaled tangent coordinates `(ω·L, v)` of the moving scan's
    /// frame (`L` the scene's length scale, so rotation and translation compare).
    pub direction: [f64; 6],
    /// Its eigenvalue over the largest one.
    pub eigenvalue_ratio: f64,
    /// What it is, in words: "translation along (0.00, 0.00, 1.00)" and so on.
    pub description: String,
    /// The data constrain it, but not uniquely: the photometric cost has a second
    /// minimum as deep along it (a repeating texture), `rival_offset_m` away in
    /// scaled coordinates. The result keeps the prior's uncertainty there.
    pub ambiguous: bool,
    pub rival_offset_m: f64,
}

impl DegenerateDirection {
    /// A direction the photometric term fixed, but at one of several equally good
    /// positions.
    pub fn ambiguous_at(
        direction: Vector6<f64>,
        eigenvalue_ratio: f64,
        rival_offset_m: f64,
    ) -> Self {
        let plain = Self::new(direction, eigenvalue_ratio);
        Self {
            description: format!(
                "ambiguous (repeating texture, a second photometric minimum {:.3} m away): {}",
                rival_offset_m.abs(),
                plain.description
            ),
            ambiguous: true,
            rival_offset_m,
            ..plain
        }
    }

    fn new(direction: Vector6<f64>, eigenvalue_ratio: f64) -> Self {
        let rot = direction.fixed_rows::<3>(0).norm_squared();
        let trans = direction.fixed_rows::<3>(3).norm_squared();
        let axis = |offset: usize| {
            let v = direction.fixed_rows::<3>(offset);
            let n = v.norm();
            let u = if n > 0.0 { v / n } else { v.into_owned() };
            // Sign convention: the largest component is positive.
            let s = if u
                .iter()
                .fold(0.0f64, |m, &c| if c.abs() > m.abs() { c } else { m })
                < 0.0
            {
                -1.0
            } else {
                1.0
            };
            // Components that print as zero print without a sign.
            let c = |x: f64| if (s * x).abs() < 0.005 { 0.0 } else { s * x };
            format!("({:.2}, {:.2}, {:.2})", c(u[0]), c(u[1]), c(u[2]))
        };
        let description = if trans >= 0.9 {
            format!("translation along {}", axis(3))
        } else if rot >= 0.9 {
            format!("rotation about {}", axis(0))
        } else {
            format!(
                "rotation about {} with translation along {}",
                axis(0),
                axis(3)
            )
        };
        Self {
            direction: [
                direction[0],
                direction[1],
                direction[2],
                direction[3],
                direction[4],
                direction[5],
            ],
            eigenvalue_ratio,
            description,
            ambiguous: false,
            rival_offset_m: 0.0,
        }
    }
}

/// The solution of one step.
#[derive(Debug, Clone)]
pub struct Step {
    /// The update `δ = (ω, v)`, zero along degenerate directions.
    pub delta: Vector6<f64>,
    /// Directions neither the geometry nor the photometric term (where it was used)
    /// fixes: the prior keeps them.
    pub degenerate: Vec<DegenerateDirection>,
    /// Orthonormal bases (scaled coordinates, as columns) of the observable and the
    /// degenerate subspaces.
    pub observable: Vec<Vector6<f64>>,
    pub unobservable: Vec<Vector6<f64>>,
    /// Scaled weighted normal matrix, for the covariance.
    pub hessian_scaled: Matrix6<f64>,
    /// The subspace the photometric term was admitted in (scaled coordinates): the
    /// geometry's weak directions under the selective mode, all six under the full
    /// one, none without it.
    pub photometric_subspace: Vec<Vector6<f64>>,
    /// Smallest eigenvalue of the scaled information, geometry alone and with the
    /// photometric term added where it was admitted.
    pub geometry_min_eigenvalue: f64,
    pub min_eigenvalue: f64,
}

/// The photometric normal equations and where they may act.
#[derive(Debug, Clone, Copy)]
pub struct PhotometricEquations<'a> {
    /// Weighted, in the geometric residuals' units (see `align`).
    pub equations: &'a NormalEquations,
    /// `Some(r)`: only in the directions whose geometric eigenvalue ratio is below
    /// `r` (the selective mode); `None`: everywhere.
    pub weak_ratio: Option<f64>,
}

/// `D = diag(L, L, L, 1, 1, 1)`: scaled coordinates `δ' = D δ` put rotations in metres
/// of motion at the scene's scale.
fn scaling(length_m: f64) -> Vector6<f64> {
    Vector6::new(length_m, length_m, length_m, 1.0, 1.0, 1.0)
}

fn scaled(h: &Matrix6<f64>, d_inv: &Vector6<f64>) -> Matrix6<f64> {
    Matrix6::from_fn(|a, b| h[(a, b)] * d_inv[a] * d_inv[b])
}

/// Eigen-directions of the scaled geometric information whose eigenvalue over the
/// largest is below `ratio` (all six without information).
pub fn weak_directions(geometry: &NormalEquations, length_m: f64, ratio: f64) -> Vec<Vector6<f64>> {
    let d_inv = scaling(length_m).map(|x| 1.0 / x);
    let eigen = SymmetricEigen::new(scaled(&geometry.hessian(), &d_inv));
    let lambda_max = eigen.eigenvalues.max();
    (0..6)
        .filter(|&i| {
            let lambda = eigen.eigenvalues[i];
            !(lambda_max.is_finite() && lambda_max > 0.0 && lambda / lambda_max >= ratio)
        })
        .map(|i| eigen.eigenvectors.column(i).into_owned())
        .collect()
}

/// Solves `H δ = -g` in the observable subspace only.
///
/// Zhang, Kaess & Singh (2016), Sec. IV-V: the eigenvectors of the normal matrix whose
/// eigenvalues fall below `threshold · λ_max` span directions the constraints do not
/// fix; the update is confined to the other eigenvectors ("solution remapping",
/// `δ = V_f⁻¹ V_u δ_u`, for a symmetric matrix the projection onto the
/// well-conditioned eigenvectors), so the estimate keeps its prior (the initial
/// guess) there. Observability is a property of the data, so it is judged on
/// `geometry` (every gated pair with weight 1) plus the photometric information
/// where it is admitted: a robust kernel that has not yet admitted the few points
/// constraining a weak direction must not make it look unobservable. The
/// photometric term is admitted in the geometry's weak subspace only (selective
/// mode, `P H_p P` with `P` the projector onto it) or everywhere (full mode). The
/// step solves the robustly `weighted` system (plus the admitted photometric one)
/// restricted to the observable subspace, with `damping` (Levenberg-Marquardt) on
/// its diagonal. The analysis runs in scaled coordinates (`length_m` converts
/// radians to metres) so that rotation and translation eigenvalues compare.
pub fn solve_remapped(
    weighted: &NormalEquations,
    geometry: &NormalEquations,
    photometric: Option<PhotometricEquations<'_>>,
    length_m: f64,
    threshold: f64,
    damping: f64,
) -> Step {
    let d = scaling(length_m);
    let d_inv = d.map(|x| 1.0 / x);
    let h_geometry = scaled(&geometry.hessian(), &d_inv);
    let mut h_weighted = scaled(&weighted.hessian(), &d_inv);
    let mut g_weighted = weighted.gradient().component_mul(&d_inv);
    let geometry_eigen = SymmetricEigen::new(h_geometry);
    let geometry_min_eigenvalue = geometry_eigen.eigenvalues.min().max(0.0);
    // The photometric term, projected onto the subspace it is admitted in.
    let mut h_information = h_geometry;
    let mut photometric_subspace = Vec::new();
    if let Some(p) = photometric.filter(|p| p.equations.count > 0) {
        photometric_subspace = match p.weak_ratio {
            Some(ratio) => weak_directions(geometry, length_m, ratio),
            None => (0..6).map(|i| Vector6::ith(i, 1.0)).collect(),
        };
        if !photometric_subspace.is_empty() {
            let projector: Matrix6<f64> =
                photometric_subspace.iter().map(|v| v * v.transpose()).sum();
            let h_p = projector * scaled(&p.equations.hessian(), &d_inv) * projector;
            let g_p = projector * p.equations.gradient().component_mul(&d_inv);
            if h_p.iter().chain(g_p.iter()).all(|c| c.is_finite()) {
                h_information += h_p;
                h_weighted += h_p;
                g_weighted += g_p;
            } else {
                photometric_subspace.clear();
            }
        }
    }
    let eigen = SymmetricEigen::new(h_information);
    let min_eigenvalue = eigen.eigenvalues.min().max(0.0);
    let lambda_max = eigen.eigenvalues.max();
    let mut observable = Vec::new();
    let mut unobservable = Vec::new();
    let mut degenerate = Vec::new();
    for i in 0..6 {
        let lambda = eigen.eigenvalues[i];
        let v = eigen.eigenvectors.column(i).into_owned();
        // A finite, positive largest eigenvalue is needed to compare against; without
        // one (no constraints at all) every direction is degenerate.
        let ratio = if lambda_max.is_finite() && lambda_max > 0.0 {
            (lambda / lambda_max).max(0.0)
        } else {
            0.0
        };
        if ratio > threshold && lambda > 0.0 {
            observable.push(v);
        } else {
            degenerate.push(DegenerateDirection::new(v, ratio));
            unobservable.push(v);
        }
    }
    // The weighted system in the observable basis B: (Bᵀ H B) y = -Bᵀ g, δ' = B y.
    let m = observable.len();
    let mut delta_scaled = Vector6::zeros();
    if m > 0 {
        let reduced = DMatrix::from_fn(m, m, |a, b| {
            observable[a].dot(&(h_weighted * observable[b]))
        });
        let rhs = DVector::from_fn(m, |a, _| -observable[a].dot(&g_weighted));
        let reduced_eigen = SymmetricEigen::new(reduced);
        let top = reduced_eigen.eigenvalues.max();
        for k in 0..m {
            let lambda = reduced_eigen.eigenvalues[k];
            // Directions the weights left without support are not moved either.
            if !(lambda > 1.0e-12 * top.max(0.0)) || !lambda.is_finite() {
                continue;
            }
            let u = reduced_eigen.eigenvectors.column(k);
            let y = u * (u.dot(&rhs) / (lambda + damping));
            for (a, basis) in observable.iter().enumerate() {
                delta_scaled += basis * y[a];
            }
        }
    }
    let delta = delta_scaled.component_mul(&d_inv);
    let delta = if delta.iter().all(|c| c.is_finite()) {
        delta
    } else {
        Vector6::zeros()
    };
    // Ascending eigenvalue order makes reports stable.
    degenerate.sort_by(|a, b| a.eigenvalue_ratio.total_cmp(&b.eigenvalue_ratio));
    Step {
        delta,
        degenerate,
        observable,
        unobservable,
        hessian_scaled: h_weighted,
        photometric_subspace,
        geometry_min_eigenvalue,
        min_eigenvalue,
    }
}

/// The covariance of the solution in `(ω, v)` coordinates: `s²` times the inverse of
/// the weighted normal matrix within the observable subspace (`s` the residual
/// scale in noise sigmas), the prior's variance along degenerate directions, never
/// more than the prior anywhere; and its inverse, the information matrix.
pub fn covariance_and_information(
    step: &Step,
    length_m: f64,
    residual_scale: f64,
    prior_sigmas: &Vector6<f64>,
) -> (Matrix6<f64>, Matrix6<f64>) {
    let d = scaling(length_m);
    let prior_scaled = prior_sigmas.component_mul(&d).map(|s| s * s);
    let prior_var = |v: &Vector6<f64>| -> f64 {
        v.iter()
            .zip(prior_scaled.iter())
            .map(|(c, p)| c * c * p)
            .sum()
    };
    let s2 = residual_scale * residual_scale;
    let mut cov = Matrix6::zeros();
    let mut info = Matrix6::zeros();
    let mut add = |v: Vector6<f64>, var: f64| {
        let var = if var.is_finite() && var > 0.0 {
            var
        } else {
            1.0
        };
        let vv = v * v.transpose();
        cov += vv * var;
        info += vv / var;
    };
    let m = step.observable.len();
    if m > 0 {
        let reduced = DMatrix::from_fn(m, m, |a, b| {
            step.observable[a].dot(&(step.hessian_scaled * step.observable[b]))
        });
        let eigen = SymmetricEigen::new(reduced);
        for k in 0..m {
            let u = eigen.eigenvectors.column(k);
            let mut v = Vector6::zeros();
            for (a, basis) in step.observable.iter().enumerate() {
                v += basis * u[a];
            }
            let lambda = eigen.eigenvalues[k];
            let p = prior_var(&v);
            // Never more certain in a direction than the data, never less than the prior.
            let var = if lambda > 0.0 {
                (s2 / lambda).min(p)
            } else {
                p
            };
            add(v, var);
        }
    }
    for v in &step.unobservable {
        add(*v, prior_var(v));
    }
    let d_inv = d.map(|x| 1.0 / x);
    let cov = Matrix6::from_fn(|a, b| cov[(a, b)] * d_inv[a] * d_inv[b]);
    let info = Matrix6::from_fn(|a, b| info[(a, b)] * d[a] * d[b]);
    (cov, info)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_full_rank_system_is_solved_exactly() {
        let mut eq = NormalEquations::default();
        let rows = [
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            [1.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        ];
        // Residuals of δ* = (0.1, -0.2, 0.3, 0.01, 0.02, -0.03): r = -J δ*.
        let truth = Vector6::new(0.1, -0.2, 0.3, 0.01, 0.02, -0.03);
        for row in rows {
            let j = Vector6::from_column_slice(&row);
            eq.add(&row, -j.dot(&truth), 1.0, 0.0);
        }
        let step = solve_remapped(&eq, &eq, None, 1.0, 1e-6, 0.0);
        assert!(step.degenerate.is_empty());
        assert!((step.delta - truth).norm() < 1e-12);
    }

    #[test]
    fn unconstrained_directions_keep_the_prior() {
        // Only z translation and rotations about x and y are constrained (a plane).
        let mut eq = NormalEquations::default();
        for (x, y) in [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.5), (0.3, -0.7)] {
            // J = [p × n, n] for p = (x, y, 2), n = (0, 0, -1).
            let row = [-y, x, 0.0, 0.0, 0.0, -1.0];
            eq.add(&row, 0.05, 1.0, 0.0);
        }
        let step = solve_remapped(&eq, &eq, None, 2.0, 1e-6, 0.0);
        assert_eq!(step.degenerate.len(), 3);
        assert!(step.delta[2].abs() < 1e-12);
        assert!(step.delta[3].abs() < 1e-12 && step.delta[4].abs() < 1e-12);
        assert!(step.delta.iter().all(|c| c.is_finite()));
        let names: Vec<_> = step
            .degenerate
            .iter()
            .map(|d| d.description.clone())
            .collect();
        assert!(
            names.contains(&"rotation about (0.00, 0.00, 1.00)".to_string()),
            "{names:?}"
        );
        let sig = Vector6::new(0.1, 0.1, 0.1, 0.2, 0.2, 0.2);
        let (cov, info) = covariance_and_information(&step, 2.0, 1.0, &sig);
        assert!((cov[(3, 3)] - 0.04).abs() < 1e-9);
        assert!(cov.iter().chain(info.iter()).all(|c| c.is_finite()));
        assert!(((cov * info) - Matrix6::identity()).norm() < 1e-6);
    }

    #[test]
    fn no_equations_mean_no_step() {
        let step = solve_remapped(
            &NormalEquations::default(),
            &NormalEquations::default(),
            None,
            1.0,
            0.01,
            0.0,
        );
        assert_eq!(step.delta, Vector6::zeros());
        assert_eq!(step.degenerate.len(), 6);
    }

    /// A corridor-like system: every direction but x translation fixed by geometry;
    /// a photometric system constraining x translation (and, less, others).
    fn corridor_systems(photometric_weight: f64) -> (NormalEquations, NormalEquations) {
        let mut geometry = NormalEquations::default();
        for i in [0, 1, 2, 4, 5] {
            let mut row = [0.0; 6];
            row[i] = 1.0;
            for _ in 0..100 {
                geometry.add(&row, 0.0, 1.0, 0.0);
            }
        }
        let mut photometric = NormalEquations::default();
        for row in [
            [0.0, 0.1, 0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.2, 0.8, 0.3, 0.0],
            [0.1, 0.0, 0.0, 0.9, 0.0, 0.2],
        ] {
            // Residuals of a true step of 0.05 along x translation.
            let r = -0.05 * row[3];
            photometric.add(&row, r, photometric_weight, 0.0);
        }
        (geometry, photometric)
    }

    #[test]
    fn the_photometric_weight_fills_the_weak_direction_only_and_conditions_the_system() {
        let mut last_min = 0.0;
        for w in [0.0, 0.1, 1.0, 10.0, 100.0] {
            let (geometry, photometric) = corridor_systems(w);
            let selective = solve_remapped(
                &geometry,
                &geometry,
                Some(PhotometricEquations {
                    equations: &photometric,
                    weak_ratio: Some(0.01),
                }),
                1.0,
                1e-3,
                0.0,
            );
            // The geometry's smallest eigenvalue is the free axis: zero.
            assert!(selective.geometry_min_eigenvalue < 1e-9);
            // The combined one grows with the weight (monotonically)...
            assert!(selective.min_eigenvalue >= last_min, "{w}");
            last_min = selective.min_eigenvalue;
            // ... and the weak direction becomes observable once there is any: its
            // eigenvalue (2.45 w) is then above 1e-3 of the largest (100).
            if w > 0.0 {
                assert!(
                    selective.degenerate.is_empty(),
                    "{w}: {:?}",
                    selective.degenerate
                );
                // Only the axis moved, by the photometric step: the other directions
                // are the geometry's alone (their residuals are 0).
                assert!(
                    (selective.delta[3] - 0.05).abs() < 1e-9,
                    "{:?}",
                    selective.delta
                );
                for i in [0, 1, 2, 4, 5] {
                    assert!(selective.delta[i].abs() < 1e-12, "{:?}", selective.delta);
                }
                assert_eq!(selective.photometric_subspace.len(), 1);
            } else {
                assert_eq!(selective.degenerate.len(), 1);
                assert_eq!(selective.delta, Vector6::zeros());
            }
            // The full mode admits the same equations in every direction.
            let full = solve_remapped(
                &geometry,
                &geometry,
                Some(PhotometricEquations {
                    equations: &photometric,
                    weak_ratio: None,
                }),
                1.0,
                1e-3,
                0.0,
            );
            assert_eq!(full.photometric_subspace.len(), 6);
            assert_eq!(full.min_eigenvalue > 0.0, w > 0.0);
            assert!(full.delta.iter().all(|c| c.is_finite()));
        }
    }
}
