//! The `plumb_bob` lens distortion model (Brown-Conrady: k1, k2, k3 radial; p1, p2
//! tangential) on normalised image coordinates, its valid domain, and its inversion.
//!
//! Forward model (normalised undistorted `(x, y)` to normalised distorted `(xd, yd)`),
//! with `r² = x² + y²`:
//!
//! ```text
//! radial = 1 + k1 r² + k2 r⁴ + k3 r⁶
//! xd = x·radial + 2 p1 x y + p2 (r² + 2x²)
//! yd = y·radial + p1 (r² + 2y²) + 2 p2 x y
//! ```
//!
//! The polynomial is only a lens model where the radial map `ρ(r) = r·radial(r)` still
//! grows with `r`: beyond the first zero of `ρ'(r)` the image folds back on itself, so a
//! distorted pixel there has two preimages and neither is trustworthy. That first zero
//! bounds the **valid domain** `r < r_max`; projection refuses points outside it and
//! undistortion reports pixels it cannot reach from inside it. The tangential terms
//! bend the fold towards the centre on some sides, so the bound also keeps the radial
//! map's slope above the most the tangential terms can take away (`fold_margin`): the
//! whole disc is then free of folds, not only its radial profile.

use nalgebra::{Matrix2, Vector2};
use serde::{Deserialize, Serialize};

/// Coefficients of the `plumb_bob` model, `D = [k1, k2, p1, p2, k3]` as in the capture
/// format.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlumbBob {
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
}

/// Largest normalised radius squared searched for the fold of the radial map. A
/// pinhole camera never sees rays more than ~89.9 degrees off axis (r ~ 570); past that
/// the model is called unbounded.
const DOMAIN_SEARCH_MAX_R2: f64 = 1.0e6;

/// Undistortion stops when the distorted-coordinate residual is below this (normalised
/// units; ~1e-9 px for focal lengths up to 1e3 px).
const UNDISTORT_TOLERANCE: f64 = 1.0e-13;

/// Iterations of the radial preimage that starts undistortion (safeguarded Newton;
/// bisection alone would need about 60 for full precision).
const RADIAL_START_ITERATIONS: u32 = 64;

/// Why a distorted point could not be undistorted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum UndistortFailure {
    /// No point inside the valid domain maps to this distorted point.
    OutsideDomain,
    /// The iteration did not reach the tolerance within its iteration budget.
    NotConverged { residual: f64 },
}

