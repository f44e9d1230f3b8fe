//! `texel-bench viewer --adaptive`: the window's frame while the camera orbits, before
//! (every frame at full quality) and after adaptive quality (the interactive frame
//! sized by the controller to the budget, upscaled), in one run per model; the time
//! from release to the full-quality frame; and the PSNR of the interactive frames
//! against the full-quality frame at the same poses, for each cheap mode. For a
//! capture of a simulated scene, also both frames against the scene's ground truth at
//! those poses (`adaptive_truth.rs`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use texel_viewer::adaptive::{AdaptiveRenderer, DEFAULT_SETTLE, Quality, Refinement};
use texel_viewer::app::CameraControls;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{
    GpuContext, IMAGE_FORMAT, RenderSettings, RenderTarget, Renderer, read_rgba_texture,
};
use texel_viewer::scenes;

use super::BenchArgs;

mod truth;

use truth::{PoseTruth, TruthScore};

/// Radians of orbit per pixel of drag (the window's).
const ORBIT_RAD_PER_PX: f64 = 0.005;
/// The orbit swings this far either side of the start, once per orbit.
const ORBIT_HALF_DEG: f64 = 20.0;
/// Times release to full quality is measured per model.
const RELEASES: usize = 5;
/// Poses along the orbit where interactive frames are scored against full ones.
const PSNR_POSES: usize = 4;

/// A model and where its orbit starts.
pub(super) struct Subject {
    pub name: String,
    pub model: texel::model::Model,
    start: CameraControls,
    fov_deg: f64,
    /// The scene file of the simulated scene the model was captured in, if any: its
    /// ground truth.
    scene: Option<PathBuf>,
}

/// The window's target: a texture of the window's size that a frame is shown in.
struct Window {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    width: u32,
    height: u32,
}

impl Window {
    fn new(gpu: &GpuContext, width: u32, height: u32) -> Self {
        let texture = texel_viewer::gpu::image_texture(
            &gpu.device,
            "bench window",
            width,
            height,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        Self {
            texture,
            view,
            width,
            height,
        }
    }

    fn target(&self) -> RenderTarget<'_> {
        RenderTarget {
            view: &self.view,
            format: IMAGE_FORMAT,
            width: self.width,
            height: self.height,
        }
    }
}

