//! The field display: this crate's renderer in the browser (wasm32), fed live by the
//! daemon over WebSocket on the page's own host and port. The page
//! (`viewer/web/index.html`) holds the canvas and plain HTML controls; the model, the
//! residency within a GPU budget, the camera controls and the renderer are the native
//! viewer's own code. Built by `scripts/build-web.sh`
//! (`cargo rustc --crate-type cdylib` for `wasm32-unknown-unknown`, then
//! `wasm-bindgen --target web`).

pub mod gestures;
pub mod load;

#[cfg(target_arch = "wasm32")]
mod input;
#[cfg(target_arch = "wasm32")]
mod link;
#[cfg(target_arch = "wasm32")]
mod page;
#[cfg(target_arch = "wasm32")]
mod run;
#[cfg(target_arch = "wasm32")]
mod wake;

/// The GPU bytes the page's scans may hold: well inside what a browser tab gets
/// (a wasm heap stops at 4 GB; the scans' CPU copies are dropped once uploaded or
/// never fetched), so a long session shows what the view needs and fetches the rest
/// by id.
pub const WEB_GPU_BUDGET_BYTES: u64 = 768 << 20;

/// The query string of a view: the deep link that reopens it (`crate::deep_link`).
pub fn view_query(
    mode: crate::composite::Mode,
    k: u32,
    world_from_eo: &texel::Pose,
    fov_deg: f64,
) -> String {
    let t = world_from_eo.translation.vector;
    let q = world_from_eo.rotation.coords;
    format!(
        "?mode={}&k={k}&fov={fov_deg:.2}&pose={:.4},{:.4},{:.4},{:.6},{:.6},{:.6},{:.6}",
        mode.name(),
        t.x,
        t.y,
        t.z,
        q.x,
        q.y,
        q.z,
        q.w
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deep_link::DeepLink;
    use crate::display_mode::DisplayMode;

    #[test]
    fn a_view_query_opens_the_same_view() {
        let pose = texel::Pose::from_parts(
            nalgebra::Translation3::new(1.25, -0.5, 3.0),
            nalgebra::UnitQuaternion::from_euler_angles(0.1, -0.4, 0.2),
        );
        let query = view_query(crate::composite::Mode::Best, 3, &pose, 48.0);
        let link = DeepLink::parse(&query).unwrap();
        assert_eq!(
            link.mode,
            Some(DisplayMode::Scans(crate::composite::Mode::Best))
        );
        assert_eq!(link.k, Some(3));
        assert_eq!(link.fov_deg, Some(48.0));
        let back = link.pose.unwrap();
        assert!((back.translation.vector - pose.translation.vector).norm() < 1e-4);
        assert!(back.rotation.angle_to(&pose.rotation) < 1e-5);
    }
}
