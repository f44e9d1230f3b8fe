//! Calibration against the simulator's truth: views of the `calib-target` scene from
//! sampled poses, the error of a calibration against the true sensor model (focal
//! length, principal point, held-out reprojection, extrinsic, bias), and the fusion
//! check (a `lab` frame fused with the calibrated and with the true sensor file).
//! The calibration itself never sees any of the truth used here.

use nalgebra::{Point3, Vector2, Vector3};
use sims::{Scene, SimOptions, Simulator};
use texel::{FuseConfig, Pose, Sensor, SensorModel};

use calib::config::TargetConfig;
use calib::detect::{DetectParams, detect_board};
use calib::eo::fit_board_pose;
use calib::gray::GrayImage;
use calib::pipeline::{CalibInput, CalibView, Calibration};

/// The board's centre and the direction its face looks in, in the `calib-target`
/// scene's world frame.
pub const BOARD_CENTRE: [f64; 3] = [0.0, 0.0, 1.2];
pub const BOARD_FACING: [f64; 3] = [0.0, -1.0, 0.0];

/// How views are placed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PoseStyle {
    /// A capture as the calibration guide asks for it: tilts of 25-55 degrees about
    /// varying axes and rolls of up to 15 degrees throughout. Even views keep the whole
    /// plate inside the lidar's view (0.95-1.35 m away, near the middle); odd views
    /// (0.55-0.85 m away) cover the EO image,
    /// putting the board into its four corners and against its four edges in turn
    /// (see [`COVERAGE_CELLS`]), where the distortion's radial and tangential terms
    /// part from the principal point.
    Varied,
    /// The board pushed towards the EO image's edges (the lidar may lose it).
    NearBorder,
    /// Board square-on to the camera (tilt below 2 degrees).
    FrontoParallel,
    /// Tilts of about `deg` degrees only.
    Tilt(f64),
    /// The board in the EO image but partly outside the lidar's narrower view.
    LidarCut,
}

/// Where the coverage views of [`PoseStyle::Varied`] put the board in the EO image, in
/// turn: `(-1, 0, +1)` along x (left, middle, right) and y (top, middle, bottom). The
/// four corners come first: they fix the tangential terms best.
pub const COVERAGE_CELLS: [(i8, i8); 8] = [
    (-1, -1),
    (1, 1),
    (1, -1),
    (-1, 1),
    (-1, 0),
    (1, 0),
    (0, -1),
    (0, 1),
];

/// A coverage view's inner corners stay this far inside the EO image (pixels), so the
/// detector's window fits.
const COVERAGE_INSIDE_PX: f64 = 10.0;
/// ... and come within this much more of the borders of their cell (pixels).
const COVERAGE_REACH_PX: f64 = 40.0;

/// A small deterministic generator (splitmix64) for pose sampling.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [lo, hi).
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
}

