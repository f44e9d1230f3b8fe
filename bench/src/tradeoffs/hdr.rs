//! `texel-bench tradeoffs hdr`: what exposure brackets buy on the high-dynamic-range
//! scenes. Each scene's trajectory is rendered with its exposure bracket (cycled frame
//! by frame); at held-out poses every pixel's surface point (the simulator's true
//! geometry and poses, so only the texture side is measured) is looked up in every
//! acquisition frame that sees it. The **LDR** texture is the one frame a best-scan
//! renderer would show (the most similar viewing direction), turned into radiance by
//! its exposure alone; the **HDR** texture merges the 8 frames that see it from the
//! most similar directions
//! (`texel::radiance::merge_exposures`' rule, per view: the seed's second strategy).
//! Both are scored against the simulator's radiance truth: the share of values no
//! exposure measured (black or saturated) and the error in log radiance. Writes the
//! hdr section of `docs/tradeoffs.md`.

use std::fmt::Write;
use std::time::Instant;

use anyhow::{Context, Result};
use nalgebra::{Point3, Vector2, Vector3};
use sims::{Effect, Scene};
use texel::radiance::{EoResponse, merge_exposures};
use texel::{EoFrame, PinholeCamera, Pose};
use texel_viewer::gpu::GpuContext;

use std::sync::Arc;

use texel::model::{Model, ModelEvent};
use texel::{FuseConfig, fuse};

use super::hdr_render::{RenderedHdr, render_hdr};
use crate::tradeoffs::rendering::held_out_poses;
use crate::tradeoffs::rendering::report::write_tradeoffs_section;

/// The section's options.
pub type HdrArgs = crate::tradeoffs::SimSectionArgs;

/// The scenes measured and their frames.
const SCENES: [(&str, usize); 2] = [("courtyard-hdr", 60), ("interior-window", 36)];

/// Held-out poses per scene.
const POSES: usize = 8;
const QUICK_POSES: usize = 3;

/// A point seen from another camera is visible there when the ray from that camera
/// first hits within this of it (metres, plus 1 % of the distance).
const VISIBILITY_TOLERANCE_M: f64 = 0.01;

/// Radiance below this counts as this in log errors (1 is white at 0 EV): black
/// estimates and truths have no log.
const LOG_FLOOR: f64 = 1.0e-4;

/// The effects measured: the scene's, without vignetting (Texel has no flat-field
/// correction yet, so vignetting would bias every radiance estimate near the edges
/// the same way in both textures).
fn effects(scene: &Scene) -> Vec<Effect> {
    scene
        .effects
        .iter()
        .filter(|e| e.name() != "vignetting")
        .cloned()
        .collect()
}

/// One texture's scores over every held-out pixel of a scene.
#[derive(Debug, Default, Clone)]
pub(super) struct Scores {
    values: usize,
    unmeasured: usize,
    log_errors: Vec<f64>,
}

impl Scores {
    pub(super) fn add(&mut self, estimate: f32, measured: bool, truth: f32) {
        self.values += 1;
        self.unmeasured += usize::from(!measured);
        let e = f64::from(estimate).max(LOG_FLOOR);
        let t = f64::from(truth).max(LOG_FLOOR);
        self.log_errors.push((e / t).ln().abs());
    }

    fn unmeasured_pct(&self) -> f64 {
        100.0 * self.unmeasured as f64 / self.values.max(1) as f64
    }

    fn percentile(&self, p: f64) -> f64 {
        crate::tradeoffs::percentile(&self.log_errors, p)
    }
}

struct SceneResult {
    name: &'static str,
    frames: usize,
    views: usize,
    pixels: usize,
    ldr: Scores,
    hdr: Scores,
    /// The seed's first strategy: each scan merged with the rest of its bracket (the
    /// frames just before and after it), then the best scan shown.
    per_scan: Scores,
    /// Merging one scan's bracket (full frames), ms, and merging per view (the
    /// held-out pixels' merges of up to 8 frames), ms per view.
    per_scan_merge_ms: f64,
    per_view_merge_ms: f64,
    merge_ms_per_scan: f64,
    rgba_ms_per_scan: f64,
    ldr_bytes_per_scan: u64,
    hdr_bytes_per_scan: u64,
    /// The same bracket rendered by the viewer's `points` mode with radiance.
    rendered: RenderedHdr,
}

