//! The renderable world: primitives in a BVH, materials, lights and background, and
//! the per-ray queries the renderers are made of (closest surface, lidar echo,
//! shaded radiance).

use std::sync::Arc;

use nalgebra::{Point3, Vector3};

use crate::geometry::{Bvh, Hit, Ray};
use crate::light::{Lighting, Occluders, ShadePoint};
use crate::material::{Material, Rgb, Texture, luminance};
use crate::noise::LANES;

/// The smallest |cos| used to widen a texture footprint at grazing incidence, so the
/// footprint stays finite.
const MIN_FOOTPRINT_COS: f64 = 0.05;

#[derive(Debug, Clone)]
pub struct World {
    /// Shared, so that a world under other lights ([`Self::with_lighting`]) costs no
    /// copy of the geometry.
    pub bvh: Arc<Bvh>,
    /// The primitives of objects that cast shadows (`casts_shadows`, default true):
    /// what shadow rays are traced against.
    pub shadow_bvh: Arc<Bvh>,
    pub materials: Vec<Material>,
    pub lighting: Lighting,
    pub background: Rgb,
}

/// The ground truth of one ray: where it meets the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthHit {
    /// Distance along the unit ray, metres.
    pub distance_m: f64,
    /// World point.
    pub point: Point3<f64>,
    /// Unit geometric normal, turned to face the ray's origin.
    pub normal: Vector3<f64>,
    /// Index of the object in the scene (see `Scene::objects`).
    pub object: u32,
    pub material: u32,
}

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

impl World {
    /// The same geometry and materials under `lighting` (the geometry is shared).
    pub fn with_lighting(&self, lighting: Lighting) -> Self {
        Self {
            bvh: self.bvh.clone(),
            shadow_bvh: self.shadow_bvh.clone(),
            materials: self.materials.clone(),
            lighting,
            background: self.background,
        }
    }

    /// The nearest surface along `ray` (unit direction).
    #[inline]
    pub fn trace(&self, ray: &Ray) -> Option<Hit> {
        self.bvh.closest_hit(ray, f64::INFINITY)
    }

    /// Ground truth for a ray; `None` when it meets nothing or is not finite.
    pub fn truth(&self, ray: &Ray) -> Option<TruthHit> {
        let h = self.trace(ray)?;
        let normal = if h.normal.dot(&ray.dir) > 0.0 {
            -h.normal
        } else {
            h.normal
        };
        Some(TruthHit {
            distance_m: h.distance_m,
            point: ray.at(h.distance_m),
            normal,
            object: h.object,
            material: h.material,
        })
    }

    /// The lidar echo of a ray: range, incidence and reflectivity. `beam_rad` is the
    /// beam's angular width (texture footprint for the reflectivity lookup).
    #[inline]
    pub fn surface_sample(&self, ray: &Ray, beam_rad: f64) -> Option<SurfaceSample> {
        self.echo_of_hit(ray, self.trace(ray), beam_rad)
    }

    /// [`Self::surface_sample`] for the hit `hit` of `ray`, found by the caller.
    #[inline]
    pub fn echo_of_hit(&self, ray: &Ray, hit: Option<Hit>, beam_rad: f64) -> Option<SurfaceSample> {
        let (h, material) = self.material_of(hit.as_ref())?;
        let footprint = footprint_m(h.distance_m, beam_rad, echo_cos(ray, h));
        Some(echo(ray, h, material.lidar_albedo(h.uv_m, footprint)))
    }

    /// Linear radiance seen along `ray` by a pixel `pixel_rad` wide; `specular`
    /// scales the materials' glossy lobe (`None` = Lambertian only).
    #[inline]
    pub fn radiance(&self, ray: &Ray, pixel_rad: f64, specular: Option<f32>) -> Rgb {
        self.shade_hit(ray, self.trace(ray), pixel_rad, specular)
    }

