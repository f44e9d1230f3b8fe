//! Rendering: the backend interface (clean echoes and clean radiance for a camera at a
//! pose), the built-in ray-casting backend, and the lidar and EO pipelines that apply
//! a scene's effects on top of whichever backend rendered the clean signal.

pub mod eo;
pub mod lidar;
pub mod mitsuba;
pub mod mitsuba_scene;

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
    /// Square tiles of [`TILE`] pixels (one ray per pixel only), row of tiles by row.
    pub tiles: Vec<Tile>,
}

/// Four vectors around a cone: its plane normals or its edge directions.
type Quad = [Vector3<f64>; 4];

/// Side of a tile of pixels whose rays share one bounding cone.
pub const TILE: u32 = 16;

/// A tile of pixels and the cone bounding all of its rays.
#[derive(Debug, Clone)]
pub struct Tile {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
    /// Inward normals (camera frame) of four planes through the centre of projection
    /// that contain every ray of the tile; `None` when no such cone was found (the
    /// tile's pixels are then traced through the whole BVH).
    pub planes: Option<[Vector3<f64>; 4]>,
    /// Directions (camera frame) of the cone's four edges, in order around it.
    pub edges: [Vector3<f64>; 4],
}

/// Bounding cone of the rays of pixels `[x0, x1) x [y0, y1)`: the pyramid of the rays
/// through the tile's corners pushed out by one pixel, checked against every ray.
fn tile_cone(
    camera: &PinholeCamera,
    rays: &[[f32; 3]],
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
) -> Option<(Quad, Quad)> {
    let max_r2 = camera.max_radius_squared();
    let corner = |u: f64, v: f64| -> Option<Vector3<f64>> {
        let n = camera
            .unproject_with_domain(Vector2::new(u, v), max_r2)
            .ok()?;
        Some(Vector3::new(n.x, n.y, 1.0))
    };
    let (l, t) = (f64::from(x0) - 1.5, f64::from(y0) - 1.5);
    let (r, b) = (f64::from(x1) + 0.5, f64::from(y1) + 0.5);
    let c = [corner(l, t)?, corner(r, t)?, corner(r, b)?, corner(l, b)?];
    let centre = c.iter().fold(Vector3::zeros(), |a, v| a + v);
    let mut planes = [Vector3::zeros(); 4];
    for k in 0..4 {
        let mut n = c[k].cross(&c[(k + 1) % 4]);
        if n.dot(&centre) < 0.0 {
            n = -n;
        }
        let len = n.norm();
        if !(len > 0.0 && len.is_finite()) {
            return None;
        }
        planes[k] = n / len;
    }
    let w = camera.width as usize;
    for y in y0..y1 {
        for x in x0..x1 {
            let r = rays[y as usize * w + x as usize];
            if r == [0.0; 3] {
                return None;
            }
            let r = Vector3::new(f64::from(r[0]), f64::from(r[1]), f64::from(r[2]));
            if planes.iter().any(|n| n.dot(&r) < 0.0) {
                return None;
            }
        }
    }
    Some((planes, c))
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
        let tiles = if offsets.len() == 1 {
            let (tw, th) = (camera.width.div_ceil(TILE), camera.height.div_ceil(TILE));
            (0..tw * th)
                .into_par_iter()
                .map(|i| {
                    let (x0, y0) = ((i % tw) * TILE, (i / tw) * TILE);
                    let (x1, y1) = (
                        (x0 + TILE).min(camera.width),
                        (y0 + TILE).min(camera.height),
                    );
                    let cone = tile_cone(camera, &rays, x0, y0, x1, y1);
                    Tile {
                        x0,
                        y0,
                        x1,
                        y1,
                        planes: cone.map(|c| c.0),
                        edges: cone.map_or([Vector3::zeros(); 4], |c| c.1),
                    }
                })
                .collect()
        } else {
            Vec::new()
        };
        Self {
            camera: camera.clone(),
            rays,
            per_pixel: offsets.len(),
            pixel_rad,
            tiles,
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

    /// Why rendering failed, if it did (an out-of-process renderer that died): the
    /// results of the failed calls are empty (no echoes, black radiance) and the
    /// simulator reports this message instead of returning them.
    fn failure(&self) -> Option<String> {
        None
    }
}

/// Which renderer makes the clean signal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BackendKind {
    /// The built-in ray caster, unless an effect only Mitsuba simulates is asked for
    /// (`global_illumination`), which selects Mitsuba.
    #[default]
    Auto,
    /// Ray casting against the scene's BVH, in this process.
    Builtin,
    /// Mitsuba 3 in a Python process ([`mitsuba`]).
    Mitsuba,
}

impl BackendKind {
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
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
        let width = rays.camera.width as usize;
        if rays.per_pixel != 1 || rays.tiles.is_empty() || width == 0 {
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
            return out;
        }
        // Strips of one row of tiles: each tile gathers the primitives its cone of
        // rays can meet once, then its pixels test only those.
        let tiles_per_row = rays.camera.width.div_ceil(TILE) as usize;
        let origin: nalgebra::Point3<f64> = world_from_camera.translation.vector.into();
        out.par_chunks_mut(TILE as usize * width)
            .zip(rays.tiles.par_chunks(tiles_per_row))
            .for_each(|(strip, tiles)| {
                let mut candidates = Vec::new();
                for tile in tiles {
                    let planes = tile
                        .planes
                        .map(|p| p.map(|n| world_from_camera.rotation * n));
                    if let Some(planes) = &planes {
                        let edges = tile.edges.map(|e| world_from_camera.rotation * e);
                        self.world
                            .bvh
                            .cone_candidates(&origin, planes, &edges, &mut candidates);
                    }
                    for y in tile.y0..tile.y1 {
                        for x in tile.x0..tile.x1 {
                            let index = y as usize * width + x as usize;
                            let local = (y - tile.y0) as usize * width + x as usize;
                            let Some(ray) = world_ray(world_from_camera, &rays.rays[index]) else {
                                continue;
                            };
                            let hit = if planes.is_some() {
                                self.world.bvh.closest_among(&ray, &candidates)
                            } else {
                                self.world.trace(&ray)
                            };
                            if let Some(o) = strip.get_mut(local) {
                                *o = self.world.shade_hit(&ray, hit, pixel_rad, specular);
                            }
                        }
                    }
                }
            });
        out
    }
}