/// An acquisition frame: where it was taken, its camera and its image.
struct Acquisition {
    /// Its frame number (brackets cycle frame by frame).
    index: usize,
    world_from_eo: Pose,
    frame: EoFrame,
}

/// The frames that see `point` and the pixel each sees it at.
fn observations<'a>(
    scene: &Scene,
    camera: &PinholeCamera,
    frames: &'a [Acquisition],
    point: &Point3<f64>,
) -> Vec<(&'a Acquisition, u32, u32)> {
    let mut seen = Vec::new();
    for a in frames {
        let eye = Point3::from(a.world_from_eo.translation.vector);
        let to_point = point - eye;
        let distance = to_point.norm();
        let Some(hit) = scene.cast_ray(eye, to_point) else {
            continue;
        };
        if (hit.distance_m - distance).abs() > VISIBILITY_TOLERANCE_M + 0.01 * distance {
            continue;
        }
        let in_camera = a.world_from_eo.inverse_transform_point(point).coords;
        let Ok(px) = camera.project(&in_camera) else {
            continue;
        };
        let (u, v) = (px.x.round(), px.y.round());
        if u < 0.0 || v < 0.0 || u >= f64::from(camera.width) || v >= f64::from(camera.height) {
            continue;
        }
        seen.push((a, u as u32, v as u32));
    }
    seen
}

