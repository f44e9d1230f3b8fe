//! Small analytic scenes for tests and benchmarks: planes and boxes with procedural
//! checkerboards, seen by an ideal texel camera. Range frames and EO images are
//! computed exactly (ray against plane / box), then fused with `texel::fuse`, so every
//! scan is a real `TexelScan`. Each scan gets its own exposure tint so that the
//! rendering modes differ visibly. (This is not the simulator: no noise, no optics.)

use std::sync::Arc;

use nalgebra::{Matrix3, Point3, Rotation3, UnitQuaternion, Vector2, Vector3};
use texel::model::{Model, ModelEvent};
use texel::{
    EoFrame, FuseConfig, PinholeCamera, Pose, RangeFrame, RangeNoise, Sensor, SensorModel,
    TexelScan,
};

/// A surface of the scene.
#[derive(Debug, Clone, Copy)]
pub enum Shape {
    /// The plane `normal · x = offset` (both sides).
    Plane { normal: [f64; 3], offset: f64 },
    /// An axis-aligned box.
    Box { min: [f64; 3], max: [f64; 3] },
}

#[derive(Debug, Clone, Copy)]
pub struct Surface {
    pub shape: Shape,
    /// Checker square size, metres.
    pub checker_m: f64,
    pub colour_a: [u8; 3],
    pub colour_b: [u8; 3],
}

#[derive(Debug, Clone, Default)]
pub struct Scene {
    pub surfaces: Vec<Surface>,
}

