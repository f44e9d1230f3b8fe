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
use texel::{PinholeCamera, Pose, RangeFrame, SensorModel};

use super::{CameraRays, RenderBackend};
use crate::effects::EffectSet;
use crate::effects::mixed_pixels::MixedPixels;
use crate::rng::{FrameRng, Stream};
use crate::world::SurfaceSample;

/// What the lidar pipeline needs about the lidar, computed once per simulator.
#[derive(Debug, Clone)]
pub struct LidarRays {
    /// One unit ray per pixel, the sensor's ray table (zero = invalid pixel), with its
    /// tiles.
    pub centre: CameraRays,
    /// The beam-footprint sub-rays of the `mixed_pixels` effect, when it runs, less
    /// the one through the pixel's centre (see [`Self::centre_sub`]).
    pub footprint: Option<CameraRays>,
    /// Where the pixel's centre ray goes among its footprint's sub-rays, when it is
    /// one of them (an odd number per side) and left out of `footprint`: its echo is
    /// the centre echo every pixel traces anyway, so it is not traced twice.
    pub centre_sub: Option<usize>,
    /// Angular width of one lidar pixel, radians.
    pub pixel_rad: f64,
}

impl LidarRays {
    /// The rays of a lidar `camera`, with the footprint sub-rays of `mixed` if given.
    pub fn new(camera: &PinholeCamera, mixed: Option<&MixedPixels>) -> Self {
        let (footprint, centre_sub) = match mixed {
            Some(m) => {
                let mut offsets = m.offsets_px();
                // The centre sub-ray is left out only where others remain (one sample
                // per side is the centre ray alone).
                let centre_sub = offsets
                    .iter()
                    .position(|o| *o == [0.0, 0.0])
                    .filter(|_| offsets.len() > 1);
                if let Some(k) = centre_sub {
                    offsets.remove(k);
                }
                (Some(CameraRays::with_offsets(camera, &offsets)), centre_sub)
            }
            None => (None, None),
        };
        Self {
            centre: CameraRays::new(camera),
            footprint,
            centre_sub,
            pixel_rad: 1.0 / camera.fx.max(camera.fy),
        }
    }

    /// One pixel's footprint echo from its centre echo and its other sub-rays' echoes
    /// (`subs`, in [`MixedPixels::offsets_px`] order less the centre).
    fn footprint_echo(
        &self,
        mixed: &MixedPixels,
        centre: &Option<SurfaceSample>,
        subs: &[Option<SurfaceSample>],
    ) -> Option<SurfaceSample> {
        match self.centre_sub {
            Some(k) if k <= subs.len() => {
                let (before, after) = subs.split_at(k);
                mixed.combine(before.iter().chain(std::iter::once(centre)).chain(after))
            }
            _ => mixed.combine(subs),
        }
    }
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
    let (Some(mixed), Some(sub)) = (&effects.mixed_pixels, &rays.footprint) else {
        return backend.camera_echoes(world_from_lidar, &rays.centre, rays.pixel_rad);
    };
    let per = sub.per_pixel.max(1);
    let centre = backend.camera_echoes(world_from_lidar, &rays.centre, rays.pixel_rad);
    if !mixed.adaptive {
        let samples = backend.camera_echoes(world_from_lidar, sub, rays.pixel_rad);
        return centre
            .par_iter()
            .zip(samples.par_chunks(per))
            .map(|(c, subs)| rays.footprint_echo(mixed, c, subs))
            .collect();
    }
    // Only beams that may straddle surfaces are sampled across their footprint;
    // elsewhere the footprint lies on one smooth surface, whose echo is the centre's.
    let (width, height) = (
        rays.centre.camera.width as usize,
        rays.centre.camera.height as usize,
    );
    let reach_px = (0.5 * mixed.footprint_px).ceil().max(1.0) as usize;
    let straddling: Vec<bool> = (0..centre.len())
        .into_par_iter()
        .map(|pixel| may_straddle(&centre, width, height, pixel, reach_px, rays.pixel_rad))
        .collect();
    let samples = backend.camera_echoes_of(world_from_lidar, sub, &straddling, rays.pixel_rad);
    centre
        .par_iter()
        .zip(samples.par_chunks(per))
        .zip(straddling.par_iter())
        .map(|((c, subs), straddles)| {
            if *straddles {
                rays.footprint_echo(mixed, c, subs)
            } else {
                *c
            }
        })
        .collect()
}

