//! Projective data association (Blais & Levine 1995; KinectFusion, Newcombe et al.
//! 2011, Sec. 3.5): a source point is moved by the current pose estimate into each
//! target scan, projected through the target's lidar model into its range grid, and
//! paired with the point stored at that pixel: O(1) per point, no search structure.
//! Each pair gives a point-to-plane residual (Chen & Medioni 1992); the
//! photometric term observes the same pairs in the EO images (`photometric`).

use nalgebra::{Matrix3, Vector2, Vector3};
use texel::{PinholeCamera, Pose};

use super::pyramid::{GridProjector, HAS_NORMAL, HAS_POINT, Level};

/// Points nearer the lidar plane than this (metres) do not project.
const MIN_PROJECT_DEPTH_M: f64 = 1.0e-9;

/// The lidar camera model for the inner loop: the projection is the camera's own
/// (`texel::PinholeCamera::normalized_to_pixel`, the same arithmetic as
/// `PinholeCamera::project`), with the distortion's domain bound computed once and the
/// division by depth done as one reciprocal for both coordinates.
#[derive(Debug, Clone, Copy)]
struct Projection<'a> {
    camera: &'a PinholeCamera,
    /// Normalised radius squared beyond which the distortion model is not used.
    max_r2: f64,
}

impl<'a> Projection<'a> {
    fn new(projector: &'a GridProjector) -> Self {
        Self {
            camera: projector.camera(),
            max_r2: projector.max_radius_squared().unwrap_or(f64::INFINITY),
        }
    }

    /// The full-resolution pixel of a lidar-frame point; `None` behind the sensor,
    /// outside the distortion domain, or not finite.
    #[inline(always)]
    fn pixel(&self, p: &Vector3<f64>) -> Option<(f64, f64)> {
        // Negated so that NaN is refused too.
        if !(p.z >= MIN_PROJECT_DEPTH_M) {
            return None;
        }
        let inv_z = 1.0 / p.z;
        let (x, y) = (p.x * inv_z, p.y * inv_z);
        if !(x * x + y * y < self.max_r2) {
            return None;
        }
        let pixel = self.camera.normalized_to_pixel(Vector2::new(x, y));
        Some((pixel.x, pixel.y))
    }
}

/// A target as the association sees it for one iteration.
pub struct TargetView<'a> {
    pub level: &'a Level,
    /// `target_from_source` as a rotation and translation.
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
    /// `target_lidar_from_source`, for projection.
    lidar_rotation: Matrix3<f64>,
    lidar_translation: Vector3<f64>,
    projection: Projection<'a>,
    /// Level pixels per full-resolution pixel.
    inv_scale: f64,
    width: f64,
    height: f64,
}

impl<'a> TargetView<'a> {
    pub fn new(level: &'a Level, projector: &'a GridProjector, target_from_source: &Pose) -> Self {
        let lidar_from_source = projector.lidar_from_scan() * target_from_source;
        Self {
            level,
            rotation: target_from_source
                .rotation
                .to_rotation_matrix()
                .into_inner(),
            translation: target_from_source.translation.vector,
            lidar_rotation: lidar_from_source.rotation.to_rotation_matrix().into_inner(),
            lidar_translation: lidar_from_source.translation.vector,
            projection: Projection::new(projector),
            inv_scale: 1.0 / level.scale,
            width: level.width as f64,
            height: level.height as f64,
        }
    }

    /// The target pixel (level index) a source point lands on, if it has a point.
    #[inline(always)]
    fn pixel_of(&self, p_source: &Vector3<f64>) -> Option<usize> {
        let p_lidar = self.lidar_rotation * p_source + self.lidar_translation;
        let (px, py) = self.projection.pixel(&p_lidar)?;
        // Full-resolution pixel centres at integers; a level pixel covers `scale` of
        // them, so its centre is at `scale·(u + 0.5) - 0.5` and the nearest level pixel
        // is `floor((x + 0.5) / scale)`. The comparisons refuse NaN as well.
        let u = (px + 0.5) * self.inv_scale;
        let v = (py + 0.5) * self.inv_scale;
        if !(u >= 0.0 && v >= 0.0 && u < self.width && v < self.height) {
            return None;
        }
        // Non-negative: truncation is the floor.
        let index = v as usize * self.level.width + u as usize;
        (self.level.flags.get(index).copied().unwrap_or(0) & HAS_POINT != 0).then_some(index)
    }
}

/// Gates a pair must pass.
#[derive(Debug, Clone, Copy)]
pub struct Gates {
    pub max_distance_m: f64,
    pub min_normal_cosine: f64,
}

/// One source point's pairing.
#[derive(Debug, Clone, Copy)]
pub struct Pair {
    pub target: usize,
    /// Target pixel index at the level.
    pub index: usize,
    /// The source point in the target frame.
    pub p_target: Vector3<f64>,
    pub q: Vector3<f64>,
    pub n: Vector3<f64>,
}

/// The outcome of associating one source point.
pub enum Association {
    /// Landed on no target return.
    Outside,
    /// Landed on a return, but every candidate failed a gate.
    Rejected,
    Paired(Pair),
}

/// Associates one source point (with its normal) against every target and keeps the
/// nearest pair that passes the gates (ties: the earlier target).
#[inline]
pub fn associate(
    p_source: &Vector3<f64>,
    n_source: &Vector3<f64>,
    targets: &[TargetView<'_>],
    gates: &Gates,
) -> Association {
    let mut landed = false;
    let mut best: Option<(f64, Pair)> = None;
    let max_d2 = gates.max_distance_m * gates.max_distance_m;
    for (k, target) in targets.iter().enumerate() {
        let Some(index) = target.pixel_of(p_source) else {
            continue;
        };
        landed = true;
        let level = target.level;
        if level.flags[index] & HAS_NORMAL == 0 {
            continue;
        }
        let p_target = target.rotation * p_source + target.translation;
        let q = level.point(index);
        let d2 = (p_target - q).norm_squared();
        if !(d2 <= max_d2) || best.as_ref().is_some_and(|(b, _)| *b <= d2) {
            continue;
        }
        let n = level.normal(index);
        if (target.rotation * n_source).dot(&n) < gates.min_normal_cosine {
            continue;
        }
        best = Some((
            d2,
            Pair {
                target: k,
                index,
                p_target,
                q,
                n,
            },
        ));
    }
    match (best, landed) {
        (Some((_, pair)), _) => Association::Paired(pair),
        (None, true) => Association::Rejected,
        (None, false) => Association::Outside,
    }
}

/// Point-to-plane residual `n·(T p - q)` and its Jacobian with respect to a right
/// perturbation of the source pose, `[p × m, m]` with `m = Rᵀ n` (Chen & Medioni 1992;
/// linearised as in Low 2004).
#[inline]
pub fn point_to_plane(
    pair: &Pair,
    p_source: &Vector3<f64>,
    rotation: &Matrix3<f64>,
) -> (f64, [f64; 6]) {
    let r = pair.n.dot(&(pair.p_target - pair.q));
    let m = rotation.tr_mul(&pair.n);
    let c = p_source.cross(&m);
    (r, [c.x, c.y, c.z, m.x, m.y, m.z])
}
