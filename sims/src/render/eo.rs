//! The EO pipeline: clean radiance from a backend (averaged over sub-exposures under
//! `motion_blur`), then vignetting → exposure gain and saturation → sensor noise →
//! response curve → 8-bit RGB, per pixel, in parallel, with noise keyed by
//! (seed, frame, pixel, stream).

use rayon::prelude::*;
use texel::{EoFrame, Pose};

use super::lidar::NoiseKey;
use super::{CameraRays, RenderBackend};
use crate::effects::EffectSet;
use crate::effects::exposure::{CLEAN, Exposure, lut_lookup};
use crate::effects::sensor_noise::SensorNoise;
use crate::material::Rgb;
use crate::rng::normal_table::normal_table;
use crate::rng::{FrameRng, Stream};

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

/// What developing an image needs that does not change from frame to frame: the
/// response curve's table, the exposure gain, each pixel's vignetting factor and the
/// sensor noise model. Built once per camera and effect set.
#[derive(Debug, Clone)]
pub struct Development {
    width: u32,
    height: u32,
    lut: Vec<u8>,
    /// The `exposure` effect when the scene lists it: each frame's gain and the
    /// exposure it records (`None`: 0 EV, nothing recorded).
    exposure: Option<Exposure>,
    /// Per pixel, the vignetting factor of its ray (`None` without `vignetting`).
    vignette: Option<Vec<f32>>,
    sensor_noise: Option<SensorNoise>,
}

impl Development {
    pub fn new(rays: &CameraRays, effects: &EffectSet) -> Self {
        let exposure = effects.exposure.clone().unwrap_or(CLEAN);
        let per = rays.per_pixel.max(1);
        let vignette = effects.vignetting.as_ref().map(|vig| {
            (0..rays.pixel_count())
                .into_par_iter()
                .map(|pixel| {
                    let cos = rays.rays.get(pixel * per).map_or(1.0, |r| f64::from(r[2]));
                    vig.factor(cos)
                })
                .collect()
        });
        Self {
            width: rays.camera.width,
            height: rays.camera.height,
            lut: exposure.lut(),
            exposure: effects.exposure.clone(),
            vignette,
            sensor_noise: effects.sensor_noise.clone(),
        }
    }

    /// Turns linear radiance (one value per pixel) into an 8-bit RGB frame through the
    /// EO effects: vignetting, exposure gain and saturation, sensor noise, response
    /// curve. Frame `key.frame` takes its place in the exposure bracket.
    pub fn develop(&self, linear: &[Rgb], key: NoiseKey, timestamp_ns: u64) -> EoFrame {
        let gain = self
            .exposure
            .as_ref()
            .map_or(1.0, |e| e.frame_gain(key.frame));
        let mut rgb = vec![0u8; 3 * linear.len()];
        let noise_rng = FrameRng::new(key.seed, key.frame, Stream::SensorNoise);
        let normals = normal_table();
        rgb.par_chunks_mut(3 * 1024)
            .enumerate()
            .for_each(|(chunk, out)| {
                for (j, px) in out.chunks_exact_mut(3).enumerate() {
                    let pixel = chunk * 1024 + j;
                    let Some(l) = linear.get(pixel) else {
                        continue;
                    };
                    let mut v = *l;
                    if let Some(vignette) = &self.vignette {
                        let f = vignette.get(pixel).copied().unwrap_or(1.0);
                        for c in v.iter_mut() {
                            *c *= f;
                        }
                    }
                    for c in v.iter_mut() {
                        *c = (*c * gain).clamp(0.0, 1.0);
                    }
                    if let Some(noise) = &self.sensor_noise {
                        v = noise.apply(v, noise_rng.pixel(pixel as u64).normals3(normals));
                    }
                    for (o, c) in px.iter_mut().zip(v) {
                        *o = lut_lookup(&self.lut, c);
                    }
                }
            });
        EoFrame {
            width: self.width,
            height: self.height,
            rgb,
            timestamp_ns,
            exposure: self.exposure.as_ref().map(|e| e.frame_exposure(key.frame)),
        }
    }
}

/// Turns linear radiance into an 8-bit RGB frame through the EO effects (building the
/// [`Development`] for this one image; keep one to develop many).
pub fn develop(
    linear: &[Rgb],
    rays: &CameraRays,
    effects: &EffectSet,
    key: NoiseKey,
    timestamp_ns: u64,
) -> EoFrame {
    Development::new(rays, effects).develop(linear, key, timestamp_ns)
}