/// Whether the beam of `pixel` may meet more than one surface, or one surface whose
/// reflectivity changes enough to shift the echo: some pixel within `reach_px` of it
/// has a return where it has none (or the reverse), a return from another object, a
/// range that differs by more than one smooth surface explains (twice the change its
/// incidence predicts over the distance, plus 1 mm), or a reflectivity whose range
/// walk could exceed [`RANGE_WALK_M`]; or the pixel lies at the image's border,
/// where its footprint reaches past the last pixel centre. Features that fall between
/// pixel centres without touching one are not seen.
fn may_straddle(
    centre: &[Option<SurfaceSample>],
    width: usize,
    height: usize,
    pixel: usize,
    reach_px: usize,
    pixel_rad: f64,
) -> bool {
    if width == 0 {
        return false;
    }
    let (u, v) = (pixel % width, pixel / width);
    // The footprint of a pixel at the border reaches past the last pixel centre.
    if u < reach_px || v < reach_px || u + reach_px >= width || v + reach_px >= height {
        return true;
    }
    let here = centre.get(pixel).copied().flatten();
    // How far the range changes across one pixel on this pixel's surface: its own
    // echo's alone, so worked out once rather than per neighbour.
    let slope_m = here.map_or(0.0, |a| {
        let cos = a.cos_incidence.clamp(MIN_STRADDLE_COS, 1.0);
        let tan = (1.0 - cos * cos).max(0.0).sqrt() / cos;
        a.range_m * pixel_rad * (1.0 + tan)
    });
    for y in v.saturating_sub(reach_px)..(v + reach_px + 1).min(height) {
        for x in u.saturating_sub(reach_px)..(u + reach_px + 1).min(width) {
            let there = centre.get(y * width + x).copied().flatten();
            match (here, there) {
                (None, None) => {}
                (Some(a), Some(b)) => {
                    if a.object != b.object {
                        return true;
                    }
                    let steps = u.abs_diff(x).max(v.abs_diff(y)) as f64;
                    if (a.range_m - b.range_m).abs() > 2.0 * slope_m * steps + 1.0e-3 {
                        return true;
                    }
                    // A reflectivity step within the footprint pulls the echo's range
                    // towards the brighter side (range walk): a step from ρ₁ to ρ₂
                    // mid-footprint by (ρ₂ - ρ₁) / (ρ₁ + ρ₂) / 4 of the range change
                    // across it, at most a quarter of it.
                    let (ra, rb) = (f64::from(a.reflectivity), f64::from(b.reflectivity));
                    let sum = ra + rb;
                    if sum > 0.0 && (ra - rb).abs() / sum * 0.25 * slope_m > RANGE_WALK_M {
                        return true;
                    }
                }
                _ => return true,
            }
        }
    }
    false
}

/// A reflectivity step whose range walk across one pixel could exceed this is
/// sampled (metres).
const RANGE_WALK_M: f64 = 1.0e-3;