pub fn run(gpu: &GpuContext, args: &BenchArgs) -> anyhow::Result<()> {
    let (w, h) = (args.width, args.height);
    println!(
        "adaptive quality: {w}x{h}, blended k = 4 at full quality, budget {} ms, orbit {:.1} s \
         (±{ORBIT_HALF_DEG}° about the pivot); frame = render + show in the window's target + \
         wait for the GPU (no overlay)",
        args.interactive_ms, args.orbit_s
    );
    let mut subjects = Vec::new();
    for spec in &args.capture {
        subjects.push(load(spec)?);
    }
    subjects.push(corridor_subject());
    let full = RenderSettings::with_mode(Mode::Blended);
    let window = Window::new(gpu, w, h);
    for s in &subjects {
        let mut renderer = Renderer::new(gpu);
        renderer.sync_model(&s.model)?;
        println!(
            "{}: {} scans, {} drawn at the start",
            s.name,
            s.model.len(),
            renderer
                .cull(&camera_at(s, 0.0, w, h, args.orbit_s)?, &full)
                .1
                .drawn
        );
        println!(
            "{:>26} {:>7} {:>9} {:>9} {:>8} {:>8} {:>10} {:>10}",
            "frames while orbiting",
            "frames",
            "p50 ms",
            "p95 ms",
            "p50 x",
            "p95 x",
            "scale",
            "PSNR dB"
        );
        let before = orbit_full(gpu, &mut renderer, s, &full, &window, args)?;
        print_row("before: full quality", &before, &before, None, None);
        // The full-quality frames at the scored poses (the same for every cheap mode),
        // and with a truth, the truth there.
        let scored = full_along_orbit(gpu, &mut renderer, s, &full, &window, args)?;
        let mut truth_rows: Vec<(String, TruthScore)> = Vec::new();
        if let Some(poses) = &scored.truths {
            let mut score = TruthScore::default();
            poses.iter().for_each(|p| score.add_full(p));
            truth_rows.push(("before: full quality".into(), score));
        }
        // Each change against the one before it: the resolution alone (painter, every
        // triangle), then the coarse triangles, then blended k = 1 instead of painter.
        for (cheap, coarse) in [
            (Mode::Painter, false),
            (Mode::Painter, true),
            (Mode::Blended, true),
        ] {
            let mut adaptive = AdaptiveRenderer::new(&gpu.device, args.interactive_ms);
            adaptive.cheap = cheap;
            adaptive.coarse = coarse;
            let after = orbit_adaptive(gpu, &mut renderer, s, &full, &window, &mut adaptive, args)?;
            let (psnr, against_truth) = psnr_along_orbit(
                gpu,
                &mut renderer,
                s,
                &full,
                &window,
                &mut adaptive,
                &scored,
                args,
            )?;
            let label = format!(
                "after: {} k=1{}",
                cheap.name(),
                if coarse { ", coarse" } else { "" }
            );
            if let Some(score) = against_truth {
                truth_rows.push((label.clone(), score));
            }
            print_row(
                &label,
                &after,
                &before,
                Some(adaptive.controller.scale()),
                Some(psnr),
            );
            if cheap == Mode::Painter && coarse {
                // A single release is one frame: on a shared machine it varies by a
                // quarter between runs, so it is repeated.
                let mut releases = Vec::new();
                for _ in 0..RELEASES {
                    releases.push(release_to_full(
                        gpu,
                        &mut renderer,
                        s,
                        &full,
                        &window,
                        &mut adaptive,
                        args,
                    )?);
                }
                let settle_ms = DEFAULT_SETTLE.as_secs_f64() * 1e3;
                let of = |f: fn(&Release) -> f64| releases.iter().map(f).collect::<Vec<f64>>();
                let stepped = of(|r| r.stepped_ms);
                let longest = of(|r| r.longest_step_ms);
                let whole = of(|r| r.whole_ms);
                let max = |v: &[f64]| v.iter().copied().fold(0.0f64, f64::max);
                println!(
                    "{:>26} settle {settle_ms:.0} ms + full frame in {} steps = p50 {:.0} ms, \
                     max {:.0} ms of {RELEASES} releases (target <= 1500); longest step {:.0} ms \
                     (input waits at most this); with the frame in one submission: p50 {:.0} ms, \
                     max {:.0} ms",
                    "release -> full quality:",
                    releases.first().map_or(0, |r| r.steps),
                    percentile(&stepped, 0.5),
                    max(&stepped),
                    max(&longest),
                    percentile(&whole, 0.5),
                    max(&whole),
                );
            }
        }
        match &s.scene {
            Some(scene) => {
                truth::print_header(&s.name, scene, PSNR_POSES, w, h);
                for (i, (label, score)) in truth_rows.iter().enumerate() {
                    truth::print_row(label, score, i > 0);
                }
            }
            None => println!(
                "{}: no ground truth (not a capture of a simulated scene: no \
                 configs/scenes/{}.toml); PSNR against the full-quality frame only",
                s.name, s.name
            ),
        }
    }
    Ok(())
}

fn print_row(label: &str, times: &[f64], base: &[f64], scale: Option<f64>, psnr: Option<f64>) {
    let (p50, p95) = (percentile(times, 0.5), percentile(times, 0.95));
    let (b50, b95) = (percentile(base, 0.5), percentile(base, 0.95));
    println!(
        "{label:>26} {:>7} {p50:>9.1} {p95:>9.1} {:>8.3} {:>8.3} {:>10} {:>10}",
        times.len(),
        p50 / b50.max(1e-9),
        p95 / b95.max(1e-9),
        scale.map_or("1.00".into(), |s| format!("{s:.2}")),
        psnr.map_or("-".into(), |p| format!("{p:.2}")),
    );
}

/// The synthetic corridor of 100 scans, seen from outside along it.
pub(super) fn corridor_subject() -> Subject {
    let sensor = scenes::sensor(64, 48, 320, 240);
    Subject {
        name: "corridor-100".into(),
        model: scenes::corridor(&sensor, 100),
        start: CameraControls::new(scenes::look_at([4.5, 0.0, -1.0], [4.5, 0.0, 5.05]), 6.05),
        fov_deg: 50.0,
        scene: None,
    }
}

