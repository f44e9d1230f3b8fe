//! The lidar pipeline: clean echoes from a backend, then the scene's lidar effects in
//! order (mixed pixels → dropouts → range noise → quantisation), per pixel, in
//! parallel, with noise keyed by (seed, frame, pixel, stream).
//!
//! Every frame also carries the return **intensity** a flash lidar reports: the
//! range-normalised Lambertian signal `ρ · cos α` (lidar reflectivity times the
//! incidence cosine of the pixel's echo) in integer counts, [`INTENSITY_FULL_SCALE`]
//! for a white surface seen head-on, 0 where the pixel has no return. Integer counts
//! travel exactly as `mono16` in captures and as TXL1 intensities.

use rayon::prelude::*;
use texel::{Pose, RangeFrame, SensorModel};

use super::{CameraRays, RenderBackend, SurfaceSample};
use crate::effects::EffectSet;
use crate::rng::{FrameRng, Stream};

/// What the lidar pipeline needs about the lidar, computed once per simulator.
#[derive(Debug, Clone)]
pub struct LidarRays {
    /// One unit ray per pixel, the sensor's ray table (zero = invalid pixel), with its
    /// tiles.
    pub centre: CameraRays,
    /// The beam-footprint sub-rays of the `mixed_pixels` effect, when it runs.
    pub footprint: Option<CameraRays>,
    /// Angular width of one lidar pixel, radians.
    pub pixel_rad: f64,
}

/// Intensity counts of a head-on return from a surface of reflectivity 1.
pub const INTENSITY_FULL_SCALE: f32 = 10_000.0;

/// The intensity counts of an echo (see the module documentation).
#[inline]
pub fn intensity_counts(echo: &SurfaceSample) -> f32 {
    let signal = f64::from(echo.reflectivity) * echo.cos_incidence;
    let signal = if signal.is_finite() {
        signal.clamp(0.0, 1.0)
    } else {
        0.0
    };
    (signal as f32 * INTENSITY_FULL_SCALE).round()
}

/// Key of a frame's random numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NoiseKey {
    pub seed: u64,
    pub frame: u64,
}

/// The clean or effected echo of every pixel, before range noise.
pub fn echoes(
    backend: &dyn RenderBackend,
    rays: &LidarRays,
    effects: &EffectSet,
    world_from_lidar: &Pose,
) -> Vec<Option<SurfaceSample>> {
    match (&effects.mixed_pixels, &rays.footprint) {
        (Some(mixed), Some(sub)) => {
            let samples = backend.camera_echoes(world_from_lidar, sub, rays.pixel_rad);
            samples
                .par_chunks(sub.per_pixel.max(1))
                .map(|echoes| mixed.combine(echoes))
                .collect()
        }
        _ => backend.camera_echoes(world_from_lidar, &rays.centre, rays.pixel_rad),
    }
}

/// Renders one range frame for a lidar at `world_from_lidar`.
#[allow(clippy::too_many_arguments)]
pub fn render_range(
    backend: &dyn RenderBackend,
    sensor: &SensorModel,
    rays: &LidarRays,
    effects: &EffectSet,
    world_from_lidar: &Pose,
    key: NoiseKey,
    timestamp_ns: u64,
    seq: u32,
) -> RangeFrame {
    let echoes = echoes(backend, rays, effects, world_from_lidar);
    let dropout_rng = FrameRng::new(key.seed, key.frame, Stream::Dropouts);
    let noise_rng = FrameRng::new(key.seed, key.frame, Stream::RangeNoise);
    let (ranges_m, intensity): (Vec<f32>, Vec<f32>) = echoes
        .par_iter()
        .enumerate()
        .map(|(pixel, echo)| {
            let Some(echo) = echo else {
                return (f32::NAN, 0.0);
            };
            // The sensor's constant range bias (zero unless its sensor file sets one):
            // a property of the camera, not an effect a scene opts into.
            let mut r = echo.range_m + sensor.range_bias_m;
            if let Some(d) = &effects.dropouts {
                let rng = dropout_rng.pixel(pixel as u64);
                if d.decide(echo, sensor.min_range_m, sensor.max_range_m, &rng)
                    .is_some()
                {
                    return (f32::NAN, 0.0);
                }
            }
            if let Some(n) = &effects.range_noise {
                r = n.apply(r, &sensor.range_noise, &noise_rng.pixel(pixel as u64));
            }
            if let Some(q) = &effects.range_quantisation {
                r = q.apply(r);
            }
            if r.is_finite() && r > 0.0 {
                (r as f32, intensity_counts(echo))
            } else {
                (f32::NAN, 0.0)
            }
        })
        .unzip();
    RangeFrame {
        width: sensor.lidar.width,
        height: sensor.lidar.height,
        ranges_m,
        timestamp_ns,
        seq,
        intensity: Some(intensity),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn echo(reflectivity: f32, cos_incidence: f64) -> SurfaceSample {
        SurfaceSample {
            range_m: 2.0,
            cos_incidence,
            reflectivity,
            object: 0,
        }
    }

    #[test]
    fn intensity_is_reflectivity_times_incidence_in_counts() {
        assert_eq!(intensity_counts(&echo(1.0, 1.0)), INTENSITY_FULL_SCALE);
        assert_eq!(intensity_counts(&echo(0.5, 0.5)), 2500.0);
        assert_eq!(intensity_counts(&echo(0.0, 1.0)), 0.0);
        assert_eq!(intensity_counts(&echo(f32::NAN, 1.0)), 0.0);
        assert_eq!(intensity_counts(&echo(2.0, 1.0)), INTENSITY_FULL_SCALE);
    }
}