fn measure_scene(
    gpu: &GpuContext,
    args: &HdrArgs,
    name: &'static str,
    frames: usize,
    poses: usize,
) -> Result<SceneResult> {
    let (scene, sim) = args.simulate(name, frames, |scene| Some(effects(scene)))?;

    let response: EoResponse = sim
        .effects()
        .exposure
        .as_ref()
        .context("the scene lists no exposure effect")?
        .true_response()?;
    let camera = sim.sensor_model().eo.clone();
    // 1. The acquisitions, and what turning each into radiance costs.
    let mut acquisitions = Vec::with_capacity(frames);
    let mut model = Model::new();
    let (mut merge_s, mut rgba_s) = (0.0, 0.0);
    for i in 0..frames {
        let f = sim.frame(i)?;
        // The baseline, in the same run: the RGB8 → RGBA8 copy an LDR texture needs.
        let start = Instant::now();
        let rgba: Vec<u8> = f
            .pair
            .eo
            .rgb
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect();
        rgba_s += start.elapsed().as_secs_f64();
        std::hint::black_box(rgba);
        let start = Instant::now();
        let radiance = merge_exposures(&[&f.pair.eo], &response)?;
        merge_s += start.elapsed().as_secs_f64();
        std::hint::black_box(radiance);
        let scan = fuse(
            &f.pair.range,
            f.pair.eo.clone(),
            sim.sensor(),
            &FuseConfig::default(),
        )?;
        model.apply(ModelEvent::ScanAdded {
            id: model.next_id(),
            scan: Arc::new(scan),
            world_from_scan: f.world_from_eo,
        })?;
        acquisitions.push(Acquisition {
            index: i,
            world_from_eo: f.world_from_eo,
            frame: f.pair.eo,
        });
    }
    // 2. Held-out views.
    let view_camera = crate::tradeoffs::sim_view_camera(&camera);
    let held_out = held_out_poses(&sim, poses);
    let (mut ldr, mut hdr) = (Scores::default(), Scores::default());
    let mut per_scan = Scores::default();
    let mut per_view_s = 0.0;
    // A scan's bracket: the frames within half a bracket of it in time.
    let bracket = sim
        .effects()
        .exposure
        .as_ref()
        .map_or(1, |e| e.bracket_ev.len().max(1));
    let half = bracket / 2;
    let mut pixels = 0;
    for pose in &held_out {
        let world_from_eo = &pose.world_from_eo;
        let truth = scene.radiance_view(world_from_eo, &view_camera);
        let eye = Point3::from(world_from_eo.translation.vector);
        for v in 0..view_camera.height {
            for u in 0..view_camera.width {
                let Some(t) = truth.get((v * view_camera.width + u) as usize) else {
                    continue;
                };
                let Ok(ray) = view_camera.unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                else {
                    continue;
                };
                let dir: Vector3<f64> = world_from_eo.rotation * ray;
                let Some(hit) = scene.cast_ray(eye, dir) else {
                    continue;
                };
                let seen = observations(&scene, &camera, &acquisitions, &hit.point);
                if seen.is_empty() {
                    continue;
                }
                pixels += 1;
                // The frames seeing the point from the most similar directions, best
                // first: the LDR texture is the first, the HDR one merges as many as the
                // blended renderer keeps per pixel (its k-buffer's largest k).
                let view_dir = (hit.point - eye).normalize();
                let mut ranked: Vec<(f64, (&Acquisition, u32, u32))> = seen
                    .iter()
                    .map(|s| {
                        let e = Point3::from(s.0.world_from_eo.translation.vector);
                        ((hit.point - e).normalize().dot(&view_dir), *s)
                    })
                    .collect();
                ranked.sort_by(|a, b| b.0.total_cmp(&a.0));
                ranked.truncate(texel_viewer::composite::MAX_K as usize);
                let Some(&(_, best)) = ranked.first() else {
                    continue;
                };
                let single = pixel_frame(best);
                let ldr_merge = merge_exposures(&[&single], &response)?;
                let all: Vec<EoFrame> = ranked.iter().map(|r| pixel_frame(r.1)).collect();
                let refs: Vec<&EoFrame> = all.iter().collect();
                let start = Instant::now();
                let hdr_merge = merge_exposures(&refs, &response)?;
                per_view_s += start.elapsed().as_secs_f64();
                // Strategy 1: the best frame's own bracket, where its frames see the
                // point (with the true geometry, as a per-scan merge would reproject
                // its neighbours into it).
                let own: Vec<EoFrame> = seen
                    .iter()
                    .filter(|s| s.0.index.abs_diff(best.0.index) <= half)
                    .map(|s| pixel_frame(*s))
                    .collect();
                let own_refs: Vec<&EoFrame> = own.iter().collect();
                let scan_merge = merge_exposures(&own_refs, &response)?;
                for (c, truth) in t.iter().enumerate() {
                    ldr.add(ldr_merge.rgb[0][c], ldr_merge.weight[0][c] > 0.0, *truth);
                    hdr.add(hdr_merge.rgb[0][c], hdr_merge.weight[0][c] > 0.0, *truth);
                    per_scan.add(scan_merge.rgb[0][c], scan_merge.weight[0][c] > 0.0, *truth);
                }
            }
        }
    }
    // The cost of strategy 1's merge: one scan's bracket of full frames (the
    // arithmetic only; a real one also reprojects the neighbours into the scan).
    let mut per_scan_s = 0.0;
    let mut merged_scans = 0usize;
    for window in acquisitions.windows(bracket) {
        let frames: Vec<&EoFrame> = window.iter().map(|a| &a.frame).collect();
        let start = Instant::now();
        std::hint::black_box(merge_exposures(&frames, &response)?);
        per_scan_s += start.elapsed().as_secs_f64();
        merged_scans += 1;
    }
    // 3. The same views rendered by the `points` mode with radiance.
    let rendered = render_hdr(gpu, &model, &scene, &response, &held_out, &view_camera)?;
    let pixels_per_frame = u64::from(camera.width) * u64::from(camera.height);
    Ok(SceneResult {
        name,
        frames,
        views: held_out.len(),
        pixels,
        ldr,
        hdr,
        per_scan,
        per_scan_merge_ms: 1e3 * per_scan_s / merged_scans.max(1) as f64,
        per_view_merge_ms: 1e3 * per_view_s / held_out.len().max(1) as f64,
        merge_ms_per_scan: 1e3 * merge_s / frames.max(1) as f64,
        rgba_ms_per_scan: 1e3 * rgba_s / frames.max(1) as f64,
        // The scan's texture as the renderer holds it: RGBA8 against RGBA16F.
        ldr_bytes_per_scan: 4 * pixels_per_frame,
        hdr_bytes_per_scan: 8 * pixels_per_frame,
        rendered,
    })
}

/// One pixel of an acquisition as a 1 x 1 frame with the acquisition's exposure.
fn pixel_frame((a, u, v): (&Acquisition, u32, u32)) -> EoFrame {
    EoFrame {
        width: 1,
        height: 1,
        rgb: a.frame.pixel(u, v).unwrap_or([0; 3]).to_vec(),
        timestamp_ns: a.frame.timestamp_ns,
        exposure: a.frame.exposure,
    }
}