/// The plate's corners in the world (the scene's board is 0.6 x 0.45 m).
fn plate_corners(target: &TargetConfig) -> Vec<Point3<f64>> {
    let [w, h] = target.plate_m;
    let c = Vector3::from(BOARD_CENTRE);
    [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        .iter()
        .map(|(sx, sz)| Point3::from(c + Vector3::new(sx * w * 0.5, 0.0, sz * h * 0.5)))
        .collect()
}

/// How far inside `camera`'s image (pixels) the plate's corners are at `world_from_camera`;
/// negative when a corner is outside.
fn margin_px(
    camera: &texel::PinholeCamera,
    world_from_camera: &Pose,
    corners: &[Point3<f64>],
) -> f64 {
    let inv = world_from_camera.inverse();
    corners
        .iter()
        .map(|p| match camera.project(&(inv * p).coords) {
            Ok(px) => {
                px.x.min(px.y)
                    .min(f64::from(camera.width) - 1.0 - px.x)
                    .min(f64::from(camera.height) - 1.0 - px.y)
            }
            Err(_) => -1.0e9,
        })
        .fold(f64::INFINITY, f64::min)
}

/// The board's outermost inner corners (the rim of the corner grid) in the world.
fn inner_corner_rim(target: &TargetConfig) -> Vec<Point3<f64>> {
    let (nx, ny) = (target.nx(), target.ny());
    let c = Vector3::from(BOARD_CENTRE);
    let s = target.square_m;
    let (hx, hz) = ((nx as f64 - 1.0) * 0.5 * s, (ny as f64 - 1.0) * 0.5 * s);
    let mut out = Vec::with_capacity(2 * (nx + ny));
    for i in 0..nx {
        for j in [0, ny - 1] {
            out.push((i, j));
        }
    }
    for j in 1..ny.saturating_sub(1) {
        for i in [0, nx - 1] {
            out.push((i, j));
        }
    }
    out.into_iter()
        .map(|(i, j)| Point3::from(c + Vector3::new(i as f64 * s - hx, 0.0, j as f64 * s - hz)))
        .collect()
}

/// Pixel bounding box `[min x, min y, max x, max y]` of `points` seen from
/// `world_from_camera`; `None` when one is behind the camera.
fn pixel_extent(
    camera: &texel::PinholeCamera,
    world_from_camera: &Pose,
    points: &[Point3<f64>],
) -> Option<[f64; 4]> {
    let inv = world_from_camera.inverse();
    let mut b = [
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    ];
    for p in points {
        let px = camera.project(&(inv * p).coords).ok()?;
        b = [
            b[0].min(px.x),
            b[1].min(px.y),
            b[2].max(px.x),
            b[3].max(px.y),
        ];
    }
    Some(b)
}

/// True when the inner corners' box `b` lies inside a `width` x `height` image and
/// reaches the borders of `cell` (see [`COVERAGE_CELLS`]).
fn covers_cell(b: [f64; 4], width: f64, height: f64, cell: (i8, i8)) -> bool {
    let inside = COVERAGE_INSIDE_PX;
    let reach = inside + COVERAGE_REACH_PX;
    let axis = |lo: f64, hi: f64, size: f64, side: i8| {
        let far = size - 1.0;
        lo >= inside
            && hi <= far - inside
            && match side {
                -1 => lo <= reach,
                1 => hi >= far - reach,
                _ => (0.5 * (lo + hi) - 0.5 * far).abs() <= size / 6.0,
            }
    };
    axis(b[0], b[2], width, cell.0) && axis(b[1], b[3], height, cell.1)
}

/// `count` camera poses (`world_from_eo`) looking at the board, by `style`.
pub fn sample_poses(
    sim: &Simulator,
    target: &TargetConfig,
    count: usize,
    style: PoseStyle,
    seed: u64,
) -> Vec<Pose> {
    let model = sim.sensor_model();
    let corners = plate_corners(target);
    let rim = inner_corner_rim(target);
    let (width, height) = (f64::from(model.eo.width), f64::from(model.eo.height));
    let centre = Point3::from(BOARD_CENTRE);
    let facing = Vector3::from(BOARD_FACING);
    let mut rng = Rng::new(seed);
    let mut out = Vec::with_capacity(count);
    let mut attempts = 0;
    while out.len() < count && attempts < 400_000 {
        attempts += 1;
        // Every other varied view covers a cell of the EO image (corners and edges,
        // in turn), the others keep the plate inside the lidar's view.
        let cell = (style == PoseStyle::Varied && out.len() % 2 == 1)
            .then(|| COVERAGE_CELLS[(out.len() / 2) % COVERAGE_CELLS.len()]);
        let (tilt_lo, tilt_hi, dist_lo, dist_hi, look) = match style {
            PoseStyle::Varied if cell.is_some() => (25.0, 55.0, 0.55, 0.85, 0.0),
            PoseStyle::Varied => (25.0, 55.0, 0.95, 1.35, 0.06),
            PoseStyle::NearBorder => (10.0, 35.0, 0.8, 1.0, 0.3),
            PoseStyle::FrontoParallel => (0.0, 2.0, 1.0, 1.3, 0.0),
            PoseStyle::Tilt(d) => (d * 0.8, d, 1.0, 1.3, 0.05),
            PoseStyle::LidarCut => (15.0, 30.0, 0.9, 1.1, 0.2),
        };
        let tilt = rng.uniform(tilt_lo, tilt_hi).to_radians();
        let azimuth = rng.uniform(0.0, std::f64::consts::TAU);
        let dist = rng.uniform(dist_lo, dist_hi);
        // Direction from the board to the camera: the facing direction tipped by `tilt`.
        let tip = Vector3::new(azimuth.cos(), 0.0, azimuth.sin()) * tilt.sin();
        let dir = (facing * tilt.cos() + tip).normalize();
        let eye = centre + dir * dist;
        let aim = centre
            + Vector3::new(
                rng.uniform(-look, look),
                0.0,
                rng.uniform(-look, look) * 0.75,
            );
        let base = sims::trajectory::look_at(eye, aim, Vector3::z());
        let roll = rng.uniform(-15.0, 15.0).to_radians();
        let mut pose = base * Pose::rotation(Vector3::z() * roll);
        if let Some((sx, sy)) = cell {
            // Turn the camera so that the board's centre lands on a pixel in the cell's
            // half of the image (the check below keeps the poses that reach its borders).
            let pick = |rng: &mut Rng, side: i8, size: f64| match side {
                -1 => rng.uniform(0.0, 0.5 * size),
                1 => rng.uniform(0.5 * size, size),
                _ => rng.uniform(0.3 * size, 0.7 * size),
            };
            let px = Vector2::new(pick(&mut rng, sx, width), pick(&mut rng, sy, height));
            let Ok(ray) = model.eo.unproject_ray(px) else {
                continue;
            };
            let Some(turn) = nalgebra::UnitQuaternion::rotation_between(&ray, &Vector3::z()) else {
                continue;
            };
            pose *= Pose::from_parts(nalgebra::Translation3::identity(), turn);
        }
        let lidar_pose = pose * model.eo_from_lidar;
        let eo_margin = margin_px(&model.eo, &pose, &corners);
        let lidar_margin = margin_px(&model.lidar, &lidar_pose, &corners);
        let ok = match style {
            PoseStyle::NearBorder => (2.0..25.0).contains(&eo_margin),
            PoseStyle::LidarCut => eo_margin > 8.0 && lidar_margin < -3.0,
            PoseStyle::Varied if let Some(cell) = cell => pixel_extent(&model.eo, &pose, &rim)
                .is_some_and(|b| covers_cell(b, width, height, cell)),
            _ => eo_margin > 8.0 && lidar_margin > 3.0,
        };
        if ok {
            out.push(pose);
        }
    }
    out
}

/// A simulator of `scene` at its own resolution with its effects (or `effects`).
pub fn simulator(
    scene: Scene,
    seed: u64,
    effects: Option<Vec<sims::Effect>>,
) -> Result<Simulator, sims::SimError> {
    Simulator::with_options(
        scene,
        &SimOptions {
            seed,
            effects,
            ..SimOptions::default()
        },
    )
}

/// Renders views at `poses` into calibration input (lidar intrinsics as a capture
/// would carry them).
pub fn render_input(sim: &Simulator, poses: &[Pose], first_noise_frame: u64) -> CalibInput {
    let views = poses
        .iter()
        .enumerate()
        .map(|(k, pose)| {
            let timestamp_ns = 1_000_000_000 + k as u64 * 500_000_000;
            CalibView {
                timestamp_ns,
                pair: sim.render_at(pose, first_noise_frame + k as u64, timestamp_ns),
            }
        })
        .collect();
    CalibInput {
        views,
        lidar: sim.sensor_model().lidar.clone(),
        info: sim.sensor_model().info(),
        warnings: Vec::new(),
    }
}

/// A calibration's errors against the truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Accuracy {
    /// `max(|fx - fx*| / fx*, |fy - fy*| / fy*)`, percent.
    pub focal_error_percent: f64,
    /// Distance of the principal point from the true one, pixels.
    pub principal_point_error_px: f64,
    /// RMS reprojection of held-out views' detected corners (pose fitted, intrinsics
    /// fixed), pixels.
    pub held_out_rms_px: f64,
    /// RMS over the image of the pixel difference between the calibrated and the true
    /// EO camera projecting the same rays, pixels.
    pub model_rms_px: f64,
    pub rotation_error_deg: f64,
    pub translation_error_mm: f64,
    /// Estimated range bias, millimetres.
    pub range_bias_mm: f64,
    /// Estimated minus true range bias, millimetres.
    pub range_bias_error_mm: f64,
    pub held_out_views: usize,
}

