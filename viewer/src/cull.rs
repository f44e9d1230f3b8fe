//! Scan culling on the CPU in f64: a scan is not drawn when its bounding sphere lies
//! outside the view frustum, or when no point of its bounding box can have a
//! positive point-of-view confidence (the virtual camera is behind it as seen from its
//! acquisition centre of projection; Sec. 3: "any scan located on the backside of a
//! 3-D texel model should not be processed"). Works in the view frame, with the scan
//! taken there by the same camera-relative transform the GPU gets (before rounding).

use glam::{BVec3, DVec3};
use texel::model::ScanListing;
use texel::{Pose, TexelScan};

use crate::camera::VirtualCamera;
use crate::gpu::pose_relative;

/// A scan's vertex bounds in its own frame: the box and the sphere around it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanBounds {
    pub centre_scan: DVec3,
    pub radius_m: f64,
    pub min_scan: DVec3,
    pub max_scan: DVec3,
}

impl ScanBounds {
    /// The sphere around the bounding box of the vertices; `None` for an empty scan.
    pub fn of(scan: &TexelScan) -> Option<Self> {
        let (lo, hi) = scan.bounds()?;
        let (lo, hi) = (
            DVec3::from_array(lo.map(f64::from)),
            DVec3::from_array(hi.map(f64::from)),
        );
        let centre = 0.5 * (lo + hi);
        let radius = scan
            .vertices
            .iter()
            .map(|v| DVec3::from_array(v.map(f64::from)).distance(centre))
            .fold(0.0f64, f64::max);
        // A little slack for the f32 vertices.
        Some(Self {
            centre_scan: centre,
            radius_m: radius * (1.0 + 1e-6) + 1e-6,
            min_scan: lo - 1e-6,
            max_scan: hi + 1e-6,
        })
    }

    /// The sphere around a listing's box (what is known of a scan before its data):
    /// never smaller than [`ScanBounds::of`] gives for the data. `None` when the box
    /// is not finite or inverted.
    pub fn of_listing(listing: &ScanListing) -> Option<Self> {
        let lo = DVec3::from_array(listing.bounds_min_m.map(f64::from));
        let hi = DVec3::from_array(listing.bounds_max_m.map(f64::from));
        if !(lo.is_finite() && hi.is_finite()) || lo.cmpgt(hi).any() {
            return None;
        }
        let centre = 0.5 * (lo + hi);
        Some(Self {
            centre_scan: centre,
            radius_m: 0.5 * (hi - lo).length() * (1.0 + 1e-6) + 1e-6,
            min_scan: lo - 1e-6,
            max_scan: hi + 1e-6,
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

/// Classifies one scan, whose acquisition centre of projection is `cop_scan` (scan
/// frame), for one camera.
pub fn classify(
    bounds: &ScanBounds,
    cop_scan: DVec3,
    world_from_scan: &Pose,
    camera: &VirtualCamera,
) -> Visibility {
    let view_from_scan = pose_relative(&camera.view_from_world(), world_from_scan);
    let c = view_from_scan.transform_point3(bounds.centre_scan);
    let r = bounds.radius_m;
    if outside_frustum(c, r, camera) {
        return Visibility::OutsideFrustum;
    }
    // POV confidence at p is positive iff (cop_a - p)·(cop_v - p) > 0, i.e. iff p lies
    // outside the ball whose diameter is the segment between the two COPs (Thales).
    // The box is convex, so it lies in that ball iff its eight corners do.
    let cop = view_from_scan.transform_point3(cop_scan);
    let centre = cop * 0.5; // the virtual COP is the view frame's origin
    let radius = cop.length() * 0.5;
    let inside = (0..8u32).all(|i| {
        let take_min = BVec3::new(i & 1 == 0, i & 2 == 0, i & 4 == 0);
        let corner = DVec3::select(take_min, bounds.min_scan, bounds.max_scan);
        let p = view_from_scan.transform_point3(corner);
        (p - centre).length() <= radius
    });
    if inside {
        return Visibility::FacingAway;
    }
    Visibility::Visible
}

/// Sphere entirely behind the near plane or outside a side plane (far is infinite).
fn outside_frustum(c: DVec3, r: f64, camera: &VirtualCamera) -> bool {
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

    /// Classifies the test box under `world_from_origin`, the camera at that origin.
    fn cases(world_from_origin: &Pose) -> Vec<Visibility> {
        let cam = VirtualCamera::new(*world_from_origin, 60.0, 100, 100).unwrap();
        let b = ScanBounds {
            centre_scan: DVec3::new(0.0, 0.0, 5.0),
            radius_m: 3f64.sqrt(),
            min_scan: DVec3::new(-1.0, -1.0, 4.0),
            max_scan: DVec3::new(1.0, 1.0, 6.0),
        };
        let at =
            |t: [f64; 3]| world_from_origin * pose_from_parts(t, [0.0, 0.0, 0.0, 1.0]).unwrap();
        vec![
            classify(&b, DVec3::ZERO, &at([0.0; 3]), &cam),
            classify(&b, DVec3::ZERO, &at([-20.0, 0.0, 0.0]), &cam),
            classify(&b, DVec3::ZERO, &at([0.0, 0.0, -10.0]), &cam),
            // Acquired from z = 12 looking back: the virtual camera at 0 sees its back.
            classify(&b, DVec3::new(0.0, 0.0, 12.0), &at([0.0; 3]), &cam),
        ]
    }

    #[test]
    fn spheres_are_classified() {
        use Visibility::*;
        let want = vec![Visible, OutsideFrustum, OutsideFrustum, FacingAway];
        assert_eq!(cases(&Pose::identity()), want);
        // The same relative placement at UTM-sized coordinates.
        let far = pose_from_parts([5.0e6, -4.0e6, 1234.5], [0.1, 0.2, -0.05, 0.97]).unwrap();
        assert_eq!(cases(&far), want);
    }
}
