//! `texel-bench viewer`: frame time and GPU memory for models of 10, 30 and 100 scans
//! with about 10 in view, k-buffer against the naive layers, all measured in one run
//! (ratios are against baselines from the same run: the machine is shared and noisy);
//! then residency: the frame time with every scan resident against only those the
//! view needs, and what planning residency costs per frame for large models; with
//! `--adaptive`, the window's adaptive quality (`viewer_bench/adaptive.rs`).

mod adaptive;
mod full_frame;

use std::time::Instant;

use texel_viewer::camera::VirtualCamera;
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{
    GpuContext, IMAGE_FORMAT, RenderSettings, RenderTarget, Renderer, Strategy,
};
use texel_viewer::scenes;

#[derive(Debug, Clone, clap::Args)]
pub struct BenchArgs {
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Timed frames per configuration (after 2 warm-up frames); the median is reported.
    #[arg(long, default_value_t = 10)]
    pub frames: u32,
    /// Scans per k-buffer batch in the main table.
    #[arg(long, default_value_t = 4)]
    pub batch: u32,
    /// Measure residency only (skip the strategy tables).
    #[arg(long)]
    pub residency_only: bool,
    /// Measure adaptive quality only: frame time while orbiting before and after,
    /// release to full quality, PSNR of the interactive frames (use --width 1280
    /// --height 800 for the window's default size).
    #[arg(long, conflicts_with = "residency_only")]
    pub adaptive: bool,
    /// Measure the full-quality frame only: ways of drawing it against each other in
    /// one interleaved run, phase by phase, and their images against the baseline's
    /// (--frames rounds; use --width 1280 --height 800 for the window's default size).
    #[arg(long, conflicts_with_all = ["residency_only", "adaptive"])]
    pub full_frame: bool,
    /// With --adaptive or --full-frame: a capture to orbit in, NAME=PATH (repeatable);
    /// the synthetic 100-scan corridor is always measured.
    #[arg(long, value_name = "NAME=PATH")]
    pub capture: Vec<String>,
    /// With --adaptive: the interactive frame's budget, ms.
    #[arg(long, default_value_t = texel_viewer::adaptive::DEFAULT_INTERACTIVE_MS)]
    pub interactive_ms: f64,
    /// With --adaptive: the scripted orbit's length, seconds.
    #[arg(long, default_value_t = 5.0)]
    pub orbit_s: f64,
}

#[derive(Debug, Clone, Copy)]
pub struct Measurement {
    pub scans: u32,
    pub drawn: usize,
    pub frame_ms: f64,
    pub target_bytes: u64,
}

/// The median render time of `frames` frames after two warm-up renders, the scans
/// drawn and the render targets' bytes.
pub(crate) fn measure(
    gpu: &GpuContext,
    renderer: &mut Renderer,
    camera: &VirtualCamera,
    settings: &RenderSettings,
    frames: u32,
) -> anyhow::Result<(f64, usize, u64)> {
    let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("bench target"),
        size: wgpu::Extent3d {
            width: camera.width,
            height: camera.height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: IMAGE_FORMAT,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        view_formats: &[],
    });
    let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
    let target = RenderTarget {
        view: &view,
        format: IMAGE_FORMAT,
        width: camera.width,
        height: camera.height,
    };
    renderer.release_targets();
    let mut stats = Default::default();
    for _ in 0..2 {
        stats = renderer.render(camera, settings, &target)?;
        renderer.wait_idle()?;
    }
    // The median frame: robust against other work on a shared machine.
    let mut times = Vec::with_capacity(frames.max(1) as usize);
    for _ in 0..frames.max(1) {
        let start = Instant::now();
        stats = renderer.render(camera, settings, &target)?;
        renderer.wait_idle()?;
        times.push(start.elapsed().as_secs_f64() * 1000.0);
    }
    times.sort_by(f64::total_cmp);
    let ms = times[times.len() / 2];
    Ok((ms, stats.drawn, stats.target_memory.total()))
}