    /// Radiance towards the eye of the hit `hit` of `ray` (background for none).
    #[inline]
    pub fn shade_hit(
        &self,
        ray: &Ray,
        hit: Option<Hit>,
        pixel_rad: f64,
        specular: Option<f32>,
    ) -> Rgb {
        self.shade_hit_with(
            &Occluders::All(&self.shadow_bvh),
            ray,
            hit,
            pixel_rad,
            specular,
        )
    }

    /// [`Self::shade_hit`] with the shadow casters chosen by the caller (see
    /// [`Occluders`]).
    #[inline]
    pub fn shade_hit_with(
        &self,
        occluders: &Occluders<'_>,
        ray: &Ray,
        hit: Option<Hit>,
        pixel_rad: f64,
        specular: Option<f32>,
    ) -> Rgb {
        let Some((h, material)) = self.material_of(hit.as_ref()) else {
            return self.background;
        };
        let cos = h.normal.dot(&ray.dir);
        let albedo = material.albedo(h.uv_m, footprint_m(h.distance_m, pixel_rad, cos.abs()));
        self.shade_surface(occluders, ray, h, material, albedo, specular)
    }

    /// Radiance towards the eye of the hit `h` of `ray`, of material `material` and
    /// diffuse reflectance `albedo` there.
    #[inline]
    fn shade_surface(
        &self,
        occluders: &Occluders<'_>,
        ray: &Ray,
        h: &Hit,
        material: &Material,
        albedo: Rgb,
        specular: Option<f32>,
    ) -> Rgb {
        // Surfaces are two-sided: the normal is turned towards the eye.
        let normal = if h.normal.dot(&ray.dir) > 0.0 {
            -h.normal
        } else {
            h.normal
        };
        self.lighting.shade_with(
            occluders,
            &ShadePoint {
                point: ray.at(h.distance_m),
                normal,
                to_eye: -ray.dir,
                albedo,
                material,
            },
            specular,
        )
    }
}

/// Lookups of one noise texture waiting to be made [`LANES`] at a time.
#[derive(Debug, Clone, Copy, Default)]
struct PendingLookups {
    /// Index of each lookup's hit.
    hit: [u32; LANES],
    uv_m: [[f64; 2]; LANES],
    footprint_m: [f64; LANES],
    len: usize,
}

impl PendingLookups {
    /// Makes the waiting lookups (a short batch repeats its last one in the spare
    /// lanes) and stores each albedo at its hit's index.
    fn flush(&mut self, texture: &Texture, albedos: &mut [Rgb]) {
        let Some(last) = self.len.checked_sub(1) else {
            return;
        };
        for l in self.len..LANES {
            self.uv_m[l] = self.uv_m[last];
            self.footprint_m[l] = self.footprint_m[last];
        }
        let colours = texture.sample_lanes(&self.uv_m, &self.footprint_m);
        for (&i, c) in self.hit.iter().zip(colours).take(self.len) {
            if let Some(a) = albedos.get_mut(i as usize) {
                *a = c;
            }
        }
        self.len = 0;
    }
}

impl World {
    /// The albedo of every item that `lookup` gives a texture lookup (material
    /// index, texture coordinates, footprint), in item order (zero for the others),
    /// bit for bit what [`Material::albedo`] gives: a noise texture's lookups are
    /// made [`LANES`] at a time ([`Texture::sample_lanes`]), material by material.
    fn albedos_batched<T>(
        &self,
        items: &[T],
        lookup: impl Fn(&T) -> Option<(u32, [f64; 2], f64)>,
    ) -> Vec<Rgb> {
        let mut albedos = vec![[0.0f32; 3]; items.len()];
        let mut pending = vec![PendingLookups::default(); self.materials.len()];
        for (i, item) in items.iter().enumerate() {
            let Some((m, uv_m, footprint)) = lookup(item) else {
                continue;
            };
            let (Some(material), Some(p)) =
                (self.materials.get(m as usize), pending.get_mut(m as usize))
            else {
                continue;
            };
            if !material.texture.is_noise() {
                if let Some(a) = albedos.get_mut(i) {
                    *a = material.albedo(uv_m, footprint);
                }
                continue;
            }
            if let Some(l) = (p.len < LANES).then_some(p.len) {
                p.hit[l] = i as u32;
                p.uv_m[l] = uv_m;
                p.footprint_m[l] = footprint;
                p.len += 1;
            }
            if p.len == LANES {
                p.flush(&material.texture, &mut albedos);
            }
        }
        for (p, material) in pending.iter_mut().zip(&self.materials) {
            p.flush(&material.texture, &mut albedos);
        }
        albedos
    }

