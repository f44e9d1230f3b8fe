//! The model made ready for view-dependent texture mapping: the merged surface fused
//! from every resident scan, the acquisition views chosen among the scans, and
//! `texel-vdtm`'s preprocessing (Debevec 1998 §5-7) run on them. Pure and synchronous:
//! the window and a live session run it on a worker thread.

use std::sync::Arc;

use nalgebra::Point3;
use texel::camera::PinholeCamera;
use texel::frames::EoFrame;
use texel::model::{Model, ScanId};
use texel::{Pose, TexelScan};
use texel_vdtm::{AcquisitionView, VdtmConfig, VdtmModel};

/// What the viewer's VDTM mode builds and from how much.
#[derive(Debug, Clone, PartialEq)]
pub struct VdtmViewConfig {
    /// The merged surface's finest voxel, metres (`tradeoffs surface`: at 0.05 m the
    /// vertices lie a median 1 mm and a 95th percentile 12 to 14 mm from the truth on
    /// `lab` and `courtyard`). A sparser lidar gets a coarser one: see
    /// [`surface_voxel_m`].
    pub voxel_m: f64,
    /// At most this many acquisition views: with more scans, every k-th is taken
    /// (evenly spread), so preprocessing time and texture memory stay bounded.
    pub max_views: usize,
    pub preprocessing: VdtmConfig,
}

