//! `texel-bench viewer --full-frame`: what the window's full-quality frame costs, one
//! way of drawing it against another in one interleaved run (the machine is shared
//! and noisy: every round draws each variant once, at the same poses), where the time
//! goes phase by phase, and whether each variant's image is the baseline's.

use std::time::Instant;

use texel_viewer::composite::Mode;
use texel_viewer::gpu::{
    GpuContext, IMAGE_FORMAT, RenderSettings, RenderTarget, Renderer, Strategy, read_rgba_texture,
};

use super::BenchArgs;
use super::adaptive::{camera_at, corridor_subject, load, percentile};

/// Poses along the orbit where each variant is drawn.
const POSES: usize = 4;

/// One way of drawing the full-quality frame.
struct Variant {
    label: String,
    settings: RenderSettings,
    /// `Renderer::layer_footprints`.
    footprints: bool,
    /// `Renderer::merge_marks`.
    marks: bool,
}

/// The variants, the first being the baseline the others are measured against.
fn variants() -> Vec<Variant> {
    let blended = RenderSettings::with_mode(Mode::Blended);
    let with = |label: &str, strategy: Strategy, footprints: bool, marks: bool| {
        let mut settings = blended.clone();
        settings.strategy = strategy;
        Variant {
            label: label.to_string(),
            settings,
            footprints,
            marks,
        }
    };
    let batch = |batch| Strategy::KBuffer { batch };
    vec![
        with("batch 4, whole layers", batch(4), false, false),
        with("batch 4, footprints", batch(4), true, false),
        with("footprints, marks", batch(4), true, true),
        with("batch 8, marks", batch(8), true, true),
        with("naive layers", Strategy::NaiveLayers, true, true),
    ]
}

pub fn run(gpu: &GpuContext, args: &BenchArgs) -> anyhow::Result<()> {
    let (w, h) = (args.width, args.height);
    println!(
        "full-quality frame: {w}x{h}, blended k = 4, {POSES} orbit poses, {} interleaved rounds; \
         frame = render + wait for the GPU; phases from one extra frame per pose submitted \
         phase by phase",
        args.frames
    );
    let mut subjects = Vec::new();
    for spec in &args.capture {
        subjects.push(load(spec)?);
    }
    subjects.push(corridor_subject());
    let variants = variants();
    let texture = texel_viewer::gpu::image_texture(
        &gpu.device,
        "bench target",
        w,
        h,
        wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
    );
    let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
    let target = RenderTarget {
        view: &view,
        format: IMAGE_FORMAT,
        width: w,
        height: h,
    };
    for s in &subjects {
        let mut renderer = Renderer::new(gpu);
        renderer.sync_model(&s.model)?;
        let cameras = (0..POSES)
            .map(|i| {
                camera_at(
                    s,
                    args.orbit_s * i as f64 / POSES as f64,
                    w,
                    h,
                    args.orbit_s,
                )
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let drawn: Vec<usize> = cameras
            .iter()
            .map(|c| renderer.cull(c, &variants[0].settings).1.drawn)
            .collect();
        println!(
            "{}: {} scans, drawn per pose {drawn:?}",
            s.name,
            s.model.len()
        );
        // The baseline's images, and each variant's distance from them.
        let mut images = Vec::new();
        let mut times = vec![Vec::new(); variants.len()];
        let mut phases = vec![[0.0f64; 4]; variants.len()];
        let mut memory = vec![0u64; variants.len()];
        let mut differ = vec![(0u64, 0u8); variants.len()];
        for (p, camera) in cameras.iter().enumerate() {
            for (v, variant) in variants.iter().enumerate() {
                renderer.layer_footprints = variant.footprints;
                renderer.merge_marks = variant.marks;
                // Warm-up, and the image compared.
                let stats = renderer.render(camera, &variant.settings, &target)?;
                memory[v] = memory[v].max(stats.target_memory.total());
                let image = read_rgba_texture(&gpu.device, &gpu.queue, &texture)?;
                if v == 0 {
                    images.push(image);
                } else {
                    let (n, max) = difference(&images[p], &image);
                    differ[v].0 += n;
                    differ[v].1 = differ[v].1.max(max);
                }
                renderer.profile_phases = true;
                let stats = renderer.render(camera, &variant.settings, &target)?;
                renderer.profile_phases = false;
                if let Some(ms) = stats.phase_ms {
                    for (sum, ms) in phases[v].iter_mut().zip(ms) {
                        *sum += ms / POSES as f64;
                    }
                }
            }
        }
        for _ in 0..args.frames.max(1) {
            for camera in &cameras {
                for (v, variant) in variants.iter().enumerate() {
                    renderer.layer_footprints = variant.footprints;
                    renderer.merge_marks = variant.marks;
                    let t0 = Instant::now();
                    renderer.render(camera, &variant.settings, &target)?;
                    renderer.wait_idle()?;
                    times[v].push(t0.elapsed().as_secs_f64() * 1e3);
                }
            }
        }
        println!(
            "{:>24} {:>9} {:>9} {:>7} {:>9} {:>9} {:>9} {:>9} {:>9} {:>10} {:>8}",
            "variant",
            "p50 ms",
            "p95 ms",
            "p50 x",
            "pre-pass",
            "layers",
            "merges",
            "composite",
            "MiB",
            "px differ",
            "max diff"
        );
        let base = percentile(&times[0], 0.5).max(1e-9);
        for (v, variant) in variants.iter().enumerate() {
            let p50 = percentile(&times[v], 0.5);
            let [pre, layers, merges, composite] = phases[v];
            println!(
                "{:>24} {p50:>9.1} {:>9.1} {:>7.3} {pre:>9.1} {layers:>9.1} {merges:>9.1} \
                 {composite:>9.1} {:>9.1} {:>10} {:>8}",
                variant.label,
                percentile(&times[v], 0.95),
                p50 / base,
                memory[v] as f64 / 1048576.0,
                differ[v].0,
                differ[v].1,
            );
        }
    }
    Ok(())
}

/// Pixels of `b` that differ from `a` in any channel, and the largest difference.
fn difference(a: &image::RgbaImage, b: &image::RgbaImage) -> (u64, u8) {
    let mut n = 0;
    let mut max = 0u8;
    for (pa, pb) in a.pixels().zip(b.pixels()) {
        let d =
            pa.0.iter()
                .zip(pb.0)
                .map(|(x, y)| x.abs_diff(y))
                .max()
                .unwrap_or(0);
        if d > 0 {
            n += 1;
            max = max.max(d);
        }
    }
    (n, max)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn difference_counts_pixels_and_the_largest_step() {
        let a = image::RgbaImage::from_pixel(2, 2, image::Rgba([10, 10, 10, 255]));
        let mut b = a.clone();
        b.put_pixel(1, 0, image::Rgba([10, 13, 10, 255]));
        b.put_pixel(0, 1, image::Rgba([4, 10, 10, 255]));
        assert_eq!(difference(&a, &a), (0, 0));
        assert_eq!(difference(&a, &b), (2, 6));
    }

    #[test]
    fn the_baseline_comes_first() {
        let v = variants();
        assert_eq!(v[0].settings.strategy, Strategy::KBuffer { batch: 4 });
        assert!(!v[0].footprints && v[1].footprints);
        assert!(v.len() >= 2);
    }
}