    /// [`Self::echo_of_hit`] for the rays and hits of `items` (`ray_hit` gives them),
    /// bit for bit the same echoes, `out(i, echo)` for the `i`-th, with the texture
    /// lookups batched ([`Self::albedos_batched`]).
    pub fn echoes_of_hits<T>(
        &self,
        items: &[T],
        ray_hit: impl Fn(&T) -> (&Ray, Option<&Hit>),
        beam_rad: f64,
        mut out: impl FnMut(usize, Option<SurfaceSample>),
    ) {
        // Step 1: reflectivity lookups of materials that take the diffuse luminance.
        let albedos = self.albedos_batched(items, |item| {
            let (ray, hit) = ray_hit(item);
            let (h, material) = self.material_of(hit)?;
            if material.lidar_reflectivity.is_some() {
                return None;
            }
            let footprint = footprint_m(h.distance_m, beam_rad, echo_cos(ray, h));
            Some((h.material, h.uv_m, footprint))
        });
        // Step 2: the echoes (as in `echo_of_hit`).
        for (i, (item, albedo)) in items.iter().zip(&albedos).enumerate() {
            let (ray, hit) = ray_hit(item);
            let echo = self.material_of(hit).map(|(h, material)| {
                let reflectivity = material
                    .lidar_reflectivity
                    .unwrap_or_else(|| luminance(*albedo));
                echo(ray, h, reflectivity)
            });
            out(i, echo);
        }
    }

    /// [`Self::shade_hit_with`] for the rays and hits of `items` (`ray_hit` gives
    /// them), bit for bit the same radiance, `out(i, radiance)` for the `i`-th: the
    /// texture lookups are made first, batched ([`Self::albedos_batched`]), then each
    /// point is shaded.
    pub fn shade_hits_with<T>(
        &self,
        occluders: &Occluders<'_>,
        items: &[T],
        ray_hit: impl Fn(&T) -> (&Ray, Option<&Hit>),
        pixel_rad: f64,
        specular: Option<f32>,
        mut out: impl FnMut(usize, Rgb),
    ) {
        // Step 1: albedos (as in `shade_hit_with`).
        let albedos = self.albedos_batched(items, |item| {
            let (ray, hit) = ray_hit(item);
            let (h, _) = self.material_of(hit)?;
            let cos = h.normal.dot(&ray.dir);
            Some((
                h.material,
                h.uv_m,
                footprint_m(h.distance_m, pixel_rad, cos.abs()),
            ))
        });
        // Step 2: shading.
        for (i, (item, albedo)) in items.iter().zip(&albedos).enumerate() {
            let (ray, hit) = ray_hit(item);
            let radiance = match self.material_of(hit) {
                Some((h, material)) => {
                    self.shade_surface(occluders, ray, h, material, *albedo, specular)
                }
                None => self.background,
            };
            out(i, radiance);
        }
    }

    /// A hit and its material (`None` for no hit or an unknown material).
    #[inline]
    fn material_of<'h>(&self, hit: Option<&'h Hit>) -> Option<(&'h Hit, &Material)> {
        let h = hit?;
        Some((h, self.materials.get(h.material as usize)?))
    }
}

/// The incidence cosine a lidar echo reports for the hit `h` of `ray`.
#[inline]
fn echo_cos(ray: &Ray, h: &Hit) -> f64 {
    h.normal.dot(&ray.dir).abs().min(1.0)
}

/// The lidar echo of the hit `h` of `ray` with the reflectivity there.
#[inline]
fn echo(ray: &Ray, h: &Hit, reflectivity: f32) -> SurfaceSample {
    SurfaceSample {
        range_m: h.distance_m,
        cos_incidence: echo_cos(ray, h),
        reflectivity,
        object: h.object,
    }
}