pub fn run(args: &BenchArgs) -> anyhow::Result<()> {
    let gpu = GpuContext::headless()?;
    println!("adapter: {}", gpu.adapter_name());
    if args.adaptive {
        return adaptive::run(&gpu, args);
    }
    if args.full_frame {
        return full_frame::run(&gpu, args);
    }
    println!(
        "target {}x{}, blended mode, k = 4, {} timed frames per row; scans: 64x48 lidar, 320x240 EO",
        args.width, args.height, args.frames
    );
    let sensor = scenes::sensor(64, 48, 320, 240);
    let camera = VirtualCamera::new(
        scenes::look_at([4.5, 0.0, -1.0], [4.5, 0.0, 5.05]),
        50.0,
        args.width,
        args.height,
    )?;
    let mut settings = RenderSettings::with_mode(Mode::Blended);
    if args.residency_only {
        return residency(&gpu, &sensor, &camera, &settings, args);
    }
    println!(
        "{:>6} {:>6} {:>10} {:>12} {:>12} {:>14} {:>12}",
        "scans", "drawn", "strategy", "frame ms", "targets MiB", "vs k-buf time", "vs k-buf mem"
    );
    let mut kbuffer_rows = Vec::new();
    for n in [10u32, 30, 100] {
        let model = scenes::corridor(&sensor, n);
        let mut renderer = Renderer::new(&gpu);
        renderer.sync_model(&model)?;
        settings.strategy = Strategy::KBuffer { batch: args.batch };
        let (kb_ms, drawn, kb_bytes) =
            measure(&gpu, &mut renderer, &camera, &settings, args.frames)?;
        settings.strategy = Strategy::NaiveLayers;
        let (nv_ms, _, nv_bytes) = measure(&gpu, &mut renderer, &camera, &settings, args.frames)?;
        settings.composite.mode = Mode::Painter;
        let (pt_ms, _, pt_bytes) = measure(&gpu, &mut renderer, &camera, &settings, args.frames)?;
        settings.composite.mode = Mode::Blended;
        let mib = |b: u64| b as f64 / 1048576.0;
        println!(
            "{n:>6} {drawn:>6} {:>10} {kb_ms:>12.2} {:>12.2} {:>14} {:>12}",
            "k-buffer",
            mib(kb_bytes),
            "1.00",
            "1.00"
        );
        println!(
            "{n:>6} {drawn:>6} {:>10} {nv_ms:>12.2} {:>12.2} {:>14.2} {:>12.2}",
            "naive",
            mib(nv_bytes),
            nv_ms / kb_ms,
            nv_bytes as f64 / kb_bytes as f64
        );
        println!(
            "{n:>6} {drawn:>6} {:>10} {pt_ms:>12.2} {:>12.2} {:>14.2} {:>12.2}",
            "painter",
            mib(pt_bytes),
            pt_ms / kb_ms,
            pt_bytes as f64 / kb_bytes as f64
        );
        kbuffer_rows.push(Measurement {
            scans: n,
            drawn,
            frame_ms: kb_ms,
            target_bytes: kb_bytes,
        });
    }
    if let (Some(first), Some(last)) = (kbuffer_rows.first(), kbuffer_rows.last()) {
        println!(
            "k-buffer: {} scans take {:.2}x the frame time of {} (target <= 2x); memory {:.2}x",
            last.scans,
            last.frame_ms / first.frame_ms,
            first.scans,
            last.target_bytes as f64 / first.target_bytes as f64
        );
    }
    // The batch size trades memory for merge passes.
    let model = scenes::corridor(&sensor, 30);
    let mut renderer = Renderer::new(&gpu);
    renderer.sync_model(&model)?;
    settings.strategy = Strategy::NaiveLayers;
    let (base_ms, drawn, base_bytes) =
        measure(&gpu, &mut renderer, &camera, &settings, args.frames)?;
    println!(
        "batch sweep, 30 scans ({drawn} drawn); naive layers: {base_ms:.2} ms, {:.2} MiB",
        base_bytes as f64 / 1048576.0
    );
    println!(
        "{:>6} {:>12} {:>12} {:>14} {:>12}",
        "batch", "frame ms", "targets MiB", "vs naive time", "vs naive mem"
    );
    for batch in [1u32, 2, 4, 8, 16] {
        settings.strategy = Strategy::KBuffer { batch };
        let (ms, _, bytes) = measure(&gpu, &mut renderer, &camera, &settings, args.frames)?;
        println!(
            "{batch:>6} {ms:>12.2} {:>12.2} {:>14.2} {:>12.2}",
            bytes as f64 / 1048576.0,
            ms / base_ms,
            bytes as f64 / base_bytes as f64
        );
    }
    profile(&gpu, &mut renderer, &camera, &mut settings, args)?;
    settings.strategy = Strategy::KBuffer { batch: args.batch };
    residency(&gpu, &sensor, &camera, &settings, args)
}

