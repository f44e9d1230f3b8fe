//! The adaptive benchmark's reading against the ground truth: at the orbit poses where
//! interactive frames are scored, the PSNR of the interactive frame and of the
//! full-quality frame (both as the window shows them) against the simulator's clean
//! image of the scene (`sims::Scene::render_view`, no sensor effects, through the
//! virtual camera's pinhole: the truth of `texel-bench tradeoffs rendering`), over
//! the pixels all three cover, and their difference in dB.
//!
//! Only captures of a simulated scene have a truth: a capture named `NAME` is scored
//! against `configs/scenes/NAME.toml`; other models (the synthetic `corridor-100`)
//! are reported as having none.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use rayon::prelude::*;
use texel::PinholeCamera;
use texel_viewer::camera::VirtualCamera;

use crate::tradeoffs::rendering::metrics::psnr_db;

/// Uncovered pixels of the renders that find the coverage get this colour (the
/// rendering tradeoff's convention: the scenes never produce pure magenta).
pub(super) const MASK_BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];
const MASK_BACKGROUND_RGB: [u8; 3] = [255, 0, 255];

/// The scene file a capture named `name` was simulated from, if there is one:
/// `configs/scenes/NAME.toml` under the working directory, else under the workspace
/// this benchmark was built in.
pub(super) fn scene_file(name: &str) -> Option<PathBuf> {
    if name.is_empty() || name.contains(['/', '\\', '.']) {
        return None;
    }
    let rel = Path::new("configs")
        .join("scenes")
        .join(format!("{name}.toml"));
    let built_in = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(&rel);
    [rel, built_in].into_iter().find(|p| p.is_file())
}

/// One orbit pose's ground truth and full-quality frame.
pub(super) struct PoseTruth {
    /// The simulator's image, RGB.
    truth: Vec<u8>,
    /// Pixels whose ray meets the scene's geometry.
    geometry: Vec<bool>,
    /// The full-quality frame as shown, RGB.
    full: Vec<u8>,
    /// Pixels the full-quality frame draws.
    full_covered: Vec<bool>,
}

impl PoseTruth {
    /// The truth seen by `camera` and the full frame shown there (`full`, and
    /// `full_masked` rendered over the mask background).
    pub(super) fn new(
        scene: &sims::Scene,
        camera: &VirtualCamera,
        full: &image::RgbaImage,
        full_masked: &image::RgbaImage,
    ) -> anyhow::Result<Self> {
        let fov = camera.fov_y_rad.to_degrees();
        let pinhole = PinholeCamera::from_vertical_fov(camera.width, camera.height, fov)
            .context("the truth's pinhole")?;
        let truth = scene.render_view(&camera.world_from_eo, &pinhole).rgb;
        let n = (camera.width * camera.height) as usize;
        anyhow::ensure!(
            truth.len() == 3 * n && full.len() == 4 * n && full_masked.len() == 4 * n,
            "ground truth and frames of different sizes"
        );
        Ok(Self {
            truth,
            geometry: truth_geometry(scene, camera),
            full: rgb(full),
            full_covered: covered(full_masked),
        })
    }
}

/// Per pixel whether the simulator's scene has geometry along the camera's ray (its
/// ray caster, `sims::Scene::cast_ray`, as `tradeoffs lod-view` masks its truth).
fn truth_geometry(scene: &sims::Scene, camera: &VirtualCamera) -> Vec<bool> {
    let origin = nalgebra::Point3::from(camera.world_from_eo.translation.vector);
    (0..camera.height)
        .into_par_iter()
        .flat_map_iter(|y| {
            (0..camera.width).map(move |x| {
                let dir = camera.world_from_eo.rotation * camera.pixel_ray_view(x, y);
                scene.cast_ray(origin, dir).is_some()
            })
        })
        .collect()
}

fn rgb(image: &image::RgbaImage) -> Vec<u8> {
    image.pixels().flat_map(|p| [p[0], p[1], p[2]]).collect()
}

/// Pixels a frame rendered over [`MASK_BACKGROUND`] draws (an upscaled pixel counts
/// when any of its samples was drawn).
pub(super) fn covered(masked: &image::RgbaImage) -> Vec<bool> {
    masked
        .pixels()
        .map(|p| [p[0], p[1], p[2]] != MASK_BACKGROUND_RGB)
        .collect()
}

/// Mean squared error over RGB (0..255) of `a` against `b` on `mask`; `None` when the
/// mask is empty.
fn masked_mse(a: &[u8], b: &[u8], mask: &[bool]) -> Option<f64> {
    let (mut se, mut n) = (0.0f64, 0usize);
    for ((p, q), m) in a.chunks_exact(3).zip(b.chunks_exact(3)).zip(mask) {
        if !m {
            continue;
        }
        for k in 0..3 {
            let d = f64::from(p[k]) - f64::from(q[k]);
            se += d * d;
        }
        n += 1;
    }
    (n > 0).then(|| se / (3 * n) as f64)
}

/// Sums over the poses of one frame kind against the truth.
#[derive(Debug, Default, Clone)]
pub(super) struct TruthScore {
    /// Pixels over all poses.
    pub pixels: usize,
    /// Pixels the frame draws, the full frame draws, the truth has geometry at.
    pub covered: usize,
    pub full_covered: usize,
    pub truth_covered: usize,
    /// Pixels scored (all three), over all poses.
    pub scored: usize,
    /// Poses with any pixel scored; sums of their PSNRs (capped at 99 dB).
    pub poses: usize,
    pub psnr_sum: f64,
    pub full_psnr_sum: f64,
}

