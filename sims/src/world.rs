//! The renderable world: primitives in a BVH, materials, lights and background, and
//! the per-ray queries the renderers are made of (closest surface, lidar echo,
//! shaded radiance).

use nalgebra::{Point3, Vector3};

use crate::geometry::{Bvh, Hit, Ray};
use crate::light::{Lighting, Occluders, ShadePoint};
use crate::material::{Material, Rgb};
use crate::render::SurfaceSample;

/// The smallest |cos| used to widen a texture footprint at grazing incidence, so the
/// footprint stays finite.
const MIN_FOOTPRINT_COS: f64 = 0.05;

#[derive(Debug, Clone)]
pub struct World {
    pub bvh: Bvh,
    /// The primitives of objects that cast shadows (`casts_shadows`, default true):
    /// what shadow rays are traced against.
    pub shadow_bvh: Bvh,
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

impl World {
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
        let h = hit?;
        let cos = h.normal.dot(&ray.dir).abs().min(1.0);
        let material = self.materials.get(h.material as usize)?;
        let footprint = footprint_m(h.distance_m, beam_rad, cos);
        Some(SurfaceSample {
            range_m: h.distance_m,
            cos_incidence: cos,
            reflectivity: material.lidar_albedo(h.uv_m, footprint),
            object: h.object,
        })
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
        let Some(h) = hit else {
            return self.background;
        };
        let Some(material) = self.materials.get(h.material as usize) else {
            return self.background;
        };
        let cos = h.normal.dot(&ray.dir);
        let normal = if cos > 0.0 { -h.normal } else { h.normal };
        let albedo = material.albedo(h.uv_m, footprint_m(h.distance_m, pixel_rad, cos.abs()));
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

/// Width in metres of a cone `angle_rad` wide at `distance_m` on a surface seen at
/// incidence cosine `cos`: the geometric mean of the two axes of its ellipse.
#[inline]
fn footprint_m(distance_m: f64, angle_rad: f64, cos: f64) -> f64 {
    distance_m * angle_rad / cos.max(MIN_FOOTPRINT_COS).sqrt()
}
