//! The photometric pass of an evaluation: the geometry's pairs observed in the
//! targets' EO images, brightness-compensated, robustly weighted and reduced into
//! normal equations in the geometric residuals' units; and the ambiguity check of
//! the directions it fixed.

use nalgebra::{Matrix6, SymmetricEigen, Vector6};
use texel::Pose;

use super::{Evaluation, MAX_TARGETS, Problem, robust_scale_of};
use crate::associate::TargetView;
use crate::config::AlignConfig;
use crate::kernel;
use crate::normal_eq::{DegenerateDirection, NormalEquations, Step, map_chunks, map_each};
use crate::photometric::ambiguity::{SIDE_SAMPLES, Verdict, judge};
use crate::photometric::{Brightness, Observation, fit_brightness, observe};
use crate::se3;

/// Most pairs the ambiguity profile reads (evenly subsampled).
const PROFILE_MAX_PAIRS: usize = 768;
/// Truncation of the profile's cost, in robust scales.
const PROFILE_TRUNCATION: f64 = 3.0;
/// A profile point with fewer observations than this fraction of the estimate's
/// has no say.
const PROFILE_MIN_COVERAGE: f64 = 0.5;

/// What the images' noise sets for one target's residuals.
#[derive(Debug, Clone, Copy)]
pub(super) struct NoiseTerms {
    inv_sigma: f64,
    /// Per level pixel.
    min_gradient: f64,
}

/// The photometric sums of one evaluation.
#[derive(Debug, Clone, Default)]
pub(super) struct PhotometricSums {
    pub total: NormalEquations,
    pub per_target: Vec<NormalEquations>,
    pub residuals: usize,
    pub scale: f64,
    pub brightness: Vec<Brightness>,
}

