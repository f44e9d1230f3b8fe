//! Where f64 poses meet the GPU's f32: every pose is first taken relative to a nearby
//! frame (the virtual camera) in f64, where large world coordinates cancel, and only
//! that relative transform is rounded to f32. A model at UTM coordinates (~5e6 m)
//! therefore renders as well as one at the origin.

use glam::{DMat4, Mat4};
use texel::Pose;

/// `origin_from_x` in f64: a pose relative to a nearby origin frame, composed before
/// any rounding. For CPU work that stays in f64 (culling).
pub fn pose_relative(origin_from_world: &Pose, world_from_x: &Pose) -> DMat4 {
    let origin_from_x: [[f64; 4]; 4] = (origin_from_world * world_from_x).to_homogeneous().into();
    DMat4::from_cols_array_2d(&origin_from_x)
}

/// `origin_from_x` for the GPU: composed in f64 by [`pose_relative`], then rounded to
/// f32. The one f64 -> f32 conversion of positions and orientations that the GPU sees;
/// a point (a centre of projection) goes through it as the origin of a frame.
pub fn gpu_from_pose_relative(origin_from_world: &Pose, world_from_x: &Pose) -> Mat4 {
    pose_relative(origin_from_world, world_from_x).as_mat4()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use texel::pose::pose_from_parts;

    #[test]
    fn relative_transforms_keep_f32_precision_far_from_the_origin() {
        // A camera and a scan 3 m apart, 5e6 m from the world origin: in f32 the world
        // positions alone would be off by up to 0.25 m.
        let world_from_view =
            pose_from_parts([5.0e6, -4.0e6, 1234.5], [0.1, 0.2, -0.05, 0.97]).unwrap();
        let view_from_scan = pose_from_parts([0.5, -0.25, 3.0], [0.0, 0.6, 0.0, 0.8]).unwrap();
        let world_from_scan = world_from_view * view_from_scan;
        let got = gpu_from_pose_relative(&world_from_view.inverse(), &world_from_scan);
        let want = gpu_from_pose_relative(&Pose::identity(), &view_from_scan);
        assert!(got.abs_diff_eq(want, 1e-6), "{got} vs {want}");
        let p = got.transform_point3(Vec3::new(0.1, 0.2, 0.3));
        let q = view_from_scan * nalgebra::Point3::new(0.1, 0.2, 0.3);
        let error = (p.as_dvec3() - glam::DVec3::new(q.x, q.y, q.z)).length();
        assert!(error < 1e-6, "{error}");
    }
}
