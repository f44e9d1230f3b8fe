//! Scan culling on the CPU in f64: a scan is not drawn when its bounding sphere lies
//! outside the view frustum, or when no point of its bounding box can have a
//! positive point-of-view confidence (the virtual camera is behind it as seen from its
//! acquisition centre of projection; Sec. 3: "any scan located on the backside of a
//! 3-D texel model should not be processed").

use nalgebra::{Point3, Vector3};
use texel::{Pose, TexelScan};

use crate::camera::VirtualCamera;

/// A scan's vertex bounds in its own frame: the box and the sphere around it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanBounds {
    pub centre_scan: [f64; 3],
    pub radius_m: f64,
    pub min_scan: [f64; 3],
    pub max_scan: [f64; 3],
}

impl ScanBounds {
    /// The sphere around the bounding box of the vertices; `None` for an empty scan.
    pub fn of(scan: &TexelScan) -> Option<Self> {
        let (lo, hi) = scan.bounds()?;
        let centre = [0, 1, 2].map(|k| 0.5 * (f64::from(lo[k]) + f64::from(hi[k])));
        let radius = scan
            .vertices
            .iter()
            .map(|v| {
                let d = [0, 1, 2].map(|k| f64::from(v[k]) - centre[k]);
                (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
            })
            .fold(0.0f64, f64::max);
        // A little slack for the f32 vertices.
        Some(Self {
            centre_scan: centre,
            radius_m: radius * (1.0 + 1e-6) + 1e-6,
            min_scan: lo.map(|v| f64::from(v) - 1e-6),
            max_scan: hi.map(|v| f64::from(v) + 1e-6),
        })
    }
}

/// Why a scan is or is not drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Visibility {
    Visible,
    OutsideFrustum,
    FacingAway,
}

/// Classifies one scan for one camera.
pub fn classify(
    bounds: &ScanBounds,
    cop_scan: [f64; 3],
    world_from_scan: &Pose,
    camera: &VirtualCamera,
) -> Visibility {
    let view_from_scan = camera.view_from_world() * world_from_scan;
    let c = view_from_scan * Point3::from(bounds.centre_scan);
    let r = bounds.radius_m;
    if outside_frustum(&c.coords, r, camera) {
        return Visibility::OutsideFrustum;
    }
    // POV confidence at p is positive iff (cop_a - p)·(cop_v - p) > 0, i.e. iff p lies
    // outside the ball whose diameter is the segment between the two COPs (Thales).
    // The box is convex, so it lies in that ball iff its eight corners do.
    let cop = view_from_scan * Point3::from(cop_scan);
    let centre = cop.coords * 0.5; // the virtual COP is the view frame's origin
    let radius = cop.coords.norm() * 0.5;
    let inside = (0..8).all(|i| {
        let corner = [0, 1, 2].map(|k| {
            if i >> k & 1 == 0 {
                bounds.min_scan[k]
            } else {
                bounds.max_scan[k]
            }
        });
        let p = view_from_scan * Point3::from(corner);
        (p.coords - centre).norm() <= radius
    });
    if inside {
        return Visibility::FacingAway;
    }
    Visibility::Visible
}

/// Sphere entirely behind the near plane or outside a side plane (far is infinite).
fn outside_frustum(c: &Vector3<f64>, r: f64, camera: &VirtualCamera) -> bool {
    if c.z + r < camera.near_m {
        return true;
    }
    let ty = camera.tan_half_fov_y();
    let tx = ty * camera.aspect();
    // Inside when |x| <= z tx: the plane x - z tx = 0 with unit normal (1, 0, -tx)/n.
    let side = |coord: f64, t: f64| (coord.abs() - c.z * t) / (1.0 + t * t).sqrt() > r;
    side(c.x, tx) || side(c.y, ty)
}

#[cfg(test)]
mod tests {
    use super::*;
    use texel::pose::pose_from_parts;

    #[test]
    fn spheres_are_classified() {
        let cam = VirtualCamera::new(Pose::identity(), 60.0, 100, 100).unwrap();
        let b = ScanBounds {
            centre_scan: [0.0, 0.0, 5.0],
            radius_m: 3f64.sqrt(),
            min_scan: [-1.0, -1.0, 4.0],
            max_scan: [1.0, 1.0, 6.0],
        };
        let id = Pose::identity();
        assert_eq!(classify(&b, [0.0; 3], &id, &cam), Visibility::Visible);
        let left = pose_from_parts([-20.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]).unwrap();
        assert_eq!(
            classify(&b, [0.0; 3], &left, &cam),
            Visibility::OutsideFrustum
        );
        let behind = pose_from_parts([0.0, 0.0, -10.0], [0.0, 0.0, 0.0, 1.0]).unwrap();
        assert_eq!(
            classify(&b, [0.0; 3], &behind, &cam),
            Visibility::OutsideFrustum
        );
        // Acquired from z = 12 looking back: the virtual camera at 0 sees its back.
        assert_eq!(
            classify(&b, [0.0, 0.0, 12.0], &id, &cam),
            Visibility::FacingAway
        );
    }
}
