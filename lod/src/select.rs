//! Choosing the tiles to draw for a view (Liu 2014 §4.3): walk the tree from its top
//! tiles, refine a tile while its projected geometric error exceeds a pixel threshold
//! (modulated towards the screen's centre, §4.3.1, with hysteresis against flicker),
//! cull tiles outside the frustum (§4.3.4), and replace a parent only once all its
//! children are resident, so the drawn set never has a hole (§4.3.2). Loading is the
//! caller's: selection only says what it wants, largest error first.

use std::collections::BTreeSet;

use nalgebra::{Matrix4, Vector4};

use crate::tree::TileId;

/// What selection needs of a tile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileInfo {
    pub bounds_min_m: [f64; 3],
    pub bounds_max_m: [f64; 3],
    pub geometric_error_m: f64,
}

/// The tree as selection sees it: its top tiles, which tiles exist and their bounds
/// and errors.
pub trait TileIndex {
    fn roots(&self) -> Vec<TileId>;
    fn tile(&self, id: TileId) -> Option<TileInfo>;
}

impl TileIndex for crate::build::Hierarchy {
    fn roots(&self) -> Vec<TileId> {
        crate::build::Hierarchy::roots(self)
    }

    fn tile(&self, id: TileId) -> Option<TileInfo> {
        self.nodes.get(&id).map(|n| TileInfo {
            bounds_min_m: n.bounds_min_m,
            bounds_max_m: n.bounds_max_m,
            geometric_error_m: n.geometric_error_m,
        })
    }
}

/// The view: where the eye is and how it projects.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    pub eye_m: [f64; 3],
    /// Clip from eye-relative world coordinates (world minus `eye_m`): view and
    /// projection in f64, so a model 5,000 km out culls as well as one at the origin.
    pub clip_from_eye: Matrix4<f64>,
    pub viewport_height_px: f64,
    /// Vertical field of view, radians.
    pub fov_y_rad: f64,
}

/// A perspective camera's lens and image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lens {
    /// Vertical field of view, radians.
    pub fov_y_rad: f64,
    /// Width over height.
    pub aspect: f64,
    pub near_m: f64,
    pub far_m: f64,
    pub viewport_height_px: f64,
}

impl View {
    /// A perspective view from `eye_m` towards `target_m` with `up` (world), in wgpu's
    /// clip convention (depth 0 at `near_m`, 1 at `far_m`). `None` for a degenerate
    /// view: target at the eye, up along the view, or bad angles and distances.
    pub fn looking_at(
        eye_m: [f64; 3],
        target_m: [f64; 3],
        up: [f64; 3],
        lens: &Lens,
    ) -> Option<View> {
        use nalgebra::Vector3;
        let Lens {
            fov_y_rad,
            aspect,
            near_m,
            far_m,
            viewport_height_px,
        } = *lens;
        let forward =
            Vector3::from([0, 1, 2].map(|a| target_m[a] - eye_m[a])).try_normalize(1e-12)?;
        let right = forward.cross(&Vector3::from(up)).try_normalize(1e-12)?;
        let true_up = right.cross(&forward);
        let ok = fov_y_rad > 1e-6
            && fov_y_rad < std::f64::consts::PI - 1e-6
            && aspect > 1e-6
            && aspect.is_finite()
            && near_m > 0.0
            && far_m > near_m
            && far_m.is_finite();
        if !ok {
            return None;
        }
        let view = Matrix4::new(
            right.x, right.y, right.z, 0.0, true_up.x, true_up.y, true_up.z, 0.0, -forward.x,
            -forward.y, -forward.z, 0.0, 0.0, 0.0, 0.0, 1.0,
        );
        let f = 1.0 / (0.5 * fov_y_rad).tan();
        let projection = Matrix4::new(
            f / aspect,
            0.0,
            0.0,
            0.0,
            0.0,
            f,
            0.0,
            0.0,
            0.0,
            0.0,
            far_m / (near_m - far_m),
            near_m * far_m / (near_m - far_m),
            0.0,
            0.0,
            -1.0,
            0.0,
        );
        Some(View {
            eye_m,
            clip_from_eye: projection * view,
            viewport_height_px,
            fov_y_rad,
        })
    }
}

/// Selection's knobs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SelectConfig {
    /// Refine while a tile's projected error exceeds this many pixels.
    pub max_error_px: f64,
    /// How much less detail the screen's edge gets than its centre: at the edge the
    /// projected error counts `1 - centre_weight` as much (Liu Fig. 4.3).
    pub centre_weight: f64,
    /// A refined tile stays refined until its error falls below
    /// `max_error_px / hysteresis`: no flicker at the threshold.
    pub hysteresis: f64,
}

impl Default for SelectConfig {
    fn default() -> Self {
        Self {
            max_error_px: 2.0,
            centre_weight: 0.5,
            hysteresis: 1.25,
        }
    }
}

/// The outcome for one view.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Selection {
    /// Tiles to draw: resident, inside the frustum, none inside another.
    pub draw: Vec<TileId>,
    /// Tiles wanted but not resident, most needed (largest projected error) first.
    pub wanted: Vec<TileId>,
    /// Tiles refined this time (feed back as `refined_before` next time).
    pub refined: BTreeSet<TileId>,
    /// Finest-level tiles (drawn, in `draw`) whose error still exceeds the threshold:
    /// the view wants more than the tree holds, so the scans under them should be
    /// drawn as well (Liu 2014 §3: the scans are the tree's leaves). Also in
    /// `refined`, so hysteresis keeps them there.
    pub below_finest: BTreeSet<TileId>,
}

