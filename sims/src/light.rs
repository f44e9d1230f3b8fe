//! Lights and the shading model.
//!
//! Radiance leaving a surface point towards the camera (linear RGB, arbitrary units
//! in which 1.0 is white at exposure 0):
//!
//! ```text
//! L = albedo ⊙ (ambient + Σ_l E_l · max(0, n·l) · V_l)
//!   + [specular effect only] k_s · Σ_l E_l · max(0, n·h)^shininess · [n·l > 0] · V_l
//! ```
//!
//! with `E_l` the light's colour × intensity (divided by the squared distance for a
//! point light, whose intensity is given at 1 m), `V_l` 1 unless the light casts
//! shadows and the shadow ray is blocked, and `n` the normal turned towards the
//! camera (surfaces are two-sided).

use nalgebra::{Point3, Vector3};

use crate::geometry::{Aabb, Bvh, Ray};
use crate::material::{Material, Rgb};

/// Point lights closer than this to the shaded point are treated as this far (m),
/// so the inverse-square law stays finite.
const MIN_LIGHT_DISTANCE_M: f64 = 1.0e-3;

/// Shadow rays start this far off the surface (m) to clear it.
pub const SHADOW_BIAS_M: f64 = 1.0e-6;

#[derive(Debug, Clone, PartialEq)]
pub enum Light {
    /// Light from a direction; `towards_light` is a unit vector.
    Directional {
        towards_light: Vector3<f64>,
        color: Rgb,
        intensity: f32,
        shadows: bool,
    },
    /// A point light; `intensity` is the irradiance at 1 m.
    Point {
        position: Point3<f64>,
        color: Rgb,
        intensity: f32,
        shadows: bool,
    },
}

/// The scene's lighting.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Lighting {
    pub ambient: Rgb,
    pub lights: Vec<Light>,
}

/// Everything shading needs about one visible point.
pub struct ShadePoint<'a> {
    pub point: Point3<f64>,
    /// Unit normal facing the camera.
    pub normal: Vector3<f64>,
    /// Unit vector from the point towards the camera.
    pub to_eye: Vector3<f64>,
    pub albedo: Rgb,
    pub material: &'a Material,
}

/// What shadow rays are tested against.
#[derive(Debug, Clone, Copy)]
pub enum Occluders<'a> {
    /// Every shadow caster, through the shadow BVH.
    All(&'a Bvh),
    /// Per light (in [`Lighting::lights`] order), the shadow casters that can lie
    /// between it and the points being shaded (from [`Bvh::overlapping`]), or `None`
    /// to test them all.
    Culled {
        bvh: &'a Bvh,
        per_light: &'a [Option<Vec<u32>>],
    },
}

impl Occluders<'_> {
    /// True when a caster blocks the shadow ray of light `light` before `t_max`.
    #[inline]
    fn blocked(&self, light: usize, ray: &Ray, t_max: f64) -> bool {
        match self {
            Self::All(bvh) => bvh.any_hit(ray, t_max),
            Self::Culled { bvh, per_light } => match per_light.get(light) {
                Some(Some(candidates)) => bvh.any_hit_among(ray, t_max, candidates),
                _ => bvh.any_hit(ray, t_max),
            },
        }
    }
}

impl Lighting {
    /// For a group of points inside `region` (padded by the shadow rays' offset), the
    /// casters each shadowed point light can be hidden behind: those whose bounds
    /// overlap the box around the light and `region`, which holds every shadow ray
    /// segment of the group, and meet the cone from the light around `region`
    /// ([`SegmentFan`]). Directional lights and lights without shadows get `None`.
    pub fn shadow_candidates(&self, bvh: &Bvh, region: &Aabb, out: &mut Vec<Option<Vec<u32>>>) {
        out.resize_with(self.lights.len(), || None);
        for (light, slot) in self.lights.iter().zip(out.iter_mut()) {
            match light {
                Light::Point {
                    position,
                    shadows: true,
                    ..
                } => {
                    let mut b = *region;
                    b.grow_point(position);
                    let list = slot.get_or_insert_with(Vec::new);
                    bvh.overlapping(&b, list);
                    let fan = SegmentFan::new(position, region);
                    list.retain(|&i| {
                        bvh.primitive(i)
                            .and_then(|p| p.bounds())
                            .is_none_or(|caster| fan.may_meet(&caster))
                    });
                }
                _ => *slot = None,
            }
        }
    }