pub fn run(args: &HdrArgs) -> Result<()> {
    let (poses, frame_div) = if args.quick {
        (QUICK_POSES, 3)
    } else {
        (POSES, 1)
    };
    // One device for every scene's rendered views.
    let gpu = GpuContext::headless()?;
    let mut results = Vec::new();
    for (name, frames) in SCENES {
        let start = Instant::now();
        let r = measure_scene(&gpu, args, name, (frames / frame_div).max(6), poses)?;
        println!(
            "{name}: {} frames, {} views, {} pixels; unmeasured LDR {:.2} % HDR {:.2} %; \
             ln error median LDR {:.4} HDR {:.4}, p95 LDR {:.4} HDR {:.4} ({:.1} s)",
            r.frames,
            r.views,
            r.pixels,
            r.ldr.unmeasured_pct(),
            r.hdr.unmeasured_pct(),
            r.ldr.percentile(0.5),
            r.hdr.percentile(0.5),
            r.ldr.percentile(0.95),
            r.hdr.percentile(0.95),
            start.elapsed().as_secs_f64()
        );
        println!(
            "{name} strategies: merge per scan then render: unmeasured {:.2} %, ln error \
             median {:.4} p95 {:.4}, {:.1} ms per scan; render then merge per view: \
             {:.2} %, {:.4} / {:.4}, {:.1} ms per view",
            r.per_scan.unmeasured_pct(),
            r.per_scan.percentile(0.5),
            r.per_scan.percentile(0.95),
            r.per_scan_merge_ms,
            r.hdr.unmeasured_pct(),
            r.hdr.percentile(0.5),
            r.hdr.percentile(0.95),
            r.per_view_merge_ms
        );
        let d = &r.rendered;
        println!(
            "{name} rendered (points, HDR): measured {} of {} surface pixels; ln error \
             median {:.4} p95 {:.4}; {:.1} ms/frame; {:.1} ms and {:.2} MB per scan",
            d.measured_pixels,
            d.surface_pixels,
            d.scores.percentile(0.5),
            d.scores.percentile(0.95),
            d.frame_ms,
            d.prepare_ms_per_scan,
            d.gpu_bytes_per_scan / 1e6
        );
        results.push(r);
    }
    let body = markdown(&results, args, &gpu.adapter_name());
    if args.quick || args.no_write {
        print!("{body}");
        return Ok(());
    }
    write_tradeoffs_section(&args.repo, "hdr", &body)
}