/// `NAME=PATH`: a capture, loaded and fused; the orbit starts at its middle scan's
/// acquisition pose, pivoting at that scan's median range.
pub(super) fn load(spec: &str) -> anyhow::Result<Subject> {
    let (name, path) = spec
        .split_once('=')
        .with_context(|| format!("--capture {spec}: expected NAME=PATH"))?;
    let path = PathBuf::from(path);
    let loaded = texel_viewer::capture_load::load_capture(&path)
        .with_context(|| format!("loading {}", path.display()))?;
    let model = loaded.model;
    let scans: Vec<_> = model.resident().collect();
    let (listed, scan) = scans
        .get(scans.len() / 2)
        .copied()
        .with_context(|| format!("{}: no scan placed", path.display()))?;
    let mut ranges: Vec<f32> = scan
        .vertices
        .iter()
        .map(|v| v[2])
        .filter(|z| z.is_finite() && *z > 0.0)
        .collect();
    ranges.sort_by(f32::total_cmp);
    let pivot = f64::from(ranges.get(ranges.len() / 2).copied().unwrap_or(3.0));
    let start = CameraControls::new(listed.world_from_scan, pivot);
    let fov_deg = VirtualCamera::fov_y_deg_of(&loaded.eo_camera);
    Ok(Subject {
        name: name.to_string(),
        model,
        start,
        fov_deg,
        scene: truth::scene_file(name),
    })
}

/// The camera `t` seconds into the orbit.
pub(super) fn camera_at(
    s: &Subject,
    t: f64,
    w: u32,
    h: u32,
    orbit_s: f64,
) -> anyhow::Result<VirtualCamera> {
    let mut c = s.start;
    let phase = std::f64::consts::TAU * t / orbit_s.max(1e-3);
    c.orbit(
        ORBIT_HALF_DEG.to_radians() * phase.sin() / ORBIT_RAD_PER_PX,
        0.0,
    );
    Ok(VirtualCamera::new(c.world_from_eo, s.fov_deg, w, h)?)
}