/// Residency: the 100-scan corridor with every scan resident against a budget that
/// holds what the view needs (frame time, GPU bytes of the scans); then the planner's
/// time per frame on listings of 2,000 and 20,000 scans (a corridor wall per 100
/// scans, walls 3 m apart, the camera seeing about 10 scans).
fn residency(
    gpu: &GpuContext,
    sensor: &texel::Sensor,
    camera: &VirtualCamera,
    settings: &RenderSettings,
    args: &BenchArgs,
) -> anyhow::Result<()> {
    use texel_viewer::residency::{DataState, PlanOptions, PlanScan, Residency, plan};
    let mib = |b: u64| b as f64 / 1048576.0;
    let full = scenes::corridor(sensor, 100);
    println!(
        "residency, 100 scans, blended k-buffer (batch {}):",
        args.batch
    );
    println!(
        "{:>12} {:>9} {:>7} {:>12} {:>10} {:>12}",
        "budget MiB", "resident", "drawn", "scans MiB", "frame ms", "vs all time"
    );
    // Every scan uploaded (no residency), then what the residency keeps.
    let mut renderer = Renderer::new(gpu);
    renderer.sync_model(&full)?;
    let (all_ms, drawn, _) = measure(gpu, &mut renderer, camera, settings, args.frames)?;
    println!(
        "{:>12} {:>9} {drawn:>7} {:>12.1} {all_ms:>10.2} {:>12.2}",
        "all",
        renderer.scan_count(),
        mib(renderer.scans_bytes()),
        1.0
    );
    drop(renderer);
    for budget_mb in [512u64, 4] {
        let mut model = full.clone();
        let mut residency =
            Residency::over_model(Residency::budget_bytes_of_mb(budget_mb), &mut model);
        let mut renderer = Renderer::new(gpu);
        let stats = residency.step(&mut model, &mut renderer, camera);
        let (ms, drawn, _) = measure(gpu, &mut renderer, camera, settings, args.frames)?;
        println!(
            "{budget_mb:>12} {:>9} {drawn:>7} {:>12.1} {ms:>10.2} {:>12.2}{}",
            stats.resident,
            mib(stats.used_bytes),
            ms / all_ms,
            if stats.left_out > 0 {
                format!("  ({} of {} needed left out)", stats.left_out, stats.needed)
            } else {
                String::new()
            }
        );
    }
    let listing = full
        .scans()
        .first()
        .map(|s| s.listing)
        .ok_or_else(|| anyhow::anyhow!("empty corridor"))?;
    for n in [2_000usize, 20_000] {
        let scans: Vec<PlanScan> = (0..n)
            .map(|i| PlanScan {
                id: i as u64,
                listing,
                world_from_scan: texel::Pose::translation(
                    (i % 100) as f64,
                    0.0,
                    -3.0 * (i / 100) as f64,
                ),
                bytes: 2 << 20,
                state: if i < 40 {
                    DataState::OnGpu
                } else {
                    DataState::Absent
                },
            })
            .collect();
        let options = PlanOptions::new(Residency::budget_bytes_of_mb(512));
        let mut times = Vec::new();
        let mut needed = 0;
        for _ in 0..args.frames.max(1) {
            let start = Instant::now();
            let p = plan(&scans, camera, &options);
            times.push(start.elapsed().as_secs_f64() * 1000.0);
            needed = p.needed;
        }
        times.sort_by(f64::total_cmp);
        println!(
            "planning {n} scans: {:.2} ms per frame (median of {}), {needed} needed",
            times[times.len() / 2],
            times.len()
        );
    }
    // A viewer with a 256 MiB budget on models of 1,000 and 20,000 scans: the frame
    // (planning, uploads, render) and the GPU memory, against the smaller model's.
    println!("models of many scans, 256 MiB budget:");
    let mut first_ms = None;
    for n in [1_000u32, 20_000] {
        let mut model = scenes::corridor(sensor, n);
        let mut residency = Residency::over_model(Residency::budget_bytes_of_mb(256), &mut model);
        let mut renderer = Renderer::new(gpu);
        // Settle: the first steps upload what the view needs.
        for _ in 0..3 {
            residency.step(&mut model, &mut renderer, camera);
        }
        let mut times = Vec::new();
        let mut last = None;
        for _ in 0..args.frames.max(1) {
            let start = Instant::now();
            let stats = residency.step(&mut model, &mut renderer, camera);
            measure(gpu, &mut renderer, camera, settings, 1)?;
            times.push(start.elapsed().as_secs_f64() * 1000.0);
            last = Some(stats);
        }
        times.sort_by(f64::total_cmp);
        let ms = times[times.len() / 2];
        let base = *first_ms.get_or_insert(ms);
        if let Some(stats) = last {
            println!(
                "{n:>7} scans: resident {}, GPU {:.1} MiB of 256, frame {ms:.2} ms ({:.2}x the 1,000-scan model's)",
                stats.resident,
                mib(stats.used_bytes),
                ms / base
            );
        }
    }
    Ok(())
}