impl Scene {
    /// The nearest hit along a unit ray: distance and colour.
    pub fn cast(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<(f64, [u8; 3])> {
        let mut best: Option<(f64, [u8; 3])> = None;
        for s in &self.surfaces {
            if let Some(t) = hit(&s.shape, origin, dir)
                && best.is_none_or(|(bt, _)| t < bt)
            {
                best = Some((t, checker(s, &(origin + dir * t))));
            }
        }
        best
    }
}

fn hit(shape: &Shape, o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
    match *shape {
        Shape::Plane { normal, offset } => {
            let n = Vector3::from(normal);
            let denom = n.dot(d);
            if denom.abs() < 1e-12 {
                return None;
            }
            let t = (offset - n.dot(&o.coords)) / denom;
            (t > 1e-9).then_some(t)
        }
        Shape::Box { min, max } => {
            let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
            for k in 0..3 {
                if d[k].abs() < 1e-15 {
                    if o[k] < min[k] || o[k] > max[k] {
                        return None;
                    }
                    continue;
                }
                let a = (min[k] - o[k]) / d[k];
                let b = (max[k] - o[k]) / d[k];
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
            }
            if t1 < t0 || t1 <= 1e-9 {
                return None;
            }
            Some(if t0 > 1e-9 { t0 } else { t1 })
        }
    }
}

fn checker(s: &Surface, p: &Point3<f64>) -> [u8; 3] {
    // A 3D checkerboard, offset so no face of the scenes lies on a square boundary.
    let c = |v: f64, off: f64| ((v + off) / s.checker_m).floor() as i64;
    if (c(p.x, 0.013) + c(p.y, 0.017) + c(p.z, 0.011)).rem_euclid(2) == 0 {
        s.colour_a
    } else {
        s.colour_b
    }
}

/// The texel camera of the test scenes: a 48x36 lidar and a 160x120 EO camera
/// sharing one centre, noise sigma 1 cm.
pub fn test_sensor() -> Sensor {
    sensor(48, 36, 160, 120)
}

/// An ideal co-boresighted texel camera of the given resolutions (52 degrees vertical).
pub fn sensor(lidar_w: u32, lidar_h: u32, eo_w: u32, eo_h: u32) -> Sensor {
    let camera = |w, h| {
        PinholeCamera::from_vertical_fov(w, h, 52.0).unwrap_or_else(|_| PinholeCamera {
            width: w,
            height: h,
            fx: f64::from(h),
            fy: f64::from(h),
            cx: f64::from(w) / 2.0 - 0.5,
            cy: f64::from(h) / 2.0 - 0.5,
            skew: 0.0,
            distortion: texel::Distortion::None,
        })
    };
    Sensor::new(SensorModel {
        name: "analytic".into(),
        lidar: camera(lidar_w, lidar_h),
        eo: camera(eo_w, eo_h),
        eo_from_lidar: Pose::identity(),
        range_noise: RangeNoise {
            sigma_m: 0.01,
            sigma_per_m: 0.0,
        },
        range_bias_m: 0.0,
        min_range_m: 0.1,
        max_range_m: 100.0,
        eo_response: None,
    })
}

/// A camera pose at `eye` looking at `target` (EO frame: x right, y down, z forward;
/// world "down" is +y).
pub fn look_at(eye: [f64; 3], target: [f64; 3]) -> Pose {
    let z = (Vector3::from(target) - Vector3::from(eye)).normalize();
    let down = Vector3::y();
    let x = down.cross(&z);
    let x = if x.norm() < 1e-9 {
        Vector3::x()
    } else {
        x.normalize()
    };
    let y = z.cross(&x);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Pose::from_parts(
        nalgebra::Translation3::from(Vector3::from(eye)),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

/// The range frame and EO image the texel camera at `world_from_eo` sees.
pub fn frames(
    scene: &Scene,
    sensor: &Sensor,
    world_from_eo: &Pose,
    tint: [f32; 3],
    seq: u32,
) -> (RangeFrame, EoFrame) {
    let origin = Point3::from(world_from_eo.translation.vector);
    let lidar = &sensor.model.lidar;
    let world_from_lidar = world_from_eo * sensor.model.eo_from_lidar;
    let mut range = RangeFrame::empty(lidar.width, lidar.height, u64::from(seq) * 100_000_000, seq);
    for v in 0..lidar.height {
        for u in 0..lidar.width {
            let Ok(ray) = lidar.unproject_ray(Vector2::new(f64::from(u), f64::from(v))) else {
                continue;
            };
            let dir = world_from_lidar.rotation * ray;
            let o = Point3::from(world_from_lidar.translation.vector);
            if let Some((t, _)) = scene.cast(&o, &dir) {
                range.ranges_m[(v * lidar.width + u) as usize] = t as f32;
            }
        }
    }
    let eo = &sensor.model.eo;
    let mut rgb = vec![0u8; (eo.width * eo.height * 3) as usize];
    for v in 0..eo.height {
        for u in 0..eo.width {
            let Ok(ray) = eo.unproject_ray(Vector2::new(f64::from(u), f64::from(v))) else {
                continue;
            };
            let dir = world_from_eo.rotation * ray;
            if let Some((_, c)) = scene.cast(&origin, &dir) {
                let i = 3 * (v * eo.width + u) as usize;
                for k in 0..3 {
                    rgb[i + k] = (f32::from(c[k]) * tint[k]).round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
    let eo_frame = EoFrame {
        width: eo.width,
        height: eo.height,
        rgb,
        timestamp_ns: range.timestamp_ns,
        exposure: None,
    };
    (range, eo_frame)
}

/// Fuses the frames a texel camera at `world_from_eo` sees into a scan.
pub fn scan(
    scene: &Scene,
    sensor: &Sensor,
    world_from_eo: &Pose,
    tint: [f32; 3],
    seq: u32,
) -> TexelScan {
    let (range, eo) = frames(scene, sensor, world_from_eo, tint, seq);
    // The frames are made for this sensor, so sizes always agree.
    texel::fuse(&range, eo, sensor, &FuseConfig::default()).unwrap_or_else(|_| empty_scan(sensor))
}

fn empty_scan(sensor: &Sensor) -> TexelScan {
    TexelScan {
        timestamp_ns: 0,
        seq: 0,
        grid_width: 0,
        grid_height: 0,
        vertices: vec![],
        tex_coords: vec![],
        vertex_textured: vec![],
        vertex_pixel: vec![],
        pixel_vertex: vec![],
        triangles: vec![],
        triangle_accuracy: vec![],
        triangle_flags: vec![],
        texture: std::sync::Arc::new(EoFrame {
            width: 1,
            height: 1,
            rgb: vec![0; 3],
            timestamp_ns: 0,
            exposure: None,
        }),
        cop_m: [0.0; 3],
        scan_from_lidar: Pose::identity(),
        range_noise: sensor.model.range_noise,
    }
}

/// A distinct exposure tint per scan.
pub fn tint(i: u32) -> [f32; 3] {
    const TINTS: [[f32; 3]; 6] = [
        [1.0, 1.0, 1.0],
        [0.85, 0.95, 1.15],
        [1.15, 0.95, 0.8],
        [0.9, 1.15, 0.9],
        [1.1, 0.85, 1.1],
        [0.8, 0.8, 0.8],
    ];
    TINTS[i as usize % TINTS.len()]
}

/// A wall (z = 6.05) with a box in front of it (front face at z = 3.1): the paper's
/// Fig. 8 set-up.
pub fn box_scene() -> Scene {
    Scene {
        surfaces: vec![
            Surface {
                shape: Shape::Plane {
                    normal: [0.0, 0.0, 1.0],
                    offset: 6.05,
                },
                checker_m: 0.5,
                colour_a: [230, 230, 220],
                colour_b: [40, 60, 150],
            },
            Surface {
                shape: Shape::Box {
                    min: [-0.55, -0.55, 3.1],
                    max: [0.55, 0.55, 4.2],
                },
                checker_m: 0.25,
                colour_a: [220, 60, 40],
                colour_b: [250, 220, 60],
            },
        ],
    }
}

/// Adds scans to a model at the given poses, each under `offset` (world_from_scan =
/// offset * pose).
pub fn model_of(scene: &Scene, sensor: &Sensor, poses: &[Pose], offset: &Pose) -> Model {
    let mut model = Model::new();
    for (i, pose) in poses.iter().enumerate() {
        let s = scan(scene, sensor, pose, tint(i as u32), i as u32);
        let _ = model.apply(ModelEvent::ScanAdded {
            id: model.next_id(),
            scan: Arc::new(s),
            world_from_scan: offset * pose,
        });
    }
    model
}

/// The acquisition poses of the box scene: front, right and left of the box.
pub fn box_scene_poses() -> Vec<Pose> {
    vec![
        look_at([0.0, -0.3, -1.0], [0.0, 0.0, 5.0]),
        look_at([2.6, -0.2, 1.6], [0.0, 0.0, 6.0]),
        look_at([-2.4, -0.4, 1.0], [0.0, 0.0, 6.0]),
    ]
}

/// A long wall (z = 5.05) scanned by `n` cameras one metre apart along x, all looking
/// at it: a model whose scans a wide view mostly culls.
pub fn corridor(sensor: &Sensor, n: u32) -> Model {
    let scene = Scene {
        surfaces: vec![Surface {
            shape: Shape::Plane {
                normal: [0.0, 0.0, 1.0],
                offset: 5.05,
            },
            checker_m: 0.4,
            colour_a: [200, 190, 170],
            colour_b: [50, 90, 60],
        }],
    };
    let poses: Vec<Pose> = (0..n)
        .map(|i| {
            let x = f64::from(i);
            look_at([x, 0.0, 0.0], [x + 0.3, 0.1, 5.05])
        })
        .collect();
    model_of(&scene, sensor, &poses, &Pose::identity())
}
