//! `texel-bench tradeoffs points`: the point proxy's per-view depth maps (Lechelek et
//! al. 2019 §4, `texel_viewer::points`, the CPU reference) against the true depth.
//! Every simulated frame is fused into a texel scan and placed at its true pose; each
//! scan vertex becomes a point with its area-weighted normal and a disk one lidar pixel
//! pitch wide at its range. At held-out poses the depth map (splatting, front/back
//! classification, pull-push) is compared pixel by pixel with the depth the
//! simulator's ray caster finds, with and without the classification. Writes the
//! points section of `docs/tradeoffs.md`.

use std::fmt::Write;
use std::time::Instant;

use anyhow::Result;
use nalgebra::{Point3, Vector3};
use sims::Simulator;
use texel::{FuseConfig, Sensor, fuse};
use texel_viewer::points::cloud::scan_points;
use texel_viewer::points::splat::{SplatCamera, SplatPoint, depth_map_with};

use crate::tradeoffs::rendering::held_out_poses;
use crate::tradeoffs::rendering::report::write_tradeoffs_section;

/// The section's options.
pub type PointsArgs = crate::tradeoffs::SimSectionArgs;

const SCENES: [(&str, usize); 2] = [("lab", 36), ("courtyard", 40)];
const POSES: usize = 6;
const QUICK_POSES: usize = 2;

#[derive(Debug, Default, Clone)]
struct DepthScores {
    /// Pixels where the truth has a surface.
    surface: usize,
    /// ... and the map gives a depth.
    covered: usize,
    /// Pixels where the map gives a depth and the truth has none.
    invented: usize,
    errors_m: Vec<f64>,
    seconds: f64,
    views: usize,
}

impl DepthScores {
    fn percentile(&self, p: f64) -> f64 {
        crate::tradeoffs::percentile(&self.errors_m, p)
    }

    fn coverage_pct(&self) -> f64 {
        100.0 * self.covered as f64 / self.surface.max(1) as f64
    }

    fn ms_per_view(&self) -> f64 {
        1e3 * self.seconds / self.views.max(1) as f64
    }
}

struct SceneResult {
    name: &'static str,
    frames: usize,
    points: usize,
    classified: DepthScores,
    unclassified: DepthScores,
}

/// Every fused vertex of every frame as a world point with its normal and radius.
struct WorldPoint {
    position: Point3<f64>,
    normal: Vector3<f64>,
    radius_m: f64,
}

fn proxy(sim: &Simulator, frames: usize) -> Result<Vec<WorldPoint>> {
    let sensor: &Sensor = sim.sensor();
    let pitch_rad = 1.0 / sim.sensor_model().lidar.fx.max(1e-9);
    let mut points = Vec::new();
    for i in 0..frames {
        let frame = sim.frame(i)?;
        let scan = fuse(
            &frame.pair.range,
            frame.pair.eo,
            sensor,
            &FuseConfig::default(),
        )?;
        // The same points the `points` mode draws, with the sensor's own pitch.
        let world_from_scan = frame.world_from_eo;
        for p in scan_points(&scan, pitch_rad) {
            let [x, y, z] = p.position.map(f64::from);
            let [nx, ny, nz] = p.normal.map(f64::from);
            points.push(WorldPoint {
                position: world_from_scan * Point3::new(x, y, z),
                normal: world_from_scan.rotation * Vector3::new(nx, ny, nz),
                radius_m: f64::from(p.radius_m),
            });
        }
    }
    Ok(points)
}

