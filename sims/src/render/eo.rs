//! The EO pipeline: clean radiance from a backend (averaged over sub-exposures under
//! `motion_blur`), then vignetting → exposure gain and saturation → sensor noise →
//! response curve → 8-bit RGB, per pixel, in parallel, with noise keyed by
//! (seed, frame, pixel, stream).

use rayon::prelude::*;
use texel::{EoFrame, Pose};

use super::lidar::NoiseKey;
use super::{CameraRays, RenderBackend};
use crate::effects::EffectSet;
use crate::effects::exposure::{CLEAN, lut_lookup};
use crate::material::Rgb;
use crate::rng::{PixelRng, Stream};

/// Linear radiance per pixel, averaged over `poses` (one pose: no motion blur).
pub fn radiance(
    backend: &dyn RenderBackend,
    rays: &CameraRays,
    effects: &EffectSet,
    poses: &[Pose],
) -> Vec<Rgb> {
    let specular = effects.specular.as_ref().map(|s| s.scale as f32);
    let mut iter = poses.iter();
    let Some(first) = iter.next() else {
        return vec![[0.0; 3]; rays.pixel_count()];
    };
    let mut acc = backend.radiance(first, rays, specular);
    let mut n = 1.0f32;
    for pose in iter {
        let next = backend.radiance(pose, rays, specular);
        acc.par_iter_mut().zip(next.par_iter()).for_each(|(a, b)| {
            for k in 0..3 {
                a[k] += b[k];
            }
        });
        n += 1.0;
    }
    if n > 1.0 {
        let inv = 1.0 / n;
        acc.par_iter_mut().for_each(|a| {
            for v in a.iter_mut() {
                *v *= inv;
            }
        });
    }
    acc
}

/// Turns linear radiance into an 8-bit RGB frame through the EO effects.
pub fn develop(
    linear: &[Rgb],
    rays: &CameraRays,
    effects: &EffectSet,
    key: NoiseKey,
    timestamp_ns: u64,
) -> EoFrame {
    let exposure = effects.exposure.clone().unwrap_or(CLEAN);
    let lut = exposure.lut();
    let gain = exposure.gain();
    let per = rays.per_pixel.max(1);
    let mut rgb = vec![0u8; 3 * linear.len()];
    rgb.par_chunks_mut(3 * 1024)
        .enumerate()
        .for_each(|(chunk, out)| {
            for (j, px) in out.chunks_exact_mut(3).enumerate() {
                let pixel = chunk * 1024 + j;
                let Some(l) = linear.get(pixel) else {
                    continue;
                };
                let mut v = *l;
                if let Some(vig) = &effects.vignetting {
                    let cos = rays.rays.get(pixel * per).map_or(1.0, |r| f64::from(r[2]));
                    let f = vig.factor(cos);
                    for c in v.iter_mut() {
                        *c *= f;
                    }
                }
                for c in v.iter_mut() {
                    *c = (*c * gain).clamp(0.0, 1.0);
                }
                if let Some(noise) = &effects.sensor_noise {
                    let rng = PixelRng::new(key.seed, key.frame, pixel as u64, Stream::SensorNoise);
                    v = noise.apply(v, &rng);
                }
                for (o, c) in px.iter_mut().zip(v) {
                    *o = lut_lookup(&lut, c);
                }
            }
        });
    EoFrame {
        width: rays.camera.width,
        height: rays.camera.height,
        rgb,
        timestamp_ns,
    }
}