impl Default for VdtmViewConfig {
    fn default() -> Self {
        Self {
            voxel_m: 0.05,
            // 128 images of 640 x 480 are 150 MiB of RGBA textures, and preprocessing
            // grows faster than linearly with the views (`tradeoffs vdtm-prep`).
            max_views: 128,
            preprocessing: VdtmConfig::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    #[error("the model holds no scan to build the merged surface from")]
    NoScans,
    #[error("the merged surface: {0}")]
    Surface(#[from] texel_lod::LodError),
    #[error("the merged surface is empty (the scans hold no surface at {voxel_m} m)")]
    EmptySurface { voxel_m: f64 },
    #[error("VDTM preprocessing: {0}")]
    Vdtm(#[from] texel_vdtm::VdtmError),
    #[error("max_views must be at least 1")]
    NoViews,
}

/// One acquisition view as the renderer needs it.
#[derive(Debug, Clone)]
pub struct PreparedView {
    pub scan: ScanId,
    /// The EO camera's optical frame in the world (the scan frame).
    pub world_from_eo: Pose,
    pub image: Arc<EoFrame>,
}

/// The model ready to draw: view `i` of `views` is the view id `i` of `model`.
#[derive(Debug, Clone)]
pub struct PreparedVdtm {
    pub model: VdtmModel,
    pub views: Vec<PreparedView>,
    pub camera: PinholeCamera,
    /// Scans the surface was fused from and the poses they had (to notice change).
    pub fused: Vec<(ScanId, Pose)>,
    /// Views left out because their image's size is not the camera's.
    pub skipped_views: usize,
    /// The voxel the merged surface was fused at, metres.
    pub voxel_m: f64,
}

/// Which resident scans become views: at most `max_views`, evenly spread.
fn chosen_views(n: usize, max_views: usize) -> Vec<usize> {
    if n <= max_views {
        return (0..n).collect();
    }
    // Spread: view j at the j-th fraction of the sequence, so the first and the last
    // scans are among them.
    (0..max_views)
        .map(|j| {
            if max_views == 1 {
                0
            } else {
                j * (n - 1) / (max_views - 1)
            }
        })
        .collect()
}

/// The recipe: the resident scans, the merged surface, the views, the preprocessing.
pub fn prepare(
    model: &Model,
    camera: &PinholeCamera,
    config: &VdtmViewConfig,
) -> Result<PreparedVdtm, PrepareError> {
    if config.max_views == 0 {
        return Err(PrepareError::NoViews);
    }
    // The scans this model holds, with the poses they are placed by now.
    let resident: Vec<(ScanId, Pose, Arc<TexelScan>)> = model
        .resident()
        .map(|(s, scan)| (s.id, s.world_from_scan, Arc::clone(scan)))
        .collect();
    if resident.is_empty() {
        return Err(PrepareError::NoScans);
    }
    // The merged surface from every scan (geometry gains from all of them).
    let voxel_m = surface_voxel_m(resident.iter().map(|(_, _, s)| s.as_ref()), config.voxel_m);
    let mesh = texel_lod::merged_surface(
        resident.iter().map(|(_, pose, scan)| (scan.as_ref(), pose)),
        voxel_m,
    )?;
    if mesh.triangle_count() == 0 {
        return Err(PrepareError::EmptySurface { voxel_m });
    }
    // The views: images of the camera's size only (the renderer's texture array holds
    // one size).
    let mut views = Vec::new();
    let mut skipped_views = 0;
    for i in chosen_views(resident.len(), config.max_views) {
        let Some((id, pose, scan)) = resident.get(i) else {
            continue;
        };
        let image = &scan.texture;
        if image.width != camera.width || image.height != camera.height {
            skipped_views += 1;
            continue;
        }
        views.push(PreparedView {
            scan: *id,
            world_from_eo: *pose,
            image: Arc::clone(image),
        });
    }
    let acquisition: Vec<AcquisitionView<'_>> = views
        .iter()
        .enumerate()
        .map(|(i, v)| AcquisitionView {
            id: u32::try_from(i).unwrap_or(u32::MAX),
            world_from_eo: v.world_from_eo,
            camera,
            image: Some(v.image.as_ref()),
        })
        .collect();
    // Debevec 1998 §5-7: visibility, hole filling, view maps.
    let prepared = VdtmModel::build(&mesh, &acquisition, &config.preprocessing)?;
    Ok(PreparedVdtm {
        model: prepared,
        views,
        camera: camera.clone(),
        fused: resident.iter().map(|(id, pose, _)| (*id, *pose)).collect(),
        skipped_views,
        voxel_m,
    })
}

/// Neighbouring lidar samples measured for the spacing, per scan (a bounded cost).
const SPACING_SAMPLES_PER_SCAN: usize = 2048;

/// The voxel the merged surface is fused at: `finest_m`, or twice the scans' median
/// spacing between neighbouring lidar samples where that is coarser. A TSDF voxel
/// with no sample near it stays unobserved, and marching cubes leaves a crack
/// there: with samples sparser than the voxels, a far wall breaks into strips.
pub fn surface_voxel_m<'a>(scans: impl IntoIterator<Item = &'a TexelScan>, finest_m: f64) -> f64 {
    let mut spacings = Vec::new();
    for scan in scans {
        let w = scan.grid_width as usize;
        let pixels = scan.pixel_vertex.len();
        let step = (pixels / SPACING_SAMPLES_PER_SCAN).max(1);
        for p in (0..pixels).step_by(step) {
            // The sample and its right-hand neighbour on the same row.
            if w == 0 || (p + 1) % w == 0 {
                continue;
            }
            let vertex = |q: usize| {
                let v = *scan.pixel_vertex.get(q)?;
                scan.vertices.get(v as usize)
            };
            if let (Some(a), Some(b)) = (vertex(p), vertex(p + 1)) {
                let d = (0..3)
                    .map(|k| f64::from(a[k] - b[k]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                if d.is_finite() {
                    spacings.push(d);
                }
            }
        }
    }
    if spacings.is_empty() {
        return finest_m;
    }
    spacings.sort_by(f64::total_cmp);
    let median = spacings[spacings.len() / 2];
    // Depth discontinuities give a few huge spacings; the median ignores them.
    finest_m.max(2.0 * median)
}

impl PreparedVdtm {
    /// Whether `model` still matches what this was built from: the same scans at the
    /// same poses (within `tolerance_m` and about `tolerance_m` over 10 m of rotation).
    pub fn matches(&self, model: &Model, tolerance_m: f64) -> bool {
        let now: Vec<(ScanId, Pose)> = model
            .resident()
            .map(|(s, _)| (s.id, s.world_from_scan))
            .collect();
        now.len() == self.fused.len()
            && now.iter().zip(&self.fused).all(|((a, pa), (b, pb))| {
                let moved = (pa.translation.vector - pb.translation.vector).norm();
                let turned = pa.rotation.angle_to(&pb.rotation);
                a == b && moved <= tolerance_m && turned * 10.0 <= tolerance_m
            })
    }

    /// The model's origin: positions on the GPU are relative to it.
    pub fn origin(&self) -> Point3<f64> {
        Point3::from(self.model.mesh.origin_m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_are_spread_over_the_whole_sequence() {
        assert_eq!(chosen_views(3, 8), vec![0, 1, 2]);
        let v = chosen_views(10, 4);
        assert_eq!(v, vec![0, 3, 6, 9]);
        assert_eq!(chosen_views(10, 1), vec![0]);
    }
}