    /// Radiance towards the eye; `specular` (a multiplier on the material's `k_s`)
    /// switches the Blinn-Phong lobe on.
    pub fn shade(&self, bvh: &Bvh, p: &ShadePoint<'_>, specular: Option<f32>) -> Rgb {
        self.shade_with(&Occluders::All(bvh), p, specular)
    }

    /// [`Self::shade`] with the shadow casters given per light.
    pub fn shade_with(
        &self,
        occluders: &Occluders<'_>,
        p: &ShadePoint<'_>,
        specular: Option<f32>,
    ) -> Rgb {
        let mut diffuse = self.ambient;
        let mut glossy = [0.0f32; 3];
        let k_s = specular.map_or(0.0, |s| s * p.material.specular);
        let use_specular = k_s > 0.0;
        for (index, light) in self.lights.iter().enumerate() {
            let (to_light, distance, irradiance, shadows) = match light {
                Light::Directional {
                    towards_light,
                    color,
                    intensity,
                    shadows,
                } => (
                    *towards_light,
                    f64::INFINITY,
                    [
                        color[0] * intensity,
                        color[1] * intensity,
                        color[2] * intensity,
                    ],
                    *shadows,
                ),
                Light::Point {
                    position,
                    color,
                    intensity,
                    shadows,
                } => {
                    let d = position - p.point;
                    let dist = d.norm().max(MIN_LIGHT_DISTANCE_M);
                    // One division for the direction and the falloff: divisions and
                    // square roots are the slow part of shading a pixel.
                    let inv_dist = 1.0 / dist;
                    let falloff = (*intensity as f64 * (inv_dist * inv_dist)) as f32;
                    (
                        d * inv_dist,
                        dist,
                        [color[0] * falloff, color[1] * falloff, color[2] * falloff],
                        *shadows,
                    )
                }
            };
            let cos = p.normal.dot(&to_light);
            if cos <= 0.0 {
                continue;
            }
            if shadows {
                let ray = Ray {
                    origin: p.point + p.normal * SHADOW_BIAS_M,
                    dir: to_light,
                };
                if occluders.blocked(index, &ray, distance - 2.0 * SHADOW_BIAS_M) {
                    continue;
                }
            }
            let c = cos as f32;
            for k in 0..3 {
                diffuse[k] += irradiance[k] * c;
            }
            if use_specular {
                let h = to_light + p.to_eye;
                let len = h.norm();
                if len > 1.0e-12 {
                    let nh = (p.normal.dot(&h) / len).max(0.0) as f32;
                    let lobe = k_s * nh.powf(p.material.shininess.max(1.0));
                    for k in 0..3 {
                        glossy[k] += irradiance[k] * lobe;
                    }
                }
            }
        }
        [
            p.albedo[0] * diffuse[0] + glossy[0],
            p.albedo[1] * diffuse[1] + glossy[1],
            p.albedo[2] * diffuse[2] + glossy[2],
        ]
    }
}

/// Every segment from a light to a point of a box (the shadow rays of a group of
/// points), bounded by a cone from the light around the box's bounding sphere, cut
/// off past the sphere's far side: a caster whose bounding sphere misses that can
/// shadow none of the points.
struct SegmentFan {
    apex: Point3<f64>,
    /// Unit axis towards the box's centre; `None` when the light is inside the
    /// box's bounding sphere (nothing is culled).
    axis: Option<Vector3<f64>>,
    half_angle_rad: f64,
    reach_m: f64,
}

/// Slack on angles (radians) so rounding never culls a caster that could shadow.
const FAN_SLACK_RAD: f64 = 1.0e-9;

impl SegmentFan {
    fn new(light: &Point3<f64>, region: &Aabb) -> Self {
        let (centre, radius) = bounding_sphere(region);
        let to_centre = centre - light;
        let distance = to_centre.norm();
        let axis = (distance > radius && distance.is_finite()).then(|| to_centre / distance);
        Self {
            apex: *light,
            axis,
            // radius < distance here, so the ratio is in [0, 1).
            half_angle_rad: (radius / distance.max(f64::MIN_POSITIVE))
                .clamp(0.0, 1.0)
                .asin(),
            reach_m: distance + radius,
        }
    }

