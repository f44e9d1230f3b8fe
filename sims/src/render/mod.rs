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
use texel::rays::pixel_ray;
use texel::{PinholeCamera, Pose};

use crate::geometry::{Aabb, Hit, Ray};
use crate::light::Occluders;
use crate::material::Rgb;
use crate::world::{SurfaceSample, World};

/// Unit rays of a camera's pixels in its optical frame, row-major, computed once per
/// camera model; with sub-pixel offsets, `offsets.len()` rays per pixel.
#[derive(Debug, Clone)]
pub struct CameraRays {
    pub camera: PinholeCamera,
    /// Unit rays; zero for a pixel outside the distortion model's domain.
    pub rays: Vec<[f32; 3]>,
    /// `rays` renormalised in f64 as [`world_ray`] does (zero for a zero ray), once
    /// per camera instead of once per ray and frame.
    pub unit_rays: Vec<Vector3<f64>>,
    /// Rays per pixel.
    pub per_pixel: usize,
    /// Angular width of one pixel at the image centre, radians (texture footprint).
    pub pixel_rad: f64,
    /// Side of the square tiles, pixels: about [`TILE_RAYS`] rays each.
    pub tile_px: u32,
    /// Square tiles of `tile_px` pixels, row of tiles by row (empty: trace every ray
    /// through the whole BVH).
    pub tiles: Vec<Tile>,
}

/// Four vectors around a cone: its plane normals or its edge directions.
type Quad = [Vector3<f64>; 4];

/// Rays in a tile of pixels whose rays share one bounding cone (16 x 16 at one ray per
/// pixel): enough to amortise gathering the cone's candidates, few enough that the
/// cone stays narrow.
pub const TILE_RAYS: u32 = 256;

/// Side of the square tiles for `per_pixel` rays per pixel: about [`TILE_RAYS`] rays.
fn tile_side_px(per_pixel: usize) -> u32 {
    let per = per_pixel.clamp(1, TILE_RAYS as usize) as f64;
    ((f64::from(TILE_RAYS) / per).sqrt().round() as u32).max(2)
}

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

/// Bounding cone of the rays of pixels `[x0, x1) x [y0, y1)` (`per_pixel` rays each,
/// up to `reach_px` pixels off their pixel's centre): the pyramid of the rays through
/// the tile's corners pushed out by one pixel more than that, checked against every
/// ray.
#[allow(clippy::too_many_arguments)]
fn tile_cone(
    camera: &PinholeCamera,
    rays: &[[f32; 3]],
    per_pixel: usize,
    reach_px: f64,
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
    let (l, t) = (
        f64::from(x0) - 1.5 - reach_px,
        f64::from(y0) - 1.5 - reach_px,
    );
    let (r, b) = (
        f64::from(x1) + 0.5 + reach_px,
        f64::from(y1) + 0.5 + reach_px,
    );
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
            let first = (y as usize * w + x as usize) * per_pixel;
            for r in rays.get(first..first + per_pixel)? {
                if *r == [0.0; 3] {
                    return None;
                }
                let r = Vector3::new(f64::from(r[0]), f64::from(r[1]), f64::from(r[2]));
                if planes.iter().any(|n| n.dot(&r) < 0.0) {
                    return None;
                }
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
                    // texel's ray through a pixel, so that these rays are the sensor's
                    // ray table bit for bit (at zero offset) and fusion's geometry.
                    pixel_ray(camera, Vector2::new(u + o[0], v + o[1]), max_r2).unwrap_or([0.0; 3])
                })
            })
            .collect();
        let unit_rays = rays
            .par_iter()
            .map(|r| unit_ray(r).unwrap_or_else(Vector3::zeros))
            .collect();
        let pixel_rad = 1.0 / camera.fx.max(camera.fy);
        let per_pixel = offsets.len();
        let reach_px = offsets
            .iter()
            .map(|o| o[0].abs().max(o[1].abs()))
            .fold(0.0, f64::max);
        let tile = tile_side_px(per_pixel);
        let (tw, th) = (camera.width.div_ceil(tile), camera.height.div_ceil(tile));
        let tiles = (0..tw * th)
            .into_par_iter()
            .map(|i| {
                let (x0, y0) = ((i % tw) * tile, (i / tw) * tile);
                let (x1, y1) = (
                    (x0 + tile).min(camera.width),
                    (y0 + tile).min(camera.height),
                );
                let cone = tile_cone(camera, &rays, per_pixel, reach_px, x0, y0, x1, y1);
                Tile {
                    x0,
                    y0,
                    x1,
                    y1,
                    planes: cone.map(|c| c.0),
                    edges: cone.map_or([Vector3::zeros(); 4], |c| c.1),
                }
            })
            .collect();
        Self {
            camera: camera.clone(),
            rays,
            unit_rays,
            per_pixel: offsets.len(),
            pixel_rad,
            tile_px: tile,
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
    unit_ray(r).map(|d| rotated_ray(world_from_camera, &d))
}