/// Before: every frame of the orbit at full quality straight into the window (as the
/// window drew before), timed to the GPU's end. At least 3 frames.
fn orbit_full(
    gpu: &GpuContext,
    renderer: &mut Renderer,
    s: &Subject,
    settings: &RenderSettings,
    window: &Window,
    args: &BenchArgs,
) -> anyhow::Result<Vec<f64>> {
    let mut times = Vec::new();
    let start = Instant::now();
    while start.elapsed().as_secs_f64() < args.orbit_s || times.len() < 3 {
        let t0 = Instant::now();
        let camera = camera_at(
            s,
            start.elapsed().as_secs_f64(),
            window.width,
            window.height,
            args.orbit_s,
        )?;
        renderer.render(&camera, settings, &window.target())?;
        gpu.wait_idle()?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    Ok(times)
}

/// After: the window's interactive frames along the orbit (the controller steering the
/// scale by each frame's time, as the window does). The controller's first second is
/// its warm-up and is timed too.
fn orbit_adaptive(
    gpu: &GpuContext,
    renderer: &mut Renderer,
    s: &Subject,
    settings: &RenderSettings,
    window: &Window,
    adaptive: &mut AdaptiveRenderer,
    args: &BenchArgs,
) -> anyhow::Result<Vec<f64>> {
    let mut times = Vec::new();
    let start = Instant::now();
    while start.elapsed().as_secs_f64() < args.orbit_s || times.len() < 3 {
        let t0 = Instant::now();
        let camera = camera_at(
            s,
            start.elapsed().as_secs_f64(),
            window.width,
            window.height,
            args.orbit_s,
        )?;
        frame(
            gpu,
            renderer,
            &camera,
            settings,
            window,
            adaptive,
            Quality::Interactive,
        )?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        adaptive.controller.observe(ms);
        times.push(ms);
    }
    Ok(times)
}

/// One window frame: render at `quality`, show it in the window, wait for the GPU.
fn frame(
    gpu: &GpuContext,
    renderer: &mut Renderer,
    camera: &VirtualCamera,
    settings: &RenderSettings,
    window: &Window,
    adaptive: &mut AdaptiveRenderer,
    quality: Quality,
) -> anyhow::Result<()> {
    adaptive.render(renderer, camera, settings, quality)?;
    show(gpu, window, adaptive)
}

/// From the release of the mouse to the full-quality frame shown, as the window does
/// it: the settle time it waits, then the full frame refined a step per turn of the
/// event loop (each step submitted and the GPU waited for, so input would be read
/// between steps; the last one shown). Also the frame in one submission (`render`), which is what input
/// waited behind before frames were drawn in steps.
struct Release {
    /// Settle plus the stepped full frame, ms.
    stepped_ms: f64,
    /// The longest step (show included): the most input waits, ms.
    longest_step_ms: f64,
    steps: usize,
    /// Settle plus the full frame in one submission, ms.
    whole_ms: f64,
}

fn release_to_full(
    gpu: &GpuContext,
    renderer: &mut Renderer,
    s: &Subject,
    settings: &RenderSettings,
    window: &Window,
    adaptive: &mut AdaptiveRenderer,
    args: &BenchArgs,
) -> anyhow::Result<Release> {
    let camera = camera_at(s, args.orbit_s, window.width, window.height, args.orbit_s)?;
    let settle_ms = DEFAULT_SETTLE.as_secs_f64() * 1e3;
    let t0 = Instant::now();
    frame(
        gpu,
        renderer,
        &camera,
        settings,
        window,
        adaptive,
        Quality::Full,
    )?;
    let whole_ms = t0.elapsed().as_secs_f64() * 1e3 + settle_ms;
    // The window's interactive frame is on screen when the refinement begins.
    frame(
        gpu,
        renderer,
        &camera,
        settings,
        window,
        adaptive,
        Quality::Interactive,
    )?;
    let t0 = Instant::now();
    let mut longest_step_ms = 0.0f64;
    let mut steps = 0;
    loop {
        let step_start = Instant::now();
        let done = matches!(
            adaptive.refine(renderer, &camera, settings)?,
            Refinement::Done(_)
        );
        steps += 1;
        if done {
            // The last step is shown; the ones before change nothing on screen.
            show(gpu, window, adaptive)?;
        } else {
            gpu.wait_idle()?;
        }
        longest_step_ms = longest_step_ms.max(step_start.elapsed().as_secs_f64() * 1e3);
        if done {
            break;
        }
    }
    Ok(Release {
        stepped_ms: t0.elapsed().as_secs_f64() * 1e3 + settle_ms,
        longest_step_ms,
        steps,
        whole_ms,
    })
}

/// Shows the last picture in the window's target and waits for the GPU.
fn show(gpu: &GpuContext, window: &Window, adaptive: &mut AdaptiveRenderer) -> anyhow::Result<()> {
    let mut encoder = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("show"),
        });
    adaptive.present(&mut encoder, &window.target());
    texel_viewer::gpu::submit(&gpu.queue, Some(encoder.finish()));
    gpu.wait_idle()?;
    Ok(())
}

/// The camera at the `i`-th of the poses where frames are scored.
fn scored_camera(
    s: &Subject,
    i: usize,
    window: &Window,
    orbit_s: f64,
) -> anyhow::Result<VirtualCamera> {
    let t = orbit_s * (i as f64 + 0.5) / PSNR_POSES as f64;
    camera_at(s, t, window.width, window.height, orbit_s)
}

/// `settings` with uncovered pixels in the colour that finds them.
fn masked(settings: &RenderSettings) -> RenderSettings {
    let mut m = settings.clone();
    m.composite.background = truth::MASK_BACKGROUND;
    m
}

/// The full-quality frames at the scored poses, as shown in the window; with a
/// scene's truth, the truth there and the full frames' coverage.
struct Scored {
    fulls: Vec<image::RgbaImage>,
    truths: Option<Vec<PoseTruth>>,
}