    /// False only when no segment of the fan can meet the box `caster`.
    fn may_meet(&self, caster: &Aabb) -> bool {
        let Some(axis) = self.axis else {
            return true;
        };
        let (centre, radius) = bounding_sphere(caster);
        let to_caster = centre - self.apex;
        let distance = to_caster.norm();
        if !(distance > radius && distance.is_finite() && radius.is_finite()) {
            return true;
        }
        if distance - radius > self.reach_m {
            return false;
        }
        let caster_half_angle = (radius / distance).clamp(0.0, 1.0).asin();
        let cos = (axis.dot(&to_caster) / distance).clamp(-1.0, 1.0);
        cos.acos() <= self.half_angle_rad + caster_half_angle + FAN_SLACK_RAD
    }
}

/// Centre and radius (half the diagonal) of a box's bounding sphere.
fn bounding_sphere(b: &Aabb) -> (Point3<f64>, f64) {
    let centre = Point3::new(b.centroid(0), b.centroid(1), b.centroid(2));
    let half = Vector3::new(
        0.5 * (b.max[0] - b.min[0]),
        0.5 * (b.max[1] - b.min[1]),
        0.5 * (b.max[2] - b.min[2]),
    );
    (centre, half.norm())
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn aabb(centre: [f64; 3], half: [f64; 3]) -> Aabb {
        Aabb {
            min: [0, 1, 2].map(|a| centre[a] - half[a]),
            max: [0, 1, 2].map(|a| centre[a] + half[a]),
        }
    }

    /// Whether the segment p-q meets the box (slab test on the segment).
    fn segment_meets(p: &Point3<f64>, q: &Point3<f64>, b: &Aabb) -> bool {
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        for a in 0..3 {
            let d = q[a] - p[a];
            if d.abs() < 1e-15 {
                if p[a] < b.min[a] || p[a] > b.max[a] {
                    return false;
                }
                continue;
            }
            let (mut near, mut far) = ((b.min[a] - p[a]) / d, (b.max[a] - p[a]) / d);
            if near > far {
                std::mem::swap(&mut near, &mut far);
            }
            t0 = t0.max(near);
            t1 = t1.min(far);
        }
        t0 <= t1
    }

    proptest! {
        /// A caster that some light-to-region segment meets is never culled.
        #[test]
        fn the_fan_keeps_every_caster_a_segment_meets(
            light in prop::array::uniform3(-3.0f64..3.0),
            region_c in prop::array::uniform3(-3.0f64..3.0),
            region_h in prop::array::uniform3(0.0f64..0.3),
            caster_c in prop::array::uniform3(-3.0f64..3.0),
            caster_h in prop::array::uniform3(0.01f64..0.5),
            samples in prop::collection::vec(prop::array::uniform3(-1.0f64..1.0), 64),
        ) {
            let light = Point3::from(light);
            let region = aabb(region_c, region_h);
            let caster = aabb(caster_c, caster_h);
            let fan = SegmentFan::new(&light, &region);
            let met = samples.iter().any(|s| {
                let p = Point3::from([0, 1, 2].map(|a| region_c[a] + s[a] * region_h[a]));
                segment_meets(&light, &p, &caster)
            });
            if met {
                prop_assert!(fan.may_meet(&caster));
            }
        }
    }

    /// Casters off to the side of the fan or beyond the region are culled.
    #[test]
    fn casters_away_from_the_fan_are_culled() {
        let light = Point3::new(0.0, 0.0, 3.0);
        let region = aabb([0.0, 0.0, 0.0], [0.1, 0.1, 0.0]);
        let fan = SegmentFan::new(&light, &region);
        assert!(fan.may_meet(&aabb([0.0, 0.0, 1.5], [0.2; 3])));
        assert!(!fan.may_meet(&aabb([1.5, 0.0, 1.5], [0.2; 3])));
        assert!(!fan.may_meet(&aabb([0.0, 0.0, -1.0], [0.2; 3])));
    }
}