/// The unit ray `r` (f32) renormalised in f64, so distances along it are metres to
/// f64 precision; `None` for an invalid (zero) ray.
#[inline]
pub fn unit_ray(r: &[f32; 3]) -> Option<Vector3<f64>> {
    if r[0] == 0.0 && r[1] == 0.0 && r[2] == 0.0 {
        return None;
    }
    let d = Vector3::new(f64::from(r[0]), f64::from(r[1]), f64::from(r[2]));
    Some(d / d.norm())
}

/// The ray along the unit camera-frame direction `d` of a camera at
/// `world_from_camera`, in world coordinates.
#[inline]
fn rotated_ray(world_from_camera: &Pose, d: &Vector3<f64>) -> Ray {
    Ray {
        origin: world_from_camera.translation.vector.into(),
        dir: world_from_camera.rotation * d,
    }
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

    /// [`Self::echoes`] of a camera's rays (`rays.per_pixel` per pixel), whose layout
    /// a backend may use (the built-in one culls per tile). By default, `echoes` of
    /// `rays.rays`.
    fn camera_echoes(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        beam_rad: f64,
    ) -> Vec<Option<SurfaceSample>> {
        self.echoes(world_from_camera, &rays.rays, beam_rad)
    }

    /// [`Self::camera_echoes`] of the pixels whose entry in `pixels` is true (one per
    /// pixel); the others' echoes are `None`. By default, `echoes` of those rays.
    fn camera_echoes_of(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        pixels: &[bool],
        beam_rad: f64,
    ) -> Vec<Option<SurfaceSample>> {
        echoes_of_pixels(self, world_from_camera, rays, pixels, beam_rad)
    }

    /// Why rendering failed, if it did (an out-of-process renderer that died): the
    /// results of the failed calls are empty (no echoes, black radiance) and the
    /// simulator reports this message instead of returning them.
    fn failure(&self) -> Option<String> {
        None
    }
}

