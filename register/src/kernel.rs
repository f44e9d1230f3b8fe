//! Robust kernels as IRLS weights `w(e) = ρ'(e)/e` of a residual `e` already divided
//! by its scale (Zhang 1997, "Parameter estimation techniques", Table 1).

use super::config::RobustKernel;

/// The weight of a scaled residual `e` under `kernel` with threshold `k > 0`; in
/// [0, 1], and 1 at `e = 0`. Non-finite residuals get weight 0.
#[inline]
pub fn weight(kernel: RobustKernel, k: f64, e: f64) -> f64 {
    let a = e.abs();
    if !a.is_finite() {
        return 0.0;
    }
    match kernel {
        // ρ = e²/2 inside k, k(|e| - k/2) outside.
        RobustKernel::Huber => {
            if a <= k {
                1.0
            } else {
                k / a
            }
        }
        // ρ = k²/6 (1 - (1 - (e/k)²)³) inside k, constant outside.
        RobustKernel::Tukey => {
            if a < k {
                let t = 1.0 - (a / k) * (a / k);
                t * t
            } else {
                0.0
            }
        }
        // ρ = (k² e²/2) / (k² + e²).
        RobustKernel::GemanMcclure => {
            let k2 = k * k;
            let t = k2 / (k2 + a * a);
            t * t
        }
    }
}

/// The kernel's cost `ρ(e)` (for comparing steps under Levenberg-Marquardt).
#[inline]
pub fn cost(kernel: RobustKernel, k: f64, e: f64) -> f64 {
    let a = e.abs();
    if !a.is_finite() {
        return match kernel {
            RobustKernel::Huber => f64::MAX,
            RobustKernel::Tukey => k * k / 6.0,
            RobustKernel::GemanMcclure => 0.5 * k * k,
        };
    }
    match kernel {
        RobustKernel::Huber => {
            if a <= k {
                0.5 * a * a
            } else {
                k * (a - 0.5 * k)
            }
        }
        RobustKernel::Tukey => {
            if a < k {
                let t = 1.0 - (a / k) * (a / k);
                k * k / 6.0 * (1.0 - t * t * t)
            } else {
                k * k / 6.0
            }
        }
        RobustKernel::GemanMcclure => {
            let k2 = k * k;
            0.5 * k2 * a * a / (k2 + a * a)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const ALL: [RobustKernel; 3] = [
        RobustKernel::Huber,
        RobustKernel::Tukey,
        RobustKernel::GemanMcclure,
    ];

    proptest! {
        /// w(e) = ρ'(e)/e, checked by a central difference of ρ.
        #[test]
        fn weights_are_the_derivative_of_the_cost(e in 0.01f64..20.0, k in 0.5f64..5.0) {
            for kernel in ALL {
                let h = 1e-6;
                let d = (cost(kernel, k, e + h) - cost(kernel, k, e - h)) / (2.0 * h);
                let w = weight(kernel, k, e);
                // Skip the kink of Huber / the edge of Tukey.
                if (e - k).abs() > 1e-3 {
                    prop_assert!((d / e - w).abs() < 1e-5, "{kernel:?} e={e} k={k}: {} vs {w}", d / e);
                }
                prop_assert!((0.0..=1.0).contains(&w));
            }
        }
    }

    #[test]
    fn zero_and_non_finite_residuals() {
        for kernel in ALL {
            assert_eq!(weight(kernel, 2.0, 0.0), 1.0);
            assert_eq!(weight(kernel, 2.0, f64::NAN), 0.0);
            assert_eq!(weight(kernel, 2.0, f64::INFINITY), 0.0);
            assert!(cost(kernel, 2.0, f64::NAN).is_finite());
        }
        assert_eq!(weight(RobustKernel::Tukey, 2.0, 3.0), 0.0);
    }
}