fn measure_scene(
    args: &PointsArgs,
    name: &'static str,
    frames: usize,
    poses: usize,
) -> Result<SceneResult> {
    let (scene, sim) = args.simulate(name, frames, |_| None)?;

    let world_points = proxy(&sim, frames)?;
    let eo = &sim.sensor_model().eo;
    let view = crate::tradeoffs::sim_view_camera(eo);
    // The splats use the view's pinhole (no distortion): the truth's rays are cast
    // through the same pinhole.
    let cam = SplatCamera {
        width: view.width,
        height: view.height,
        fx: view.fx as f32,
        fy: view.fy as f32,
        cx: view.cx as f32,
        cy: view.cy as f32,
    };
    let (mut classified, mut unclassified) = (DepthScores::default(), DepthScores::default());
    for pose in held_out_poses(&sim, poses) {
        let world_from_eo = pose.world_from_eo;
        let eo_from_world = world_from_eo.inverse();
        // Points in the view's frame, f32 relative to its eye.
        let points: Vec<SplatPoint> = world_points
            .iter()
            .map(|p| {
                let q = eo_from_world * p.position;
                let n = eo_from_world.rotation * p.normal;
                SplatPoint {
                    position: [q.x as f32, q.y as f32, q.z as f32],
                    normal: [n.x as f32, n.y as f32, n.z as f32],
                    radius_m: p.radius_m as f32,
                }
            })
            .collect();
        // The true z-depth of every pixel through the same pinhole.
        let eye = Point3::from(world_from_eo.translation.vector);
        let truth: Vec<Option<f64>> = (0..view.height)
            .flat_map(|v| (0..view.width).map(move |u| (u, v)))
            .map(|(u, v)| {
                let ray = Vector3::new(
                    (f64::from(u) - view.cx) / view.fx,
                    (f64::from(v) - view.cy) / view.fy,
                    1.0,
                );
                let dir = world_from_eo.rotation * ray;
                scene
                    .cast_ray(eye, dir)
                    .map(|hit| hit.distance_m / ray.norm())
            })
            .collect();
        for (classify, scores) in [(true, &mut classified), (false, &mut unclassified)] {
            let start = Instant::now();
            let (map, _, _) = depth_map_with(&points, &cam, classify);
            scores.seconds += start.elapsed().as_secs_f64();
            scores.views += 1;
            for (m, t) in map.iter().zip(&truth) {
                match (m, t) {
                    (Some(m), Some(t)) => {
                        scores.surface += 1;
                        scores.covered += 1;
                        scores.errors_m.push((f64::from(*m) - t).abs());
                    }
                    (None, Some(_)) => scores.surface += 1,
                    (Some(_), None) => scores.invented += 1,
                    (None, None) => {}
                }
            }
        }
    }
    Ok(SceneResult {
        name,
        frames,
        points: world_points.len(),
        classified,
        unclassified,
    })
}

pub fn run(args: &PointsArgs) -> Result<()> {
    let (poses, frame_div) = if args.quick {
        (QUICK_POSES, 3)
    } else {
        (POSES, 1)
    };
    let mut results = Vec::new();
    for (name, frames) in SCENES {
        let r = measure_scene(args, name, (frames / frame_div).max(4), poses)?;
        for (label, s) in [
            ("classified", &r.classified),
            ("unclassified", &r.unclassified),
        ] {
            println!(
                "{name} {label}: {} points, coverage {:.2} %, invented {}, depth error median {:.4} m p95 {:.4} m, {:.0} ms/view",
                r.points,
                s.coverage_pct(),
                s.invented,
                s.percentile(0.5),
                s.percentile(0.95),
                s.ms_per_view()
            );
        }
        results.push(r);
    }
    let body = markdown(&results, args);
    if args.quick || args.no_write {
        print!("{body}");
        return Ok(());
    }
    write_tradeoffs_section(&args.repo, "points", &body)
}

fn markdown(results: &[SceneResult], args: &PointsArgs) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "## Point proxy: per-view depth maps against the truth\n");
    let _ = writeln!(
        s,
        "`cargo run --release -p texel-bench -- tradeoffs points` (seed {}). Every \
         simulated frame (the scene's effects) is fused and placed at its true pose; \
         each scan vertex is a point with its area-weighted normal and a disk one lidar \
         pixel pitch wide at its range. At {POSES} held-out poses per scene (views a \
         quarter of the EO camera's size per side, undistorted) the depth map of \
         Lechelek et al. §4 (`texel_viewer::points`, the CPU reference: ellipse \
         splatting, front/back classification, pull-push, kept where the splats drew) is \
         compared with the ray caster's depth, with and without the classification. \
         Coverage: pixels with a true surface that get a depth; invented: pixels with a \
         depth and no true surface. Time: the whole depth map on one thread.\n",
        args.seed
    );
    let _ = writeln!(
        s,
        "| scene | frames | points | classification | coverage | invented pixels | depth error median | depth error p95 | time per view |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
    for r in results {
        for (label, d) in [("on", &r.classified), ("off", &r.unclassified)] {
            let _ = writeln!(
                s,
                "| `{}` | {} | {} | {label} | {:.2} % | {} | {:.1} mm | {:.1} mm | {:.0} ms |",
                r.name,
                r.frames,
                r.points,
                d.coverage_pct(),
                d.invented,
                1e3 * d.percentile(0.5),
                1e3 * d.percentile(0.95),
                d.ms_per_view()
            );
        }
    }
    s
}