/// Width in metres of a cone `angle_rad` wide at `distance_m` on a surface seen at
/// incidence cosine `cos`: the geometric mean of the two axes of its ellipse.
#[inline]
fn footprint_m(distance_m: f64, angle_rad: f64, cos: f64) -> f64 {
    distance_m * angle_rad / cos.max(MIN_FOOTPRINT_COS).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Scene;
    use crate::render::{CameraRays, world_ray};
    use crate::simulator::rescale_camera;

    /// The rays of a small EO image of `lab` from three poses and their hits, with
    /// every 37th hit given an unknown material.
    fn lab_hits() -> (World, Vec<(Ray, Option<Hit>)>, f64) {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/scenes/lab.toml");
        let scene = Scene::load(&path).expect("lab loads");
        let mut world = (*scene.world).clone();
        // Lidar reflectivity given, on a noise material and on the checkered cube.
        for m in &mut world.materials {
            if m.name == "plaster" || m.name == "cube" {
                m.lidar_reflectivity = Some(0.3);
            }
        }
        let rays = CameraRays::new(&rescale_camera(&scene.sensor().eo, 96, 72));
        let mut items = Vec::new();
        for frame in [0, 9, 23] {
            let pose = scene.trajectory.frame_pose(frame);
            for r in &rays.rays {
                if let Some(ray) = world_ray(&pose, r) {
                    let mut hit = world.trace(&ray);
                    if items.len() % 37 == 0
                        && let Some(h) = &mut hit
                    {
                        h.material = 999;
                    }
                    items.push((ray, hit));
                }
            }
        }
        (world, items, rays.pixel_rad)
    }

    /// Batched texture lookups (noise textures four points per evaluation) shade every
    /// hit bit for bit as one at a time does, and give the same lidar echoes.
    #[test]
    fn batched_lookups_match_one_ray_at_a_time_bit_for_bit() {
        let (world, items, pixel_rad) = lab_hits();
        let noise_hits = items
            .iter()
            .filter(|(_, h)| {
                h.and_then(|h| world.materials.get(h.material as usize))
                    .is_some_and(|m| m.texture.is_noise())
            })
            .count();
        assert!(
            noise_hits > items.len() / 3,
            "{noise_hits} of {}",
            items.len()
        );
        let occluders = Occluders::All(&world.shadow_bvh);
        // Tile-sized groups, as the renderer calls it, and one group of everything.
        for group in [64, items.len()] {
            for (g, chunk) in items.chunks(group).enumerate() {
                let mut seen = 0;
                world.shade_hits_with(
                    &occluders,
                    chunk,
                    |(ray, hit)| (ray, hit.as_ref()),
                    pixel_rad,
                    Some(1.0),
                    |i, radiance| {
                        let (ray, hit) = &chunk[i];
                        let one = world.shade_hit_with(&occluders, ray, *hit, pixel_rad, Some(1.0));
                        assert_eq!(
                            radiance.map(f32::to_bits),
                            one.map(f32::to_bits),
                            "group {g} item {i}"
                        );
                        seen += 1;
                    },
                );
                assert_eq!(seen, chunk.len());
                let mut seen = 0;
                world.echoes_of_hits(
                    chunk,
                    |(ray, hit)| (ray, hit.as_ref()),
                    2.0e-3,
                    |i, echo| {
                        let (ray, hit) = &chunk[i];
                        let one = world.echo_of_hit(ray, *hit, 2.0e-3);
                        assert_eq!(
                            echo.map(|e| (
                                e.range_m.to_bits(),
                                e.cos_incidence.to_bits(),
                                e.reflectivity.to_bits(),
                                e.object
                            )),
                            one.map(|e| (
                                e.range_m.to_bits(),
                                e.cos_incidence.to_bits(),
                                e.reflectivity.to_bits(),
                                e.object
                            )),
                            "group {g} item {i}"
                        );
                        seen += 1;
                    },
                );
                assert_eq!(seen, chunk.len());
            }
        }
    }
}