impl Problem<'_> {
    /// Observes every paired sample in its target's EO image, fits each target's
    /// brightness change, and reduces the robustly weighted residuals. Weights carry
    /// `(s_g / s_p)²` so that the sum with the geometric equations is information in
    /// one unit (the covariance is `s_g² H⁻¹` for both).
    pub(super) fn photometric_sums(
        &self,
        views: &[TargetView<'_>],
        pairs: &[(u32, u8)],
        geometric_scale: f64,
        config: &AlignConfig,
    ) -> PhotometricSums {
        let n_targets = self.targets.len().min(MAX_TARGETS);
        let terms = self.noise_terms(self.eo_level, config);
        let observations: Vec<Vec<Observation>> = map_chunks(pairs, config.parallel, |chunk| {
            chunk
                .iter()
                .filter_map(|&(i, t)| self.observe_pair(views, i, t, self.eo_level, &terms))
                .collect()
        });
        let all = || observations.iter().flatten();
        // Brightness per target, from that target's observations.
        let brightness: Vec<Brightness> = (0..n_targets)
            .map(|t| {
                let (mut s, mut d): (Vec<f64>, Vec<f64>) = all()
                    .filter(|o| usize::from(o.target) == t)
                    .map(|o| (o.source_intensity, o.target_intensity))
                    .unzip();
                fit_brightness(&mut s, &mut d)
            })
            .collect();
        let inv_sigma = |o: &Observation| {
            terms
                .get(usize::from(o.target))
                .map_or(0.0, |t| t.inv_sigma)
        };
        let residual = |o: &Observation| {
            let b = brightness
                .get(usize::from(o.target))
                .copied()
                .unwrap_or_default();
            (o.target_intensity - (b.gain * o.source_intensity + b.bias)) * inv_sigma(o)
        };
        let scale = robust_scale_of(all().map(residual));
        let ratio = (geometric_scale / scale).powi(2);
        let kernel_kind = config.kernel;
        let kernel_k = config.kernel_threshold();
        let cut = config.photometric.outlier_scales;
        let per_chunk = map_each(&observations, config.parallel, |group| {
            let mut sums = [NormalEquations::default(); MAX_TARGETS];
            for o in group {
                let r = residual(o);
                let e = r / scale;
                if !(e.abs() <= cut) {
                    continue;
                }
                let w = kernel::weight(kernel_kind, kernel_k, e) * ratio;
                let j = o.jacobian.map(|x| x * inv_sigma(o));
                let t = usize::from(o.target).min(MAX_TARGETS - 1);
                sums[t].add(&j, r, w, 0.0);
            }
            sums
        });
        let mut per_target = vec![NormalEquations::default(); n_targets];
        for sums in &per_chunk {
            for (t, eq) in per_target.iter_mut().enumerate() {
                eq.merge(&sums[t]);
            }
        }
        let mut total = NormalEquations::default();
        for eq in &per_target {
            total.merge(eq);
        }
        if total.count < config.photometric.min_residuals as usize {
            // Too few to be a texture: the term constrains nothing.
            total = NormalEquations::default();
            per_target
                .iter_mut()
                .for_each(|eq| *eq = NormalEquations::default());
        }
        PhotometricSums {
            residuals: total.count,
            total,
            per_target,
            scale,
            brightness,
        }
    }

    /// Per target at `eo_level`: the residuals' sigma (the two images' noise, at
    /// least the configured floor) and the gradient a pixel needs.
    fn noise_terms(&self, eo_level: usize, config: &AlignConfig) -> Vec<NoiseTerms> {
        let p = &config.photometric;
        let source = self.source_eo.map_or(0.0, |eo| eo.noise_sigma(eo_level));
        let level_scale = f64::from(1u32 << eo_level.min(16));
        self.targets
            .iter()
            .map(|t| {
                let target = t
                    .pyramid
                    .eo
                    .as_ref()
                    .map_or(0.0, |eo| eo.noise_sigma(eo_level));
                let sigma = source.hypot(target).max(p.intensity_sigma);
                NoiseTerms {
                    inv_sigma: 1.0 / sigma,
                    min_gradient: (p.gradient_snr * target).max(p.min_gradient / level_scale),
                }
            })
            .collect()
    }

    /// The source's EO value at each sample, at the problem's EO level (read once).
    fn source_intensities(&self) -> &[Option<f64>] {
        self.source_intensities.get_or_init(|| {
            let Some(eo) = self.source_eo else {
                return vec![None; self.samples.len()];
            };
            self.samples
                .iter()
                .map(|s| {
                    Some(
                        eo.sample(self.eo_level, &eo.project(&s.p)?.pixel)?
                            .intensity,
                    )
                })
                .collect()
        })
    }

    /// One paired sample seen by one target's EO image at `eo_level`.
    fn observe_pair(
        &self,
        views: &[TargetView<'_>],
        sample: u32,
        target: u8,
        eo_level: usize,
        terms: &[NoiseTerms],
    ) -> Option<Observation> {
        let s = self.samples.get(sample as usize)?;
        let source_intensity = if eo_level == self.eo_level {
            (*self.source_intensities().get(sample as usize)?)?
        } else {
            let eo = self.source_eo?;
            eo.sample(eo_level, &eo.project(&s.p)?.pixel)?.intensity
        };
        let view = views.get(usize::from(target))?;
        let eo = self.targets.get(usize::from(target))?.pyramid.eo.as_ref()?;
        observe(
            eo,
            eo_level,
            terms.get(usize::from(target))?.min_gradient,
            target,
            &s.p,
            source_intensity,
            &view.rotation,
            &view.translation,
        )
    }

    /// The ambiguity check (see `photometric::ambiguity`): for each weak geometric
    /// direction the photometric term made observable, the truncated photometric
    /// cost along it on both sides of `pose`, over `span_m` (scaled coordinates).
    /// A direction with a rival minimum is taken out of the observable subspace (its
    /// covariance returns to the prior's) and reported ambiguous.
    pub(super) fn check_ambiguity(
        &self,
        pose: &Pose,
        step: &mut Step,
        evaluation: &Evaluation,
        config: &AlignConfig,
        span_m: f64,
    ) -> Vec<DegenerateDirection> {
        let (Some(sums), pairs, geometry) = (
            evaluation.photometric.as_ref(),
            &evaluation.pairs,
            &evaluation.geometry,
        ) else {
            return Vec::new();
        };
        let weak = crate::normal_eq::weak_directions(
            geometry,
            self.length_m,
            config.photometric.weak_ratio,
        );
        let stride = pairs.len().div_ceil(PROFILE_MAX_PAIRS).max(1);
        let subset: Vec<(u32, u8)> = pairs.iter().step_by(stride).copied().collect();
        let mut found = Vec::new();
        for direction in weak {
            // Only directions the data now fix (not already reported degenerate).
            let still_degenerate = step
                .unobservable
                .iter()
                .any(|u| u.dot(&direction).abs() > 0.7);
            if still_degenerate {
                continue;
            }
            let (offsets, costs) = self.profile(
                pose,
                &direction,
                &subset,
                sums,
                span_m,
                &self.noise_terms(self.eo_level, config),
            );
            if let Verdict::Rival { offset_m } = judge(&offsets, &costs) {
                demote(step, &direction);
                found.push(DegenerateDirection::ambiguous_at(direction, 0.0, offset_m));
            }
        }
        found
    }

    /// The truncated mean photometric cost at `pose` moved along `direction`
    /// (scaled coordinates) by `2·SIDE_SAMPLES + 1` offsets over `±span_m`.
    fn profile(
        &self,
        pose: &Pose,
        direction: &Vector6<f64>,
        pairs: &[(u32, u8)],
        sums: &PhotometricSums,
        span_m: f64,
        terms: &[NoiseTerms],
    ) -> (Vec<f64>, Vec<f64>) {
        let d_inv = Vector6::new(
            1.0 / self.length_m,
            1.0 / self.length_m,
            1.0 / self.length_m,
            1.0,
            1.0,
            1.0,
        );
        let tangent = direction.component_mul(&d_inv);
        // The finest level the alignment read: a repeating texture's period must
        // be resolved, and the offsets are dense enough for its valleys.
        let level = self.eo_level;
        let offsets: Vec<f64> = (0..=2 * SIDE_SAMPLES)
            .map(|k| (k as f64 - SIDE_SAMPLES as f64) * span_m / SIDE_SAMPLES as f64)
            .collect();
        let mut counts = Vec::with_capacity(offsets.len());
        let mut costs = Vec::with_capacity(offsets.len());
        let truncation = PROFILE_TRUNCATION * PROFILE_TRUNCATION;
        for &t in &offsets {
            let moved = pose * se3::exp(&(tangent * t));
            let views = self.views(&moved);
            let (mut sum, mut n) = (0.0, 0usize);
            for &(i, target) in pairs {
                let Some(o) = self.observe_pair(&views, i, target, level, terms) else {
                    continue;
                };
                let b = sums
                    .brightness
                    .get(usize::from(target))
                    .copied()
                    .unwrap_or_default();
                let inv_sigma = terms.get(usize::from(target)).map_or(0.0, |t| t.inv_sigma);
                let e = (o.target_intensity - (b.gain * o.source_intensity + b.bias)) * inv_sigma
                    / sums.scale;
                sum += (e * e).min(truncation);
                n += 1;
            }
            counts.push(n);
            costs.push(if n > 0 { sum / n as f64 } else { f64::NAN });
        }
        let centre = counts.get(SIDE_SAMPLES).copied().unwrap_or(0);
        for (c, &n) in costs.iter_mut().zip(&counts) {
            if (n as f64) < PROFILE_MIN_COVERAGE * centre as f64 {
                *c = f64::NAN;
            }
        }
        (offsets, costs)
    }
}

/// Moves `direction` (scaled coordinates) from the step's observable subspace to its
/// unobservable one.
pub(super) fn demote(step: &mut Step, direction: &Vector6<f64>) {
    let mut v = *direction;
    for u in &step.unobservable {
        v -= u * u.dot(&v);
    }
    let norm = v.norm();
    if !(norm > 1.0e-6) {
        return;
    }
    let v = v / norm;
    let away = Matrix6::identity() - v * v.transpose();
    let projector: Matrix6<f64> = step.observable.iter().map(|o| o * o.transpose()).sum();
    let eigen = SymmetricEigen::new(away * projector * away);
    step.observable = (0..6)
        .filter(|&i| eigen.eigenvalues[i] > 0.5)
        .map(|i| eigen.eigenvectors.column(i).into_owned())
        .collect();
    step.unobservable.push(v);
}