/// Errors of `calibration` against `truth`, with `held_out` views (not used to
/// calibrate) for the reprojection figure.
pub fn accuracy(
    calibration: &Calibration,
    truth: &SensorModel,
    held_out: &CalibInput,
    target: &TargetConfig,
) -> Accuracy {
    let eo = &calibration.sensor.eo;
    let t = &truth.eo;
    let focal_error_percent =
        ((eo.fx - t.fx).abs() / t.fx).max((eo.fy - t.fy).abs() / t.fy) * 100.0;
    let principal_point_error_px = (eo.cx - t.cx).hypot(eo.cy - t.cy);
    let (mut sum, mut n, mut views) = (0.0, 0usize, 0usize);
    for (k, v) in held_out.views.iter().enumerate() {
        let Some(g) = GrayImage::from_eo(&v.pair.eo) else {
            continue;
        };
        let Ok(corners) = detect_board(&g, target, &DetectParams::eo(g.width, g.height)) else {
            continue;
        };
        if let Some((_, r)) = fit_board_pose(eo, &corners, target, k) {
            sum += r.residuals.iter().map(|x| x.2.norm_squared()).sum::<f64>();
            n += r.residuals.len();
            views += 1;
        }
    }
    let held_out_rms_px = if n > 0 {
        (sum / n as f64).sqrt()
    } else {
        f64::NAN
    };
    // The two cameras projecting the true camera's pixel rays, on a 16 x 12 grid.
    let (mut msum, mut mn) = (0.0, 0usize);
    for gy in 0..12 {
        for gx in 0..16 {
            let px = Vector2::new(
                (f64::from(gx) + 0.5) / 16.0 * f64::from(t.width) - 0.5,
                (f64::from(gy) + 0.5) / 12.0 * f64::from(t.height) - 0.5,
            );
            if let Ok(ray) = t.unproject_ray(px)
                && let Ok(q) = eo.project(&ray)
            {
                msum += (q - px).norm_squared();
                mn += 1;
            }
        }
    }
    let (rot, trans) =
        texel::pose::pose_difference(&truth.eo_from_lidar, &calibration.sensor.eo_from_lidar);
    Accuracy {
        focal_error_percent,
        principal_point_error_px,
        held_out_rms_px,
        model_rms_px: if mn > 0 {
            (msum / mn as f64).sqrt()
        } else {
            f64::NAN
        },
        rotation_error_deg: rot.to_degrees(),
        translation_error_mm: trans * 1e3,
        range_bias_mm: calibration.lidar.range_bias_m * 1e3,
        range_bias_error_mm: (calibration.lidar.range_bias_m - truth.range_bias_m) * 1e3,
        held_out_views: views,
    }
}