fn full_along_orbit(
    gpu: &GpuContext,
    renderer: &mut Renderer,
    s: &Subject,
    settings: &RenderSettings,
    window: &Window,
    args: &BenchArgs,
) -> anyhow::Result<Scored> {
    let scene = match &s.scene {
        Some(path) => {
            Some(sims::Scene::load(path).with_context(|| format!("loading {}", path.display()))?)
        }
        None => None,
    };
    let mut adaptive = AdaptiveRenderer::new(&gpu.device, args.interactive_ms);
    let mut fulls = Vec::with_capacity(PSNR_POSES);
    let mut truths = Vec::with_capacity(PSNR_POSES);
    for i in 0..PSNR_POSES {
        let camera = scored_camera(s, i, window, args.orbit_s)?;
        let mut shown = |settings: &RenderSettings| -> anyhow::Result<image::RgbaImage> {
            frame(
                gpu,
                renderer,
                &camera,
                settings,
                window,
                &mut adaptive,
                Quality::Full,
            )?;
            Ok(read_rgba_texture(&gpu.device, &gpu.queue, &window.texture)?)
        };
        let full = shown(settings)?;
        if let Some(scene) = &scene {
            let full_masked = shown(&masked(settings))?;
            truths.push(truth::timed(
                &format!(
                    "{}: ground truth of pose {i} ({}x{})",
                    s.name, window.width, window.height
                ),
                || PoseTruth::new(scene, &camera, &full, &full_masked),
            )?);
        }
        fulls.push(full);
    }
    Ok(Scored {
        fulls,
        truths: scene.map(|_| truths),
    })
}

/// The mean PSNR of the interactive frames (at the scale the controller settled on,
/// shown in the window) against the full-quality frames at the same poses, over
/// poses spread along the orbit; with a truth, both against it.
#[allow(clippy::too_many_arguments)]
fn psnr_along_orbit(
    gpu: &GpuContext,
    renderer: &mut Renderer,
    s: &Subject,
    settings: &RenderSettings,
    window: &Window,
    adaptive: &mut AdaptiveRenderer,
    scored: &Scored,
    args: &BenchArgs,
) -> anyhow::Result<(f64, Option<TruthScore>)> {
    let mut sum = 0.0;
    let mut against_truth = scored.truths.as_ref().map(|_| TruthScore::default());
    for (i, full) in scored.fulls.iter().enumerate() {
        let camera = scored_camera(s, i, window, args.orbit_s)?;
        let mut shown = |settings: &RenderSettings| -> anyhow::Result<image::RgbaImage> {
            frame(
                gpu,
                renderer,
                &camera,
                settings,
                window,
                adaptive,
                Quality::Interactive,
            )?;
            Ok(read_rgba_texture(&gpu.device, &gpu.queue, &window.texture)?)
        };
        let cheap = shown(settings)?;
        sum += psnr(&cheap, full);
        if let (Some(score), Some(truths)) = (against_truth.as_mut(), scored.truths.as_ref()) {
            let cheap_masked = shown(&masked(settings))?;
            score.add(&cheap, &truth::covered(&cheap_masked), &truths[i]);
        }
    }
    Ok((sum / scored.fulls.len().max(1) as f64, against_truth))
}

/// PSNR of `a` against `b` over RGB, dB; identical images give 99 dB (no infinity).
pub fn psnr(a: &image::RgbaImage, b: &image::RgbaImage) -> f64 {
    let mut se = 0.0;
    let mut n = 0usize;
    for (p, q) in a.pixels().zip(b.pixels()) {
        for k in 0..3 {
            let d = f64::from(p[k]) - f64::from(q[k]);
            se += d * d;
            n += 1;
        }
    }
    let mse = se / n.max(1) as f64;
    if mse <= 0.0 {
        return 99.0;
    }
    (10.0 * (255.0 * 255.0 / mse).log10()).min(99.0)
}

/// The `q` quantile (nearest rank) of `v`; 0 for none.
pub(super) fn percentile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    if s.is_empty() {
        return 0.0;
    }
    let i = ((q * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1;
    s[i]
}

#[cfg(test)]
mod tests {
    #[test]
    fn psnr_is_finite_and_falls_with_error() {
        let a = image::RgbaImage::from_pixel(4, 4, image::Rgba([10, 20, 30, 255]));
        let mut b = a.clone();
        assert_eq!(super::psnr(&a, &b), 99.0);
        b.put_pixel(0, 0, image::Rgba([40, 20, 30, 255]));
        let one = super::psnr(&a, &b);
        b.put_pixel(1, 0, image::Rgba([40, 20, 30, 255]));
        assert!(one.is_finite() && super::psnr(&a, &b) < one);
    }

    #[test]
    fn percentiles_take_the_nearest_rank() {
        let v = [5.0, 1.0, 3.0, 2.0, 4.0];
        assert_eq!(super::percentile(&v, 0.5), 3.0);
        assert_eq!(super::percentile(&v, 0.95), 5.0);
        assert_eq!(super::percentile(&[], 0.5), 0.0);
    }
}