impl PlumbBob {
    /// The model as the capture format writes it: `[k1, k2, p1, p2, k3]`.
    pub fn to_array(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// From `D`; the capture format allows 5 coefficients (fewer are zero-padded, as
    /// ROS and OpenCV do for `[k1, k2, p1, p2]`).
    pub fn from_slice(d: &[f64]) -> Option<Self> {
        if d.len() > 5 || d.len() < 4 {
            return None;
        }
        Some(Self {
            k1: d[0],
            k2: d[1],
            p1: d[2],
            p2: d[3],
            k3: d.get(4).copied().unwrap_or(0.0),
        })
    }

    pub fn is_finite(&self) -> bool {
        self.to_array().iter().all(|c| c.is_finite())
    }

    /// True when every coefficient is zero (the model is the identity).
    pub fn is_identity(&self) -> bool {
        self.to_array().iter().all(|&c| c == 0.0)
    }

    /// `ρ'(r)/1` as a polynomial in `s = r²`: `1 + 3 k1 s + 5 k2 s² + 7 k3 s³`.
    fn radial_slope(&self, s: f64) -> f64 {
        1.0 + s * (3.0 * self.k1 + s * (5.0 * self.k2 + s * 7.0 * self.k3))
    }

    /// How far the map is from folding at `s = r²`, a lower bound on the smallest
    /// singular value of its Jacobian anywhere on the circle `r`: the radial part's
    /// is `min(radial, ρ')` (tangentially and radially), and the tangential part
    /// `2 (q'·v) v + r² q'` (with `q' = (p2, p1)`) has a Jacobian of norm at most
    /// `6 r |q|`.
    fn fold_margin(&self, s: f64) -> f64 {
        let radial = 1.0 + s * (self.k1 + s * (self.k2 + s * self.k3));
        let tangential = 6.0 * s.max(0.0).sqrt() * self.p1.hypot(self.p2);
        radial.min(self.radial_slope(s)) - tangential
    }

    /// The valid domain's bound `r_max²`: the first `s > 0` where the map may stop
    /// being locally invertible (the radial map stops growing, or the tangential
    /// terms could outweigh it: see `fold_margin`), or `None` when it stays
    /// invertible over every radius a pinhole camera can see. Without tangential
    /// terms this is exactly the first zero of `ρ'`.
    pub fn max_radius_squared(&self) -> Option<f64> {
        // Bracket the first sign change on a geometric grid (the margin is a cubic in
        // s less a multiple of √s, so it changes sign only a few times; a 5 % grid
        // cannot step over the first of a pair that are far apart relative to their
        // size), then bisect.
        let mut lo = 0.0;
        let mut hi = 1.0e-4;
        while hi <= DOMAIN_SEARCH_MAX_R2 {
            if self.fold_margin(hi) <= 0.0 {
                for _ in 0..200 {
                    let mid = 0.5 * (lo + hi);
                    if self.fold_margin(mid) > 0.0 {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                // `lo` is the last radius where the map still grows.
                return Some(lo);
            }
            lo = hi;
            hi *= 1.05;
        }
        None
    }

    /// Distorts a normalised point. Pure arithmetic: finite in, finite out for finite
    /// coefficients (callers check the domain separately).
    #[inline]
    pub fn distort(&self, p: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xy = x * y;
        Vector2::new(
            x * radial + 2.0 * self.p1 * xy + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * xy,
        )
    }

    /// The undistortion's starting point: `distorted` scaled to the radius `r` inside
    /// the valid domain where the radial map alone reaches its radius, `ρ(r) = |d|`
    /// (safeguarded Newton on the monotone branch, so it cannot leave the bracket).
    /// Where the radial map does not reach that far inside the domain, half the
    /// domain's radius squared (the iteration then reports the point as outside).
    fn radial_start(&self, distorted: Vector2<f64>, max_r2: Option<f64>) -> Vector2<f64> {
        let target = distorted.norm();
        if target <= 0.0 || !target.is_finite() {
            return distorted;
        }
        let rho = |r: f64| r * (1.0 + r * r * (self.k1 + r * r * (self.k2 + r * r * self.k3)));
        let mut hi = max_r2.map_or(DOMAIN_SEARCH_MAX_R2, |m| m.max(0.0)).sqrt();
        if rho(hi) <= target {
            return match max_r2 {
                Some(m) => distorted * (0.5 * m).sqrt() / target,
                None => distorted,
            };
        }
        // rho(0) = 0 < target < rho(hi), and rho grows on [0, hi].
        let mut lo = 0.0;
        let mut r = target.min(0.5 * hi);
        for _ in 0..RADIAL_START_ITERATIONS {
            let g = rho(r) - target;
            if g.abs() <= UNDISTORT_TOLERANCE * (1.0 + target) {
                break;
            }
            if g < 0.0 {
                lo = r;
            } else {
                hi = r;
            }
            // The slope is positive inside the bracket; a step that leaves it (or a
            // slope too flat to trust) falls back to bisection.
            let slope = self.radial_slope(r * r);
            let newton = r - g / slope;
            r = if slope > 0.0 && newton > lo && newton < hi {
                newton
            } else {
                0.5 * (lo + hi)
            };
        }
        distorted * (r / target)
    }

    /// The Jacobian of [`Self::distort`] with respect to `(x, y)`.
    pub fn jacobian(&self, p: Vector2<f64>) -> Matrix2<f64> {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d(radial)/d(r2)
        let d_radial = self.k1 + r2 * (2.0 * self.k2 + r2 * 3.0 * self.k3);
        let dxd_dx = radial + 2.0 * x * x * d_radial + 2.0 * self.p1 * y + 6.0 * self.p2 * x;
        let dxd_dy = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dyd_dx = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dyd_dy = radial + 2.0 * y * y * d_radial + 6.0 * self.p1 * y + 2.0 * self.p2 * x;
        Matrix2::new(dxd_dx, dxd_dy, dyd_dx, dyd_dy)
    }

    /// Inverts [`Self::distort`] by damped Newton iteration inside the valid domain.
    ///
    /// `max_r2` is [`Self::max_radius_squared`] (passed in so callers compute it once).
    /// The iteration count is bounded by `max_iterations`; a point that does not
    /// converge is reported, never returned half-solved.
    pub fn undistort(
        &self,
        distorted: Vector2<f64>,
        max_r2: Option<f64>,
        max_iterations: u32,
    ) -> Result<Vector2<f64>, UndistortFailure> {
        if !distorted.x.is_finite() || !distorted.y.is_finite() {
            return Err(UndistortFailure::NotConverged {
                residual: f64::INFINITY,
            });
        }
        let inside = |p: &Vector2<f64>| max_r2.is_none_or(|m| p.norm_squared() < m);
        // Start from the radial model's own preimage, on the monotone branch: starting
        // from the distorted point itself can put a pincushion lens's first Newton
        // step next to the fold, where the Jacobian is nearly singular and the step
        // throws the iterate out of the domain.
        let mut p = self.radial_start(distorted, max_r2);
        let mut residual = self.distort(p) - distorted;
        for _ in 0..max_iterations {
            let residual_norm = residual.norm();
            if residual_norm < UNDISTORT_TOLERANCE * (1.0 + distorted.norm()) {
                return Ok(p);
            }
            let Some(step) = self.jacobian(p).try_inverse().map(|inv| -(inv * residual)) else {
                // A singular Jacobian only happens on the domain's edge.
                return Err(UndistortFailure::OutsideDomain);
            };
            // Backtrack until the step stays inside the domain and reduces the residual.
            let mut scale = 1.0;
            let mut accepted = false;
            for _ in 0..40 {
                let candidate = p + step * scale;
                if inside(&candidate) {
                    let candidate_residual = self.distort(candidate) - distorted;
                    if candidate_residual.norm() < residual_norm {
                        p = candidate;
                        residual = candidate_residual;
                        accepted = true;
                        break;
                    }
                }
                scale *= 0.5;
            }
            if !accepted {
                // No step inside the domain gets closer: the target lies beyond the
                // image of the domain (or on its rim).
                return Err(if max_r2.is_some() {
                    UndistortFailure::OutsideDomain
                } else {
                    UndistortFailure::NotConverged {
                        residual: residual_norm,
                    }
                });
            }
        }
        let residual_norm = residual.norm();
        if residual_norm < UNDISTORT_TOLERANCE * (1.0 + distorted.norm()) {
            Ok(p)
        } else {
            Err(UndistortFailure::NotConverged {
                residual: residual_norm,
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn barrel() -> PlumbBob {
        PlumbBob {
            k1: -0.3,
            k2: 0.1,
            p1: 0.001,
            p2: -0.0005,
            k3: 0.0,
        }
    }

    /// Inside the domain the map never folds, tangential terms included: the
    /// Jacobian's determinant stays positive on every circle up to the bound, for
    /// lenses whose tangential terms bend the fold inwards (the radial-only bound of
    /// the strong barrel lens lies where its determinant is already negative).
    #[test]
    fn the_domain_is_fold_free_with_tangential_terms() {
        let lenses = [
            PlumbBob {
                k1: -0.362,
                k2: 0.0588,
                p1: -0.00365,
                p2: 0.00227,
                k3: 0.000128,
            },
            PlumbBob {
                k1: 0.198,
                k2: 0.016,
                p1: 0.0,
                p2: -0.00334,
                k3: -0.0298,
            },
            barrel(),
        ];
        for d in lenses {
            // Unbounded lenses are checked out to r = 3.
            let m = d.max_radius_squared().unwrap_or(9.0);
            for i in 1..=200 {
                let r = m.sqrt() * f64::from(i) / 200.0 * (1.0 - 1e-9);
                for k in 0..360 {
                    let a = f64::from(k).to_radians();
                    let det = d
                        .jacobian(Vector2::new(r * a.cos(), r * a.sin()))
                        .determinant();
                    assert!(det > 0.0, "{d:?}: det {det} at r {r}, {k} deg");
                }
            }
        }
        // The first lens's radial map never stops growing (its slope dips to 0.0006 at
        // r 1.36), so a radial-only bound would call every radius valid; with its
        // tangential terms the map folds within r 1.5 on some side.
        let d = lenses[0];
        let radial_only = PlumbBob {
            p1: 0.0,
            p2: 0.0,
            ..d
        };
        assert_eq!(radial_only.max_radius_squared(), None);
        let folds = (1..=150).any(|i| {
            let r = f64::from(i) / 100.0;
            (0..360).any(|k| {
                let a = f64::from(k).to_radians();
                d.jacobian(Vector2::new(r * a.cos(), r * a.sin()))
                    .determinant()
                    <= 0.0
            })
        });
        assert!(folds);
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let d = barrel();
        let p = Vector2::new(0.31, -0.22);
        let j = d.jacobian(p);
        let h = 1e-7;
        for c in 0..2 {
            let mut e = Vector2::zeros();
            e[c] = h;
            let numeric = (d.distort(p + e) - d.distort(p - e)) / (2.0 * h);
            for r in 0..2 {
                assert!((numeric[r] - j[(r, c)]).abs() < 1e-6, "{r},{c}");
            }
        }
    }

    #[test]
    fn pure_barrel_domain_matches_the_analytic_fold() {
        // rho(r) = r (1 + k1 r²): rho' = 1 + 3 k1 r² = 0 at r² = -1/(3 k1).
        let d = PlumbBob {
            k1: -0.4,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        };
        let m = d.max_radius_squared().unwrap();
        assert!((m - 1.0 / 1.2).abs() < 1e-9, "{m}");
    }

    #[test]
    fn pincushion_has_no_fold() {
        let d = PlumbBob {
            k1: 0.2,
            k2: 0.05,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        };
        assert_eq!(d.max_radius_squared(), None);
    }

    #[test]
    fn undistort_inverts_distort() {
        let d = barrel();
        let m = d.max_radius_squared();
        for &(x, y) in &[(0.0, 0.0), (0.5, 0.3), (-0.7, 0.6), (0.01, -0.9)] {
            let p = Vector2::new(x, y);
            if m.is_some_and(|m| p.norm_squared() >= m) {
                continue;
            }
            let back = d.undistort(d.distort(p), m, 50).unwrap();
            assert!((back - p).norm() < 1e-12, "{p:?} -> {back:?}");
        }
    }

    #[test]
    fn beyond_the_fold_is_reported() {
        let d = PlumbBob {
            k1: -0.4,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        };
        let m = d.max_radius_squared();
        // The largest distorted radius the model reaches is rho(r_max) ~ 0.608.
        let err = d.undistort(Vector2::new(0.7, 0.0), m, 50).unwrap_err();
        assert_eq!(err, UndistortFailure::OutsideDomain);
    }
}
