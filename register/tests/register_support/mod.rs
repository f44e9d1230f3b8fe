//! Analytic scenes for registration tests: boxes and planes ray-cast exactly into
//! lidar range frames and EO images (procedural texture), then fused into scans, so
//! true poses are known exactly.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::sync::Arc;

use nalgebra::{Matrix3, Point3, Rotation3, UnitQuaternion, Vector2, Vector3};
use texel::{
    EoFrame, FuseConfig, PinholeCamera, Pose, RangeFrame, RangeNoise, Sensor, SensorModel,
    TexelScan, fuse,
};

/// A surface of the scene.
#[derive(Debug, Clone, Copy)]
pub enum Shape {
    /// An axis-aligned box; rays from inside hit its inner walls.
    Box {
        min: Vector3<f64>,
        max: Vector3<f64>,
    },
    /// The plane `n·x = d`.
    Plane { n: Vector3<f64>, d: f64 },
}

#[derive(Debug, Clone, Default)]
pub struct Scene {
    pub shapes: Vec<Shape>,
}

impl Scene {
    /// A 8 x 6 x 3 m room (floor at z = 0) with three boxes on the floor.
    pub fn room() -> Self {
        let b = |min: [f64; 3], max: [f64; 3]| Shape::Box {
            min: Vector3::from(min),
            max: Vector3::from(max),
        };
        Self {
            shapes: vec![
                b([-4.0, -3.0, 0.0], [4.0, 3.0, 3.0]),
                b([1.5, -1.0, 0.0], [2.3, -0.2, 0.9]),
                b([0.5, 1.2, 0.0], [1.1, 2.0, 1.4]),
                b([2.5, 0.8, 0.0], [3.2, 1.6, 0.5]),
                b([-2.5, -2.2, 0.0], [-1.5, -1.2, 1.1]),
            ],
        }
    }

    /// One infinite plane: the wall x = 3.
    pub fn plane() -> Self {
        Self {
            shapes: vec![Shape::Plane {
                n: Vector3::x(),
                d: 3.0,
            }],
        }
    }

    /// An infinite corridor along x: walls at y = ±1, floor z = 0, ceiling z = 2.5.
    pub fn corridor() -> Self {
        let p = |n: [f64; 3], d: f64| Shape::Plane {
            n: Vector3::from(n),
            d,
        };
        Self {
            shapes: vec![
                p([0.0, 1.0, 0.0], 1.0),
                p([0.0, 1.0, 0.0], -1.0),
                p([0.0, 0.0, 1.0], 0.0),
                p([0.0, 0.0, 1.0], 2.5),
            ],
        }
    }

    /// Nearest hit along a unit ray, `t > 1e-6`.
    pub fn cast(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        let mut best: Option<f64> = None;
        let mut offer = |t: f64| {
            if t > 1e-6 && best.is_none_or(|b| t < b) {
                best = Some(t);
            }
        };
        for shape in &self.shapes {
            match *shape {
                Shape::Plane { n, d } => {
                    let denom = n.dot(dir);
                    if denom.abs() > 1e-12 {
                        offer((d - n.dot(origin)) / denom);
                    }
                }
                Shape::Box { min, max } => {
                    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
                    for k in 0..3 {
                        if dir[k].abs() < 1e-15 {
                            if origin[k] < min[k] || origin[k] > max[k] {
                                t0 = f64::INFINITY;
                            }
                            continue;
                        }
                        let a = (min[k] - origin[k]) / dir[k];
                        let b = (max[k] - origin[k]) / dir[k];
                        t0 = t0.max(a.min(b));
                        t1 = t1.min(a.max(b));
                    }
                    if t0 <= t1 {
                        if t0 > 1e-6 {
                            offer(t0);
                        } else {
                            offer(t1);
                        }
                    }
                }
            }
        }
        best
    }
}