/// Where a k-buffer frame's time goes: each phase submitted and waited for on its
/// own (the medians of `frames` frames; the sum exceeds an unprofiled frame by the
/// lost overlap).
fn profile(
    gpu: &GpuContext,
    renderer: &mut Renderer,
    camera: &VirtualCamera,
    settings: &mut RenderSettings,
    args: &BenchArgs,
) -> anyhow::Result<()> {
    let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("profile target"),
        size: wgpu::Extent3d {
            width: camera.width,
            height: camera.height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: IMAGE_FORMAT,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        view_formats: &[],
    });
    let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
    let target = RenderTarget {
        view: &view,
        format: IMAGE_FORMAT,
        width: camera.width,
        height: camera.height,
    };
    println!(
        "k-buffer phases, 30 scans, ms (median of {} frames):",
        args.frames
    );
    println!(
        "{:>6} {:>10} {:>10} {:>10} {:>10} {:>10}",
        "batch", "pre-pass", "layers", "merges", "composite", "sum"
    );
    renderer.profile_phases = true;
    for batch in [args.batch, 16] {
        settings.strategy = Strategy::KBuffer { batch };
        let mut samples: Vec<[f64; 4]> = Vec::new();
        for i in 0..args.frames.max(1) + 1 {
            let stats = renderer.render(camera, settings, &target)?;
            if i > 0
                && let Some(p) = stats.phase_ms
            {
                samples.push(p);
            }
        }
        let median = |j: usize| {
            let mut v: Vec<f64> = samples.iter().map(|p| p[j]).collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
        };
        let m = [median(0), median(1), median(2), median(3)];
        println!(
            "{batch:>6} {:>10.2} {:>10.2} {:>10.2} {:>10.2} {:>10.2}",
            m[0],
            m[1],
            m[2],
            m[3],
            m.iter().sum::<f64>()
        );
    }
    renderer.profile_phases = false;
    Ok(())
}