fn markdown(results: &[SceneResult], args: &HdrArgs, adapter: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "## High dynamic range: what exposure brackets buy\n");
    let _ = writeln!(
        s,
        "`cargo run --release -p texel-bench -- tradeoffs hdr` (seed {}), on the scenes \
         with a real dynamic range, each EO frame exposed at its place in the scene's \
         bracket (docs/hdr.md). At held-out poses (views a quarter of \
         the EO camera's size per side) every pixel's surface point is looked up in \
         every frame that sees it, with the simulator's true geometry and poses, so only \
         the texture is measured. **LDR**: the one frame a best-scan renderer shows (the \
         most similar viewing direction), made radiance by its own exposure; **HDR**: \
         the 8 frames that see the point from the most similar directions (as many as \
         the blended renderer keeps per pixel), merged per view (Debevec & Malik's eq. 6 with \
         the camera's true response). Unmeasured: channel values black or saturated in \
         every frame used. Log errors against the simulator's radiance truth (values \
         below 10^-4 count as 10^-4). The scenes' effects without vignetting, which \
         Texel does not correct yet.\n",
        args.seed
    );
    let _ = writeln!(
        s,
        "| scene | frames | held-out pixels | unmeasured LDR | unmeasured HDR | ln error median LDR / HDR | ln error p95 LDR / HDR | radiance per scan (× RGBA8 copy) | texture per scan LDR / HDR |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
    for r in results {
        let _ = writeln!(
            s,
            "| `{}` | {} | {} ({} views) | {:.2} % | {:.2} % | {:.4} / {:.4} | {:.4} / {:.4} | {:.1} ms ({:.0}×) | {:.2} / {:.2} MB |",
            r.name,
            r.frames,
            r.pixels,
            r.views,
            r.ldr.unmeasured_pct(),
            r.hdr.unmeasured_pct(),
            r.ldr.percentile(0.5),
            r.hdr.percentile(0.5),
            r.ldr.percentile(0.95),
            r.hdr.percentile(0.95),
            r.merge_ms_per_scan,
            r.merge_ms_per_scan / r.rgba_ms_per_scan.max(1e-9),
            r.ldr_bytes_per_scan as f64 / 1e6,
            r.hdr_bytes_per_scan as f64 / 1e6,
        );
    }
    let _ = writeln!(
        s,
        "\n\"Radiance per scan\" is the time to turn one full EO frame into radiance \
         with its weights (`merge_exposures` of one exposure, one thread), and in \
         brackets its ratio to the RGB8 to RGBA8 copy an LDR texture needs, timed in \
         the same run. \"Texture per scan\" is the GPU texture the renderer holds: \
         RGBA8 today, RGBA16F for radiance. The p95 errors of both include resampling \
         (each frame's nearest pixel, from frames that saw the surface coarser or finer \
         than the held-out view)."
    );
    let _ = writeln!(
        s,
        "\n**The seed's two strategies** (Lechelek et al. §6), on the same pixels with \
         the same true geometry. *Merge per scan, then render*: each scan merged once \
         with the rest of its bracket (the frames within half a bracket of it in time, \
         where they see the point), the best scan's radiance shown; its cost is one \
         bracket of full frames merged per scan (the arithmetic; reprojecting the \
         neighbours into the scan comes on top) and an RGBA16F texture kept per scan. \
         *Render, then merge per view* (the HDR column above, and what the `points` \
         mode renders): the 8 most similar frames merged at every view; its cost is the \
         merges of every held-out pixel per view, the scans keeping their RGBA8 \
         textures.\n"
    );
    let _ = writeln!(
        s,
        "| scene | strategy | unmeasured | ln error median | ln error p95 | merge cost | texture per scan |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|");
    for r in results {
        let strategies = [
            (
                "merge per scan, then render",
                &r.per_scan,
                r.per_scan_merge_ms,
                "scan",
                r.hdr_bytes_per_scan,
            ),
            (
                "render, then merge per view",
                &r.hdr,
                r.per_view_merge_ms,
                "view",
                r.ldr_bytes_per_scan,
            ),
        ];
        for (strategy, scores, merge_ms, per, bytes) in strategies {
            let _ = writeln!(
                s,
                "| `{}` | {strategy} | {:.2} % | {:.4} | {:.4} | {merge_ms:.1} ms per {per} | {:.2} MB |",
                r.name,
                scores.unmeasured_pct(),
                scores.percentile(0.5),
                scores.percentile(0.95),
                bytes as f64 / 1e6,
            );
        }
    }
    let _ = writeln!(
        s,
        "\n**Rendered.** The same frames fused into scans at their true poses and drawn \
         at the same held-out poses (the same size, an undistorted pinhole of the same \
         field of view) by the viewer's `points` mode with radiance (`--mode points \
         --hdr`: each scan's frame made radiance through the true response, alpha its \
         least hat weight; blended per view in half floats), read back before tone \
         mapping and scored against the radiance truth. Unmeasured: pixels where the \
         scene has a surface and no view measured the render's (the proxy left it \
         uncovered, such as ground beyond the lidar's range, or every view saw it black \
         or saturated); log errors over the measured ones. Frame time: render, tone mapping and read-back of the 8-bit image, \
         median over the views, on {}. Per scan: building its points, acquisition depth \
         map and radiance texture once, and the GPU bytes they add.\n",
        adapter
    );
    let _ = writeln!(
        s,
        "| scene | surface pixels | unmeasured | ln error median | ln error p95 | ms/frame | build per scan | GPU per scan |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|");
    for r in results {
        let d = &r.rendered;
        let _ = writeln!(
            s,
            "| `{}` | {} | {:.2} % | {:.4} | {:.4} | {:.0} | {:.1} ms | {:.2} MB |",
            r.name,
            d.surface_pixels,
            100.0 * (1.0 - d.measured_pixels as f64 / d.surface_pixels.max(1) as f64),
            d.scores.percentile(0.5),
            d.scores.percentile(0.95),
            d.frame_ms,
            d.prepare_ms_per_scan,
            d.gpu_bytes_per_scan / 1e6
        );
    }
    s
}
