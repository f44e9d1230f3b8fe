//! Temporal smoothness: a fly-through between consecutive acquisition poses, drawn by
//! each mode and by the simulator (the truth). A mode's flicker is how much more each
//! pixel changes between consecutive frames than the truth changes there: the mean
//! absolute change (grey levels, RGB) over the pixels every mode covers in both
//! frames, minus the truth's over the same pixels. Smooth weights are Debevec 1998's
//! claim for view maps; painter and best switch scans at once.

use anyhow::{Context, Result};
use texel::{PinholeCamera, Pose};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{GpuContext, Renderer};
use texel_viewer::vdtm::{LiveVdtm, VdtmSettings};

use super::{BACKGROUND, BACKGROUND_RGB, Config};

/// Acquisition intervals the fly-through crosses.
const INTERVALS: usize = 4;
const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

/// One mode's flicker.
#[derive(Debug, Clone)]
pub struct FlickerRow {
    pub mode: String,
    /// Mean absolute change between consecutive frames, grey levels, and the
    /// truth's over the same pixels.
    pub change: f64,
    pub truth_change: f64,
}

impl FlickerRow {
    /// The change beyond the truth's: what the mode adds.
    pub fn flicker(&self) -> f64 {
        self.change - self.truth_change
    }
}

/// `from` moved a share `t` towards `to`: translations mixed, rotations slerped.
fn between(from: &Pose, to: &Pose, t: f64) -> Pose {
    let p = from.translation.vector * (1.0 - t) + to.translation.vector * t;
    let r = from
        .rotation
        .try_slerp(&to.rotation, t, 1e-9)
        .unwrap_or(from.rotation);
    Pose::from_parts(nalgebra::Translation3::from(p), r)
}

/// `frames` poses evenly along `INTERVALS` acquisition intervals from a third of the
/// way into the walk.
fn fly_through(sim: &sims::Simulator, frames: usize) -> Vec<Pose> {
    let n = sim.frame_count();
    if n < 2 || frames < 2 {
        return Vec::new();
    }
    let intervals = INTERVALS.min(n - 1);
    let first = (n / 3).min(n - 1 - intervals);
    (0..frames)
        .map(|f| {
            let s = f as f64 * intervals as f64 / (frames - 1) as f64;
            let i = (s.floor() as usize).min(intervals - 1);
            between(
                &sim.true_pose(first + i),
                &sim.true_pose(first + i + 1),
                s - i as f64,
            )
        })
        .collect()
}

/// A mode of the fly-through: a compositing mode or VDTM with switches.
enum FlyMode {
    Scans(Mode),
    Vdtm(VdtmSettings),
}

impl FlyMode {
    fn name(&self) -> String {
        match self {
            FlyMode::Scans(m) => m.name().to_string(),
            FlyMode::Vdtm(v) => v.label(),
        }
    }
}

fn rgb_of(image: &image::RgbaImage) -> Vec<u8> {
    image.pixels().flat_map(|p| [p[0], p[1], p[2]]).collect()
}

/// Renders the fly-through in every mode and the truth, and scores each mode.
pub fn measure(
    gpu: &GpuContext,
    sim: &sims::Simulator,
    renderer: &mut Renderer,
    vdtm: &mut LiveVdtm,
    fov_deg: f64,
    frames: usize,
) -> Result<Vec<FlickerRow>> {
    let poses = fly_through(sim, frames);
    let modes = [
        FlyMode::Scans(Mode::Painter),
        FlyMode::Scans(Mode::Best),
        FlyMode::Scans(Mode::Blended),
        FlyMode::Vdtm(VdtmSettings::default()),
        FlyMode::Vdtm(VdtmSettings::improved()),
    ];
    let intrinsics = PinholeCamera::from_vertical_fov(WIDTH, HEIGHT, fov_deg)?;
    let truth: Vec<Vec<u8>> = poses
        .iter()
        .map(|p| sim.scene().render_view(p, &intrinsics).rgb)
        .collect();
    let saved = vdtm.settings;
    let mut images: Vec<Vec<Vec<u8>>> = Vec::with_capacity(modes.len());
    for mode in &modes {
        let mut frames_rgb = Vec::with_capacity(poses.len());
        for pose in &poses {
            let camera = VirtualCamera::new(*pose, fov_deg, WIDTH, HEIGHT)?;
            let image = match mode {
                FlyMode::Scans(m) => {
                    renderer
                        .render_to_image(&camera, &Config::base(*m).settings())?
                        .0
                }
                FlyMode::Vdtm(v) => {
                    vdtm.settings = *v;
                    vdtm.render_to_image(gpu, &camera, BACKGROUND)?
                        .context("VDTM: nothing prepared")?
                }
            };
            frames_rgb.push(rgb_of(&image));
        }
        images.push(frames_rgb);
    }
    vdtm.settings = saved;

    let pixels = (WIDTH * HEIGHT) as usize;
    let mut sums = vec![0.0f64; modes.len()];
    let mut truth_sum = 0.0f64;
    let mut counted = 0usize;
    for t in 1..poses.len() {
        // Pixels every mode covers in both frames.
        let covered = |i: usize| {
            images.iter().all(|m| {
                [t - 1, t].iter().all(|&f| {
                    m.get(f)
                        .and_then(|rgb| rgb.get(3 * i..3 * i + 3))
                        .is_some_and(|p| p != BACKGROUND_RGB)
                })
            })
        };
        for i in (0..pixels).filter(|&i| covered(i)) {
            let change = |rgb: &[Vec<u8>]| -> f64 {
                (0..3)
                    .map(|k| f64::from(rgb[t][3 * i + k].abs_diff(rgb[t - 1][3 * i + k])))
                    .sum::<f64>()
                    / 3.0
            };
            for (sum, m) in sums.iter_mut().zip(&images) {
                *sum += change(m);
            }
            truth_sum += change(&truth);
            counted += 1;
        }
    }
    let n = counted.max(1) as f64;
    Ok(modes
        .iter()
        .zip(sums)
        .map(|(m, sum)| FlickerRow {
            mode: m.name(),
            change: sum / n,
            truth_change: truth_sum / n,
        })
        .collect())
}