/// Selects the tiles to draw for `view`. `resident` says which tiles are loaded;
/// `refined_before` is the previous selection's `refined`, for hysteresis.
pub fn select(
    index: &impl TileIndex,
    view: &View,
    resident: &dyn Fn(TileId) -> bool,
    refined_before: &BTreeSet<TileId>,
    config: &SelectConfig,
) -> Selection {
    let mut out = Selection::default();
    let mut wanted: Vec<(f64, TileId)> = Vec::new();
    // The top tiles have no parent to stand in for them: until one is resident its
    // ground stays empty (only while a viewer starts).
    let mut stack = Vec::new();
    for id in index.roots() {
        let Some(info) = index.tile(id) else {
            continue;
        };
        if resident(id) {
            stack.push((id, info));
        } else if in_frustum(view, &info) {
            wanted.push((f64::INFINITY, id));
        }
    }
    while let Some((id, info)) = stack.pop() {
        if !in_frustum(view, &info) {
            continue;
        }
        let error_px = projected_error_px(view, &info, config.centre_weight);
        let threshold = if refined_before.contains(&id) {
            config.max_error_px / config.hysteresis.max(1.0)
        } else {
            config.max_error_px
        };
        let children: Vec<(TileId, TileInfo)> = id
            .children()
            .into_iter()
            .flatten()
            .filter_map(|c| index.tile(c).map(|i| (c, i)))
            .collect();
        if error_px <= threshold || children.is_empty() {
            if error_px > threshold && id.lod == 0 {
                out.below_finest.insert(id);
                out.refined.insert(id);
            }
            out.draw.push(id);
            continue;
        }
        // Liu §4.3.2: the parent stays until every child in view is in, then they all
        // replace it (children out of view are culled below and never wanted).
        let missing: Vec<TileId> = children
            .iter()
            .filter(|(c, info)| !resident(*c) && in_frustum(view, info))
            .map(|(c, _)| *c)
            .collect();
        if missing.is_empty() {
            out.refined.insert(id);
            stack.extend(children);
        } else {
            out.draw.push(id);
            wanted.extend(missing.into_iter().map(|c| (error_px, c)));
        }
    }
    wanted.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    out.wanted = wanted.into_iter().map(|(_, id)| id).collect();
    out.draw.sort();
    out
}

/// The tile's geometric error in pixels at its nearest point (infinite with the eye
/// inside its bounds), weighted down away from the screen's centre.
pub fn projected_error_px(view: &View, info: &TileInfo, centre_weight: f64) -> f64 {
    let nearest =
        [0, 1, 2].map(|a| view.eye_m[a].clamp(info.bounds_min_m[a], info.bounds_max_m[a]));
    let distance = (0..3)
        .map(|a| (nearest[a] - view.eye_m[a]).powi(2))
        .sum::<f64>()
        .sqrt();
    let error = info.geometric_error_m.max(0.0);
    // Guard: the eye inside the box (distance 0) or a degenerate field of view.
    let half_fov_tan = (0.5 * view.fov_y_rad).tan();
    if distance < 1e-9 || half_fov_tan.is_nan() || half_fov_tan <= 1e-9 || !half_fov_tan.is_finite()
    {
        return if error > 0.0 { f64::INFINITY } else { 0.0 };
    }
    let px = error * view.viewport_height_px / (2.0 * distance * half_fov_tan);
    px * (1.0 - centre_weight.clamp(0.0, 1.0) * off_centre(view, info))
}

/// How far the tile's centre projects from the screen's centre: 0 at the centre, 1 at
/// a corner or beyond, 1 behind the eye.
fn off_centre(view: &View, info: &TileInfo) -> f64 {
    let c = [0, 1, 2].map(|a| 0.5 * (info.bounds_min_m[a] + info.bounds_max_m[a]) - view.eye_m[a]);
    let clip = view.clip_from_eye * Vector4::new(c[0], c[1], c[2], 1.0);
    if clip.w.is_nan() || clip.w <= 1e-9 {
        return 1.0;
    }
    let (x, y) = (clip.x / clip.w, clip.y / clip.w);
    ((x * x + y * y).sqrt() / std::f64::consts::SQRT_2).min(1.0)
}

/// False only when every corner of the box lies outside one clip plane.
pub fn in_frustum(view: &View, info: &TileInfo) -> bool {
    let corners: Vec<Vector4<f64>> = (0..8)
        .map(|k| {
            let pick = |a: usize| {
                if k >> a & 1 == 0 {
                    info.bounds_min_m[a]
                } else {
                    info.bounds_max_m[a]
                }
            };
            view.clip_from_eye
                * Vector4::new(
                    pick(0) - view.eye_m[0],
                    pick(1) - view.eye_m[1],
                    pick(2) - view.eye_m[2],
                    1.0,
                )
        })
        .collect();
    // Planes of the wgpu clip volume: -w ≤ x, y ≤ w, 0 ≤ z ≤ w.
    let planes: [fn(&Vector4<f64>) -> f64; 6] = [
        |p| p.w + p.x,
        |p| p.w - p.x,
        |p| p.w + p.y,
        |p| p.w - p.y,
        |p| p.z,
        |p| p.w - p.z,
    ];
    planes
        .iter()
        .all(|plane| corners.iter().any(|c| plane(c) >= 0.0))
}
