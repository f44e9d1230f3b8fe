//! Rendering: the backend interface (clean echoes and clean radiance for a camera at a
//! pose), the built-in ray-casting backend, and the lidar and EO pipelines that apply
//! a scene's effects on top of whichever backend rendered the clean signal.

pub mod eo;
pub mod lidar;

use std::sync::Arc;

use nalgebra::{Vector2, Vector3};
use rayon::prelude::*;
use texel::{PinholeCamera, Pose};

use crate::geometry::Ray;
use crate::material::Rgb;
use crate::world::World;

/// What a lidar ray brings back from a surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceSample {
    /// Radial range along the unit ray, metres.
    pub range_m: f64,
    /// |cos| of the angle between the ray and the surface normal, in [0, 1].
    pub cos_incidence: f64,
    /// Reflectivity at the lidar's wavelength, in [0, 1].
    pub reflectivity: f32,
    /// The object hit.
    pub object: u32,
}

/// Unit rays of a camera's pixels in its optical frame, row-major, computed once per
/// camera model; with sub-pixel offsets, `offsets.len()` rays per pixel.
#[derive(Debug, Clone)]
pub struct CameraRays {
    pub camera: PinholeCamera,
    /// Unit rays; zero for a pixel outside the distortion model's domain.
    pub rays: Vec<[f32; 3]>,
    /// Rays per pixel.
    pub per_pixel: usize,
    /// Angular width of one pixel at the image centre, radians (texture footprint).
    pub pixel_rad: f64,
}

impl CameraRays {
    /// One ray through each pixel centre.
    pub fn new(camera: &PinholeCamera) -> Self {
        Self::with_offsets(camera, &[[0.0, 0.0]])
    }

    /// `offsets.len()` rays per pixel, through `pixel centre + offset` (pixels).
    pub fn with_offsets(camera: &PinholeCamera, offsets: &[[f64; 2]]) -> Self {
        let max_r2 = camera.max_radius_squared();
        let (w, h) = (camera.width as usize, camera.height as usize);
        let offsets: Vec<[f64; 2]> = if offsets.is_empty() {
            vec![[0.0, 0.0]]
        } else {
            offsets.to_vec()
        };
        let rays: Vec<[f32; 3]> = (0..w * h)
            .into_par_iter()
            .flat_map_iter(|i| {
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                offsets.iter().map(move |o| {
                    match camera.unproject_with_domain(Vector2::new(u + o[0], v + o[1]), max_r2) {
                        Ok(n) => {
                            // z = 1 keeps the norm >= 1.
                            let r = Vector3::new(n.x, n.y, 1.0).normalize();
                            [r.x as f32, r.y as f32, r.z as f32]
                        }
                        Err(_) => [0.0; 3],
                    }
                })
            })
            .collect();
        let pixel_rad = 1.0 / camera.fx.max(camera.fy);
        Self {
            camera: camera.clone(),
            rays,
            per_pixel: offsets.len(),
            pixel_rad,
        }
    }

    pub fn pixel_count(&self) -> usize {
        self.camera.width as usize * self.camera.height as usize
    }
}

/// The unit ray `r` (camera frame, f32) turned into world coordinates; `None` for an
/// invalid (zero) ray.
#[inline]
pub fn world_ray(world_from_camera: &Pose, r: &[f32; 3]) -> Option<Ray> {
    if r[0] == 0.0 && r[1] == 0.0 && r[2] == 0.0 {
        return None;
    }
    let d = Vector3::new(f64::from(r[0]), f64::from(r[1]), f64::from(r[2]));
    // Renormalise in f64 so distances are metres to f64 precision.
    let d = d / d.norm();
    Some(Ray {
        origin: world_from_camera.translation.vector.into(),
        dir: world_from_camera.rotation * d,
    })
}

/// A renderer of the clean signal: lidar echoes and EO radiance for a camera at a pose.
/// Effects are applied by the pipelines in [`lidar`] and [`eo`], the same for every
/// backend. Implementations must be deterministic and `Sync` (rendered from rayon).
pub trait RenderBackend: Send + Sync {
    fn name(&self) -> &'static str;

    /// The echo of each ray (`rays` in the camera frame, zero = invalid), for a camera
    /// at `world_from_camera`; `beam_rad` is a ray's angular width.
    fn echoes(
        &self,
        world_from_camera: &Pose,
        rays: &[[f32; 3]],
        beam_rad: f64,
    ) -> Vec<Option<SurfaceSample>>;

    /// Linear radiance of each ray of `rays` (one per pixel) for a camera at
    /// `world_from_camera`; `specular` scales the glossy lobe (`None` = Lambertian).
    fn radiance(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        specular: Option<f32>,
    ) -> Vec<Rgb>;
}

/// Which renderer makes the clean signal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BackendKind {
    /// Ray casting against the scene's BVH, in this process.
    #[default]
    Builtin,
    /// Mitsuba 3 (not available in this build).
    Mitsuba,
}

impl BackendKind {
    pub fn name(self) -> &'static str {
        match self {
            Self::Builtin => "builtin",
            Self::Mitsuba => "mitsuba",
        }
    }
}

/// Rays per rayon task: big enough to amortise scheduling, small enough to balance.
const CHUNK: usize = 1024;

/// The built-in ray caster.
#[derive(Debug, Clone)]
pub struct BuiltinBackend {
    world: Arc<World>,
}

impl BuiltinBackend {
    pub fn new(world: Arc<World>) -> Self {
        Self { world }
    }
}

impl RenderBackend for BuiltinBackend {
    fn name(&self) -> &'static str {
        "builtin"
    }

    fn echoes(
        &self,
        world_from_camera: &Pose,
        rays: &[[f32; 3]],
        beam_rad: f64,
    ) -> Vec<Option<SurfaceSample>> {
        let mut out = vec![None; rays.len()];
        out.par_chunks_mut(CHUNK)
            .zip(rays.par_chunks(CHUNK))
            .for_each(|(out, rays)| {
                for (o, r) in out.iter_mut().zip(rays) {
                    *o = world_ray(world_from_camera, r)
                        .and_then(|ray| self.world.surface_sample(&ray, beam_rad));
                }
            });
        out
    }

    fn radiance(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        specular: Option<f32>,
    ) -> Vec<Rgb> {
        let mut out = vec![[0.0f32; 3]; rays.rays.len()];
        let pixel_rad = rays.pixel_rad;
        out.par_chunks_mut(CHUNK)
            .zip(rays.rays.par_chunks(CHUNK))
            .for_each(|(out, rays)| {
                for (o, r) in out.iter_mut().zip(rays) {
                    *o = match world_ray(world_from_camera, r) {
                        Some(ray) => self.world.radiance(&ray, pixel_rad, specular),
                        None => [0.0; 3],
                    };
                }
            });
        out
    }
}