/// [`RenderBackend::camera_echoes_of`] through [`RenderBackend::echoes`] of the wanted
/// pixels' rays alone (the trait's default).
fn echoes_of_pixels<B: RenderBackend + ?Sized>(
    backend: &B,
    world_from_camera: &Pose,
    rays: &CameraRays,
    pixels: &[bool],
    beam_rad: f64,
) -> Vec<Option<SurfaceSample>> {
    let per = rays.per_pixel.max(1);
    let wanted: Vec<[f32; 3]> = rays
        .rays
        .chunks(per)
        .zip(pixels)
        .filter(|(_, w)| **w)
        .flat_map(|(r, _)| r.iter().copied())
        .collect();
    let mut out = vec![None; rays.rays.len()];
    if wanted.is_empty() {
        return out;
    }
    let mut found = backend
        .echoes(world_from_camera, &wanted, beam_rad)
        .into_iter();
    for (o, w) in out.chunks_mut(per).zip(pixels) {
        if *w {
            for e in o.iter_mut() {
                *e = found.next().flatten();
            }
        }
    }
    out
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

/// One ray of a tile and what it hits, found by [`BuiltinBackend::trace_tiles`].
struct TileRay {
    /// Index of the ray's output within its strip of tiles.
    local: usize,
    ray: Ray,
    hit: Option<Hit>,
}

impl BuiltinBackend {
    pub fn new(world: Arc<World>) -> Self {
        Self { world }
    }

    /// Traces every ray of `rays` tile by tile: each tile gathers the primitives its
    /// cone of rays can meet once, then its rays test only those (a tile without a
    /// cone traces through the BVH). `finish` turns a tile's rays and hits into
    /// outputs in `strip`, the tile's row of tiles; strips run in parallel.
    fn trace_tiles<T, F>(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        pixels: Option<&[bool]>,
        out: &mut [T],
        finish: F,
    ) where
        T: Send,
        F: Fn(&[TileRay], &mut [T]) + Sync,
    {
        let width = rays.camera.width as usize;
        let per = rays.per_pixel.max(1);
        let tile_px = rays.tile_px.max(1);
        let tiles_per_row = rays.camera.width.div_ceil(tile_px) as usize;
        let origin: nalgebra::Point3<f64> = world_from_camera.translation.vector.into();
        let bvh = &self.world.bvh;
        out.par_chunks_mut(tile_px as usize * width * per)
            .zip(rays.tiles.par_chunks(tiles_per_row.max(1)))
            .for_each(|(strip, tiles)| {
                let mut candidates = Vec::new();
                let mut traced = Vec::with_capacity((tile_px * tile_px) as usize * per);
                for tile in tiles {
                    let wanted = |x: u32, y: u32| {
                        pixels.is_none_or(|p| {
                            p.get(y as usize * width + x as usize)
                                .copied()
                                .unwrap_or(false)
                        })
                    };
                    if pixels.is_some()
                        && !(tile.y0..tile.y1).any(|y| (tile.x0..tile.x1).any(|x| wanted(x, y)))
                    {
                        continue;
                    }
                    let planes = tile
                        .planes
                        .map(|p| p.map(|n| world_from_camera.rotation * n));
                    if let Some(planes) = &planes {
                        let edges = tile.edges.map(|e| world_from_camera.rotation * e);
                        bvh.cone_candidates(&origin, planes, &edges, &mut candidates);
                    }
                    traced.clear();
                    for y in tile.y0..tile.y1 {
                        let row = y as usize * width;
                        let local_row = (y - tile.y0) as usize * width;
                        for x in tile.x0..tile.x1 {
                            if !wanted(x, y) {
                                continue;
                            }
                            for k in 0..per {
                                let index = (row + x as usize) * per + k;
                                let local = (local_row + x as usize) * per + k;
                                let Some(ray) = rays
                                    .unit_rays
                                    .get(index)
                                    .filter(|d| **d != Vector3::zeros())
                                    .map(|d| rotated_ray(world_from_camera, d))
                                else {
                                    continue;
                                };
                                let hit = if planes.is_some() {
                                    bvh.closest_among(&ray, &candidates)
                                } else {
                                    self.world.trace(&ray)
                                };
                                traced.push(TileRay { local, ray, hit });
                            }
                        }
                    }
                    finish(&traced, strip);
                }
            });
    }
}

impl BuiltinBackend {
    /// Echoes of `rays` (of the pixels `pixels` marks, all without), tile by tile.
    fn tiled_echoes(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        pixels: Option<&[bool]>,
        beam_rad: f64,
    ) -> Vec<Option<SurfaceSample>> {
        let mut out = vec![None; rays.rays.len()];
        self.trace_tiles(
            world_from_camera,
            rays,
            pixels,
            &mut out,
            |traced, strip| {
                self.world.echoes_of_hits(
                    traced,
                    |t| (&t.ray, t.hit.as_ref()),
                    beam_rad,
                    |i, echo| {
                        if let Some(o) = traced.get(i).and_then(|t| strip.get_mut(t.local)) {
                            *o = echo;
                        }
                    },
                );
            },
        );
        out
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

    fn camera_echoes(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        beam_rad: f64,
    ) -> Vec<Option<SurfaceSample>> {
        if rays.tiles.is_empty() || rays.camera.width == 0 {
            return self.echoes(world_from_camera, &rays.rays, beam_rad);
        }
        self.tiled_echoes(world_from_camera, rays, None, beam_rad)
    }

    fn camera_echoes_of(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        pixels: &[bool],
        beam_rad: f64,
    ) -> Vec<Option<SurfaceSample>> {
        if rays.tiles.is_empty() || rays.camera.width == 0 {
            return echoes_of_pixels(self, world_from_camera, rays, pixels, beam_rad);
        }
        self.tiled_echoes(world_from_camera, rays, Some(pixels), beam_rad)
    }

    fn radiance(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        specular: Option<f32>,
    ) -> Vec<Rgb> {
        let mut out = vec![[0.0f32; 3]; rays.rays.len()];
        let pixel_rad = rays.pixel_rad;
        if rays.per_pixel != 1 || rays.tiles.is_empty() || rays.camera.width == 0 {
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
        let world = &self.world;
        self.trace_tiles(world_from_camera, rays, None, &mut out, |traced, strip| {
            // Shadow rays of the tile run from its hit points to the lights: only the
            // casters between the two can block them.
            let mut region = Aabb::EMPTY;
            for t in traced {
                if let Some(h) = &t.hit {
                    region.grow_point(&t.ray.at(h.distance_m));
                }
            }
            let mut per_light = Vec::new();
            let occluders = if region.min[0] <= region.max[0] {
                for a in 0..3 {
                    // Room for the shadow rays' offset off the surface.
                    let pad = 1.0e-5 * (1.0 + region.min[a].abs().max(region.max[a].abs()));
                    region.min[a] -= pad;
                    region.max[a] += pad;
                }
                world
                    .lighting
                    .shadow_candidates(&world.shadow_bvh, &region, &mut per_light);
                Occluders::Culled {
                    bvh: &world.shadow_bvh,
                    per_light: &per_light,
                }
            } else {
                Occluders::All(&world.shadow_bvh)
            };
            world.shade_hits_with(
                &occluders,
                traced,
                |t| (&t.ray, t.hit.as_ref()),
                pixel_rad,
                specular,
                |i, radiance| {
                    if let Some(o) = traced.get(i).and_then(|t| strip.get_mut(t.local)) {
                        *o = radiance;
                    }
                },
            );
        });
        out
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use texel::rays::RayTable;
    use texel::{Distortion, PlumbBob};

    use super::*;

    /// A camera's rays through pixel centres are the sensor's ray table to the bit,
    /// pixels outside the distortion's domain included (zero rays in both).
    #[test]
    fn centre_rays_are_texels_ray_table_bit_for_bit() {
        let camera = PinholeCamera {
            width: 40,
            height: 30,
            fx: 15.0,
            fy: 15.5,
            cx: 19.3,
            cy: 14.6,
            skew: 0.2,
            distortion: Distortion::PlumbBob(PlumbBob {
                k1: -0.35,
                k2: 0.02,
                p1: 0.001,
                p2: -0.002,
                k3: 0.0,
            }),
        };
        let table = RayTable::new(&camera);
        let (expected, valid) = table.rays();
        let ours = CameraRays::new(&camera);
        let bits = |rays: &[[f32; 3]]| -> Vec<[u32; 3]> {
            rays.iter().map(|r| r.map(f32::to_bits)).collect()
        };
        assert_eq!(bits(&ours.rays), bits(expected));
        let invalid = valid.iter().filter(|v| !**v).count();
        assert!(invalid > 0 && invalid < valid.len(), "{invalid} invalid");
    }
}