/// Fusion errors of one sensor file on simulated frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusionErrors {
    /// RMS distance of fused points from the true surface points, millimetres.
    pub point_rms_mm: f64,
    /// RMS distance of each point's texture coordinate from the true projection of its
    /// true surface point, EO pixels.
    pub texture_rms_px: f64,
    /// RMS difference between each point's colour (the frame sampled at its texture
    /// coordinate) and the clean render at the true projection, 8-bit units.
    pub colour_rms: f64,
    pub points: usize,
}

/// Fuses frames of `sim` (rendered with the true sensor) with `sensor`, and measures
/// the errors against the truth.
pub fn fusion_errors(sim: &Simulator, sensor: &SensorModel, frames: &[usize]) -> FusionErrors {
    let truth = sim.sensor_model();
    let fuse_sensor = Sensor::new(sensor.clone());
    let (mut p2, mut t2, mut c2, mut n, mut nt) = (0.0, 0.0, 0.0, 0usize, 0usize);
    for &i in frames {
        let Ok(frame) = sim.frame(i) else {
            continue;
        };
        let world_from_eo = frame.world_from_eo;
        let clean = sim.clean_eo_at(&world_from_eo, frame.timestamp_ns);
        let lidar_truth = sim.lidar_truth_at(&world_from_eo);
        let eo_image = frame.pair.eo.clone();
        let Ok(scan) = texel::fuse(
            &frame.pair.range,
            frame.pair.eo,
            &fuse_sensor,
            &FuseConfig::default(),
        ) else {
            continue;
        };
        let eo_from_world = world_from_eo.inverse();
        for (v, vert) in scan.vertices.iter().enumerate() {
            let pixel = scan.vertex_pixel[v] as usize;
            let Some(Some(hit)) = lidar_truth.hits.get(pixel) else {
                continue;
            };
            let true_eo = eo_from_world * hit.point;
            let fused = Vector3::new(f64::from(vert[0]), f64::from(vert[1]), f64::from(vert[2]));
            let d2 = (fused - true_eo.coords).norm_squared();
            // Mixed pixels and dropouts at depth edges are range effects, not calibration:
            // points more than 10 cm off are left out of both figures alike.
            if !(d2 < 0.01) {
                continue;
            }
            p2 += d2;
            n += 1;
            if !scan.vertex_textured[v] {
                continue;
            }
            let Ok(true_px) = truth.eo.project(&true_eo.coords) else {
                continue;
            };
            let px = texel::fuse::pixel_of_tex_coord(
                scan.tex_coords[v],
                eo_image.width,
                eo_image.height,
            );
            t2 += (px - true_px).norm_squared();
            let a = sample_rgb(&eo_image, px);
            let b = sample_rgb(&clean, true_px);
            c2 += (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>() / 3.0;
            nt += 1;
        }
    }
    FusionErrors {
        point_rms_mm: (p2 / n.max(1) as f64).sqrt() * 1e3,
        texture_rms_px: (t2 / nt.max(1) as f64).sqrt(),
        colour_rms: (c2 / nt.max(1) as f64).sqrt(),
        points: n,
    }
}

/// Bilinear RGB of an EO frame at a pixel-centre coordinate (clamped).
fn sample_rgb(frame: &texel::EoFrame, p: Vector2<f64>) -> [f64; 3] {
    let (w, h) = (frame.width as f64, frame.height as f64);
    let x = if p.x.is_finite() {
        p.x.clamp(0.0, w - 1.0)
    } else {
        0.0
    };
    let y = if p.y.is_finite() {
        p.y.clamp(0.0, h - 1.0)
    } else {
        0.0
    };
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (ax, ay) = (x - f64::from(x0), y - f64::from(y0));
    let get = |u: u32, v: u32| {
        frame
            .pixel(u.min(frame.width - 1), v.min(frame.height - 1))
            .map_or([0.0; 3], |c| {
                [f64::from(c[0]), f64::from(c[1]), f64::from(c[2])]
            })
    };
    let (a, b, c, d) = (
        get(x0, y0),
        get(x0 + 1, y0),
        get(x0, y0 + 1),
        get(x0 + 1, y0 + 1),
    );
    let mut out = [0.0; 3];
    for k in 0..3 {
        let top = a[k] + (b[k] - a[k]) * ax;
        let bottom = c[k] + (d[k] - c[k]) * ax;
        out[k] = top + (bottom - top) * ay;
    }
    out
}
