//! The acquisition views VDTM textures from: where each EO image was taken and the
//! calibrated camera model (distortion included) that took it.

use nalgebra::{Point3, Vector2};
use texel::Pose;
use texel::camera::PinholeCamera;
use texel::frames::EoFrame;

/// One acquisition EO view.
#[derive(Debug, Clone, Copy)]
pub struct AcquisitionView<'a> {
    /// The view's id, as view maps and visibility lists name it.
    pub id: u32,
    /// The EO camera's optical frame (+x right, +y down, +z forward) in the world.
    pub world_from_eo: Pose,
    pub camera: &'a PinholeCamera,
    /// The image, when the caller has it (visibility needs only the geometry).
    pub image: Option<&'a EoFrame>,
}

impl AcquisitionView<'_> {
    /// The centre of projection in the world.
    pub fn centre(&self) -> Point3<f64> {
        Point3::from(self.world_from_eo.translation.vector)
    }

    /// A world point's pixel (distortion included, pixel centres at integers) and
    /// its depth along the optical axis; `None` behind the camera, outside the
    /// distortion model's domain or not finite. The pixel may lie outside the image.
    pub fn project(&self, world: &Point3<f64>) -> Option<(Vector2<f64>, f64)> {
        let p = self.world_from_eo.inverse_transform_point(world);
        let pixel = self.camera.project(&p.coords).ok()?;
        Some((pixel, p.z))
    }

    /// Whether a pixel (centres at integers) lies inside the image, `margin_px` in
    /// from its border.
    pub fn inside(&self, pixel: &Vector2<f64>, margin_px: f64) -> bool {
        let (w, h) = (f64::from(self.camera.width), f64::from(self.camera.height));
        pixel.x >= margin_px - 0.5
            && pixel.y >= margin_px - 0.5
            && pixel.x <= w - 0.5 - margin_px
            && pixel.y <= h - 0.5 - margin_px
    }
}