/// The incidence cosine below which [`may_straddle`] stops widening its smooth-surface
/// allowance (about 87°), so the allowance stays finite at grazing incidence.
const MIN_STRADDLE_COS: f64 = 0.05;

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
    #![allow(clippy::unwrap_used)]
    use std::sync::Arc;

    use super::*;
    use crate::render::BuiltinBackend;
    use crate::scene::Scene;

    /// Tile-traced echoes of every pixel, and of some, equal tracing every ray alone.
    #[test]
    fn echoes_of_some_pixels_equal_tracing_those_rays() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/scenes/lab.toml");
        let lab = Scene::load(&path).unwrap();
        let camera = crate::rescale_camera(&lab.sensor().lidar, 40, 30);
        let rays = CameraRays::with_offsets(&camera, &[[-0.3, -0.3], [0.3, 0.1], [0.0, 0.0]]);
        let backend = BuiltinBackend::new(Arc::clone(&lab.world));
        let pixels: Vec<bool> = (0..40 * 30).map(|i| i % 3 == 0 || i % 7 == 1).collect();
        let beam = 0.01;
        for frame in [0, 13] {
            let pose = lab.trajectory.frame_pose(frame);
            let each = backend.echoes(&pose, &rays.rays, beam);
            assert_eq!(backend.camera_echoes(&pose, &rays, beam), each);
            let some = backend.camera_echoes_of(&pose, &rays, &pixels, beam);
            for (i, (s, e)) in some.iter().zip(&each).enumerate() {
                let wanted = pixels[i / 3];
                assert_eq!(*s, if wanted { *e } else { None }, "ray {i}");
            }
            assert!(each.iter().filter(|e| e.is_some()).count() > 3000);
            // The trait's own version (what the Mitsuba backend runs) agrees.
            let plain = Plain(backend.clone());
            assert_eq!(plain.camera_echoes_of(&pose, &rays, &pixels, beam), some);
            let none = vec![false; pixels.len()];
            assert!(
                plain
                    .camera_echoes_of(&pose, &rays, &none, beam)
                    .iter()
                    .all(Option::is_none)
            );
        }
    }

    /// Footprints whose centre sub-ray's echo is the pixel's centre echo (traced once)
    /// merge to exactly what tracing every sub-ray gives, for an odd number per side
    /// (3 and 5: the centre left out) and an even one (4: no centre sub-ray), adaptive
    /// or not.
    #[test]
    fn reusing_the_centre_echo_equals_tracing_every_sub_ray() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/scenes/lab.toml");
        let lab = Scene::load(&path).unwrap();
        let camera = crate::rescale_camera(&lab.sensor().lidar, 40, 30);
        let backend = BuiltinBackend::new(Arc::clone(&lab.world));
        let pose = lab.trajectory.frame_pose(5);
        for (side, adaptive) in [(3, true), (3, false), (5, true), (4, false)] {
            let mixed = MixedPixels {
                samples_per_side: side,
                footprint_px: 1.5,
                adaptive,
                ..MixedPixels::default()
            };
            let rays = LidarRays::new(&camera, Some(&mixed));
            let per = (side * side) as usize;
            assert_eq!(rays.centre_sub.is_some(), side % 2 == 1, "{side} per side");
            let sub = rays.footprint.as_ref().unwrap();
            assert_eq!(sub.per_pixel, per - usize::from(side % 2 == 1));
            let effects = EffectSet {
                mixed_pixels: Some(mixed.clone()),
                ..EffectSet::default()
            };
            let got = echoes(&backend, &rays, &effects, &pose);
            // Every sub-ray traced, the centre's too, merged in offset order.
            let all = CameraRays::with_offsets(&camera, &mixed.offsets_px());
            let traced = backend.camera_echoes(&pose, &all, rays.pixel_rad);
            let centre = backend.camera_echoes(&pose, &rays.centre, rays.pixel_rad);
            let (mut merged, mut differs) = (0, 0);
            for (pixel, (g, subs)) in got.iter().zip(traced.chunks(per)).enumerate() {
                let full = mixed.combine(subs);
                if *g == full {
                    merged += usize::from(*g != centre[pixel]);
                } else {
                    // Adaptive sampling keeps the centre echo where no edge is near.
                    assert!(
                        adaptive && *g == centre[pixel],
                        "pixel {pixel}, {side} per side"
                    );
                    differs += 1;
                }
            }
            assert!(merged > 50, "{merged} footprints merged, {side} per side");
            assert_eq!(differs > 0, adaptive, "{side} per side");
        }
    }

    /// A backend with only the required methods: the trait's defaults for the rest.
    struct Plain(BuiltinBackend);

    impl RenderBackend for Plain {
        fn name(&self) -> &'static str {
            "plain"
        }

        fn echoes(
            &self,
            world_from_camera: &Pose,
            rays: &[[f32; 3]],
            beam_rad: f64,
        ) -> Vec<Option<SurfaceSample>> {
            self.0.echoes(world_from_camera, rays, beam_rad)
        }

        fn radiance(
            &self,
            world_from_camera: &Pose,
            rays: &CameraRays,
            specular: Option<f32>,
        ) -> Vec<crate::material::Rgb> {
            self.0.radiance(world_from_camera, rays, specular)
        }
    }

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