/// Procedural albedo in [0, 1]: smooth stripes and blobs, so that intensity has
/// gradients everywhere.
pub fn albedo(p: &Vector3<f64>) -> f64 {
    let a = (3.1 * p.x + 1.3 * p.y).sin() * (2.3 * p.z + 0.7 * p.x).cos();
    let b = (5.0 * p.y - 2.1 * p.z).sin();
    (0.5 + 0.3 * a + 0.15 * b).clamp(0.0, 1.0)
}

/// A deterministic generator of standard normal samples (xorshift + Box-Muller).
pub struct Gaussian(u64);

impl Gaussian {
    pub fn new(seed: u64) -> Self {
        Self(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }

    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    pub fn sample(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// The test texel camera: a `w x h` lidar with a 60° vertical field, an EO camera
/// twice its resolution, 2 cm apart.
pub fn sensor(w: u32, h: u32, sigma_m: f64) -> Sensor {
    Sensor::new(SensorModel {
        name: "registration test".into(),
        lidar: PinholeCamera::from_vertical_fov(w, h, 60.0).unwrap(),
        eo: PinholeCamera::from_vertical_fov(2 * w, 2 * h, 66.0).unwrap(),
        eo_from_lidar: Pose::translation(0.02, 0.0, 0.0),
        range_noise: RangeNoise {
            sigma_m: sigma_m.max(1e-4),
            sigma_per_m: 0.0,
        },
        range_bias_m: 0.0,
        min_range_m: 0.1,
        max_range_m: 30.0,
        eo_response: None,
    })
}

/// `world_from_eo` for a camera at `eye` looking at `target` with world +z up.
pub fn look_at(eye: [f64; 3], target: [f64; 3]) -> Pose {
    let eye = Vector3::from(eye);
    let z = (Vector3::from(target) - eye).normalize();
    let mut x = z.cross(&Vector3::z());
    if x.norm() < 1e-9 {
        x = Vector3::x();
    }
    let x = x.normalize();
    let y = z.cross(&x);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Pose::from_parts(eye.into(), UnitQuaternion::from_rotation_matrix(&r))
}

/// Renders the texel frame a camera at `world_from_eo` sees, with Gaussian range
/// noise of `sigma_m` (0 for none).
pub fn render(
    scene: &Scene,
    sensor: &Sensor,
    world_from_eo: &Pose,
    sigma_m: f64,
    seed: u64,
) -> (RangeFrame, EoFrame) {
    render_with(scene, sensor, world_from_eo, sigma_m, seed, &albedo, 1.0)
}

/// [`render`] with the surface's albedo given and the EO exposure scaled by `gain`
/// (8-bit values clip at 255).
pub fn render_with(
    scene: &Scene,
    sensor: &Sensor,
    world_from_eo: &Pose,
    sigma_m: f64,
    seed: u64,
    albedo: &dyn Fn(&Vector3<f64>) -> f64,
    gain: f64,
) -> (RangeFrame, EoFrame) {
    let m = &sensor.model;
    let world_from_lidar = world_from_eo * m.eo_from_lidar;
    let mut noise = Gaussian::new(seed);
    let mut range = RangeFrame::empty(m.lidar.width, m.lidar.height, seed, seed as u32);
    let origin = world_from_lidar.translation.vector;
    for v in 0..m.lidar.height {
        for u in 0..m.lidar.width {
            let ray = m
                .lidar
                .unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                .unwrap();
            let dir = world_from_lidar.rotation * ray;
            if let Some(t) = scene.cast(&origin, &dir)
                && t < m.max_range_m
            {
                let r = t + sigma_m * noise.sample();
                range.ranges_m[(v * m.lidar.width + u) as usize] = r as f32;
            }
        }
    }
    let eo_origin = world_from_eo.translation.vector;
    let mut rgb = Vec::with_capacity((m.eo.width * m.eo.height * 3) as usize);
    for v in 0..m.eo.height {
        for u in 0..m.eo.width {
            let ray =
                m.eo.unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                    .unwrap();
            let dir = world_from_eo.rotation * ray;
            let c = scene
                .cast(&eo_origin, &dir)
                .map_or(0.0, |t| albedo(&(eo_origin + dir * t)));
            let g = (gain * c * 255.0).round().clamp(0.0, 255.0) as u8;
            rgb.extend_from_slice(&[g, g, g]);
        }
    }
    let eo = EoFrame {
        width: m.eo.width,
        height: m.eo.height,
        rgb,
        timestamp_ns: seed,
        exposure: None,
    };
    (range, eo)
}

/// Renders and fuses one scan.
pub fn scan(
    scene: &Scene,
    sensor: &Sensor,
    world_from_eo: &Pose,
    sigma_m: f64,
    seed: u64,
) -> Arc<TexelScan> {
    let (range, eo) = render(scene, sensor, world_from_eo, sigma_m, seed);
    Arc::new(fuse(&range, eo, sensor, &FuseConfig::default()).unwrap())
}

/// Renders and fuses one scan with the surface's albedo given and the exposure
/// scaled by `gain`.
pub fn scan_with(
    scene: &Scene,
    sensor: &Sensor,
    world_from_eo: &Pose,
    seed: u64,
    albedo: &dyn Fn(&Vector3<f64>) -> f64,
    gain: f64,
) -> Arc<TexelScan> {
    let (range, eo) = render_with(scene, sensor, world_from_eo, 0.003, seed, albedo, gain);
    Arc::new(fuse(&range, eo, sensor, &FuseConfig::default()).unwrap())
}

/// A non-repeating texture with detail at 5 to 30 cm (posters, plaster, tiles):
/// sinusoids of incommensurate frequencies in several directions.
pub fn speckle(p: &Vector3<f64>) -> f64 {
    let waves = [
        (23.0, 7.1, 3.3, 0.0),
        (-11.3, 29.0, 5.9, 1.1),
        (41.7, -13.9, 17.3, 2.3),
        (5.3, 19.1, -37.7, 0.7),
        (61.1, 3.7, 11.9, 1.9),
    ];
    let sum: f64 = waves
        .iter()
        .map(|&(a, b, c, phase)| (a * p.x + b * p.y + c * p.z + phase).sin())
        .sum();
    (0.5 + 0.08 * sum).clamp(0.05, 0.95)
}

/// The registrar's pyramid of a scan under the default settings: range levels and
/// the EO pyramid.
pub fn eo_pyramid(scan: Arc<TexelScan>, s: &Sensor) -> texel_register::ScanPyramid {
    let defaults = texel_register::AlignConfig::default();
    texel_register::ScanPyramid::build_with(
        scan,
        &s.model.lidar,
        Some(&Arc::new(s.model.eo.clone())),
        texel_register::PyramidOptions {
            levels: defaults.pyramid_levels,
            eo_levels: defaults.photometric.eo_levels,
            first_eo_level: defaults.photometric.finest_eo_level,
        },
    )
}

/// A pose perturbation: `rot_deg` about `axis`, `trans_m` along `dir`.
pub fn perturbation(rot_deg: f64, axis: [f64; 3], trans_m: f64, dir: [f64; 3]) -> Pose {
    let axis = Vector3::from(axis).normalize();
    let dir = Vector3::from(dir).normalize();
    Pose::from_parts(
        (dir * trans_m).into(),
        UnitQuaternion::from_scaled_axis(axis * rot_deg.to_radians()),
    )
}

/// Rotation (degrees) and translation (millimetres) between two poses.
pub fn error_deg_mm(a: &Pose, b: &Pose) -> (f64, f64) {
    let (r, t) = texel::pose::pose_difference(a, b);
    (r.to_degrees(), t * 1000.0)
}

pub fn point(p: [f64; 3]) -> Point3<f64> {
    Point3::from(Vector3::from(p))
}