impl TruthScore {
    /// Scores one pose's frame (`image` as shown, `covered` its drawn pixels) and the
    /// full frame against the truth over the pixels all three cover.
    pub(super) fn add(&mut self, image: &image::RgbaImage, covered: &[bool], pose: &PoseTruth) {
        self.add_rgb(&rgb(image), covered, pose);
    }

    /// The full-quality frame itself against the truth (over the pixels it and the
    /// truth cover).
    pub(super) fn add_full(&mut self, pose: &PoseTruth) {
        self.add_rgb(&pose.full, &pose.full_covered, pose);
    }

    fn add_rgb(&mut self, image: &[u8], covered: &[bool], pose: &PoseTruth) {
        let mask: Vec<bool> = covered
            .iter()
            .zip(&pose.full_covered)
            .zip(&pose.geometry)
            .map(|((a, b), c)| *a && *b && *c)
            .collect();
        self.pixels += mask.len();
        self.covered += covered.iter().filter(|c| **c).count();
        self.full_covered += pose.full_covered.iter().filter(|c| **c).count();
        self.truth_covered += pose.geometry.iter().filter(|c| **c).count();
        let scored = mask.iter().filter(|c| **c).count();
        let (Some(mse), Some(full_mse)) = (
            masked_mse(image, &pose.truth, &mask),
            masked_mse(&pose.full, &pose.truth, &mask),
        ) else {
            return;
        };
        self.scored += scored;
        self.poses += 1;
        self.psnr_sum += psnr_db(mse).min(99.0);
        self.full_psnr_sum += psnr_db(full_mse).min(99.0);
    }

    /// Mean PSNR over the scored poses, dB (NaN for none).
    pub(super) fn psnr_db(&self) -> f64 {
        self.mean(self.psnr_sum)
    }

    pub(super) fn full_psnr_db(&self) -> f64 {
        self.mean(self.full_psnr_sum)
    }

    fn mean(&self, sum: f64) -> f64 {
        if self.poses == 0 {
            f64::NAN
        } else {
            sum / self.poses as f64
        }
    }
}

/// The header of the table against the truth.
pub(super) fn print_header(name: &str, scene: &Path, poses: usize, w: u32, h: u32) {
    println!(
        "{name} against the ground truth ({}: sims::Scene::render_view, no sensor effects), \
         {poses} orbit poses of {w}x{h}; scored where the frame, the full frame and the truth's \
         geometry all are; PSNR is the mean over poses (99 dB = identical)",
        // As the workspace names it, not where this machine keeps it.
        Path::new("configs/scenes")
            .join(scene.file_name().unwrap_or_default())
            .display()
    );
    println!(
        "{:>26} {:>7} {:>7} {:>7} {:>10} {:>9} {:>9} {:>9}",
        "frame vs ground truth",
        "drawn%",
        "full%",
        "truth%",
        "scored px",
        "PSNR dB",
        "full dB",
        "diff dB"
    );
}

/// One row: the frame's coverage, the truth's, the pixels scored (summed over the
/// poses), the frame's and the full frame's PSNR and their difference.
pub(super) fn print_row(label: &str, s: &TruthScore, diff: bool) {
    let share = |n: usize| 100.0 * n as f64 / s.pixels.max(1) as f64;
    let db = |v: f64| {
        if v.is_finite() {
            format!("{v:.2}")
        } else {
            "-".into()
        }
    };
    let (p, f) = (s.psnr_db(), s.full_psnr_db());
    println!(
        "{label:>26} {:>7.1} {:>7.1} {:>7.1} {:>10} {:>9} {:>9} {:>9}",
        share(s.covered),
        share(s.full_covered),
        share(s.truth_covered),
        s.scored,
        db(p),
        db(f),
        if diff && p.is_finite() && f.is_finite() {
            format!("{:+.2}", p - f)
        } else {
            "-".into()
        }
    );
}

/// Times the truth of a subject's poses (the CPU ray caster), for the log.
pub(super) fn timed<T>(what: &str, f: impl FnOnce() -> anyhow::Result<T>) -> anyhow::Result<T> {
    let start = Instant::now();
    let out = f()?;
    eprintln!("{what} in {:.1} s", start.elapsed().as_secs_f64());
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn pose(
        truth: [u8; 3],
        full: [u8; 3],
        geometry: Vec<bool>,
        full_covered: Vec<bool>,
    ) -> PoseTruth {
        let n = geometry.len();
        PoseTruth {
            truth: truth.repeat(n),
            geometry,
            full: full.repeat(n),
            full_covered,
        }
    }

    #[test]
    fn scores_only_pixels_all_three_cover_and_caps_identical_images() {
        let p = pose(
            [100, 100, 100],
            [100, 100, 100],
            vec![true, true, true, false],
            vec![true, true, false, true],
        );
        let img = image::RgbaImage::from_pixel(2, 2, image::Rgba([110, 100, 100, 255]));
        let mut s = TruthScore::default();
        s.add(&img, &[true, false, true, true], &p);
        // Only pixel 0 is drawn by all three.
        assert_eq!((s.pixels, s.scored, s.poses), (4, 1, 1));
        assert_eq!(s.full_psnr_db(), 99.0);
        let mse: f64 = 100.0 / 3.0;
        assert!((s.psnr_db() - 10.0 * (255.0f64 * 255.0 / mse).log10()).abs() < 1e-9);
        // Nothing in common: no pose scored, no NaN printed as a number.
        let mut none = TruthScore::default();
        none.add(&img, &[false; 4], &p);
        assert_eq!((none.scored, none.poses), (0, 0));
        assert!(none.psnr_db().is_nan());
    }

    #[test]
    fn only_scene_names_find_scene_files() {
        assert!(scene_file("lab").is_some());
        assert!(scene_file("corridor-100").is_none());
        assert!(scene_file("../lab").is_none());
    }
}
