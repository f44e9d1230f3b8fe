//! Which scans to draw below the finest tiles ([`scans_below`]): per tile, the scans
//! view-dependent blending would pick at points spread over the tile's surface
//! (Killpack & Budge 2016 §3's point-of-view and range confidences, taken per point),
//! chosen greedily so that the few a tile may show cover as much of what the view
//! sees of it as they can. Scans acquired a frame apart see nearly the same ground:
//! ranking them at one point would spend every slot on such near-twins and leave the
//! rest of the tile to the coarser tile mesh.

use std::collections::BTreeSet;

use glam::DVec3;
use nalgebra::Point3;
use texel::Pose;
use texel::model::{ModelScan, ScanId};
use texel_lod::TileInfo;

use super::hybrid::HybridSettings;
use crate::camera::VirtualCamera;
use crate::cull::{ScanBounds, Visibility, classify};

/// A finest tile whose scans are shown: its bounds and points on its surface (world
/// metres; empty when the tile is not resident, and then its centre stands in).
#[derive(Debug, Clone, Copy)]
pub struct ShownTile<'a> {
    pub info: TileInfo,
    pub samples_m: &'a [[f64; 3]],
}

/// How reliable a scan acquired at `cop_m` is for a view from `eye_m` of a surface
/// at `at_m` (Killpack & Budge 2016 §3 without the per-triangle accuracy): the
/// point-of-view confidence (cosine between the directions to the two centres of
/// projection, 0 when opposite) times the range confidence
/// `min(1, d_virtual / d_acquisition)`. 0 for a degenerate geometry.
pub fn view_reliability(cop_m: [f64; 3], eye_m: [f64; 3], at_m: [f64; 3]) -> f64 {
    let to_cop = [0, 1, 2].map(|a| cop_m[a] - at_m[a]);
    let to_eye = [0, 1, 2].map(|a| eye_m[a] - at_m[a]);
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let (d_acquisition, d_virtual) = (norm(to_cop), norm(to_eye));
    // Guard: a centre of projection on the surface point has no direction.
    if !(d_acquisition > 1e-9 && d_virtual > 1e-9) {
        return 0.0;
    }
    let cos = (0..3).map(|a| to_cop[a] * to_eye[a]).sum::<f64>() / (d_acquisition * d_virtual);
    let pov = cos.clamp(0.0, 1.0);
    let range = (d_virtual / d_acquisition).min(1.0);
    let r = pov * range;
    if r.is_finite() { r } else { 0.0 }
}

/// A scan that may be chosen: its world bounds (the listing's box through its pose),
/// its own-frame box and the inverse pose to test points against it, and its
/// acquisition centre in the world.
struct Candidate {
    id: ScanId,
    world_lo: [f64; 3],
    world_hi: [f64; 3],
    local_lo: [f64; 3],
    local_hi: [f64; 3],
    scan_from_world: Pose,
    cop: [f64; 3],
    /// Squared distance from the acquisition centre to the eye (ties go nearer).
    eye_d2: f64,
}

impl Candidate {
    fn of(scan: &ModelScan, eye_m: [f64; 3]) -> Option<Self> {
        let (lo, hi) = (scan.listing.bounds_min_m, scan.listing.bounds_max_m);
        if !(lo.iter().chain(&hi).all(|c| c.is_finite()) && (0..3).all(|a| lo[a] <= hi[a])) {
            return None;
        }
        let mut world_lo = [f64::INFINITY; 3];
        let mut world_hi = [f64::NEG_INFINITY; 3];
        for k in 0..8 {
            let pick = |a: usize| f64::from(if k >> a & 1 == 0 { lo[a] } else { hi[a] });
            let p = scan.world_from_scan * Point3::new(pick(0), pick(1), pick(2));
            for a in 0..3 {
                world_lo[a] = world_lo[a].min(p[a]);
                world_hi[a] = world_hi[a].max(p[a]);
            }
        }
        let c = scan.listing.cop_m.map(f64::from);
        let c = scan.world_from_scan * Point3::new(c[0], c[1], c[2]);
        let cop = [c.x, c.y, c.z];
        let eye_d2 = (0..3).map(|a| (cop[a] - eye_m[a]).powi(2)).sum::<f64>();
        let ok = world_lo
            .iter()
            .chain(&world_hi)
            .chain(&cop)
            .all(|v| v.is_finite());
        ok.then(|| Self {
            id: scan.id,
            world_lo,
            world_hi,
            local_lo: lo.map(f64::from),
            local_hi: hi.map(f64::from),
            scan_from_world: scan.world_from_scan.inverse(),
            cop,
            eye_d2,
        })
    }

    fn reaches(&self, tile: &TileInfo, margin: f64) -> bool {
        (0..3).all(|a| {
            self.world_lo[a] <= tile.bounds_max_m[a] + margin
                && self.world_hi[a] >= tile.bounds_min_m[a] - margin
        })
    }

    /// Whether the point lies within the scan's own-frame box grown by the margin:
    /// tighter than the world box, which a turned scan's fills with empty corners.
    fn holds(&self, p: [f64; 3], margin: f64) -> bool {
        let q = self.scan_from_world * Point3::new(p[0], p[1], p[2]);
        (0..3).all(|a| q[a] >= self.local_lo[a] - margin && q[a] <= self.local_hi[a] + margin)
    }
}

/// Whether the scan renderer would draw the scan from `camera` (judged from its
/// listing, which bounds its data).
fn drawn_from(scan: &ModelScan, camera: &VirtualCamera) -> bool {
    let Some(bounds) = ScanBounds::of_listing(&scan.listing) else {
        return false;
    };
    let cop = DVec3::from_array(scan.listing.cop_m.map(f64::from));
    classify(&bounds, cop, &scan.world_from_scan, camera) == Visibility::Visible
}

/// The scans to draw below `tiles` (finest tiles whose scans are shown): for each,
/// at most `settings.scans_per_tile` of the scans whose world bounds come within the
/// margin of the tile's and that the scan renderer would draw from `camera` (not
/// culled: `crate::cull`), first those [`choose_for_points`] picks at the tile's
/// surface points in view, then the most reliable at its centre.
pub fn scans_below(
    tiles: &[ShownTile<'_>],
    scans: &[ModelScan],
    camera: &VirtualCamera,
    settings: &HybridSettings,
) -> BTreeSet<ScanId> {
    let eye = camera.world_from_eo.translation.vector;
    let eye_m = [eye.x, eye.y, eye.z];
    let mut chosen = BTreeSet::new();
    if tiles.is_empty() || settings.scans_per_tile == 0 {
        return chosen;
    }
    let candidates: Vec<Candidate> = scans
        .iter()
        .filter(|s| drawn_from(s, camera))
        .filter_map(|s| Candidate::of(s, eye_m))
        .collect();
    let margin = settings.margin_m.max(0.0);
    let view_from_world = camera.view_from_world();
    for tile in tiles {
        let reaching: Vec<&Candidate> = candidates
            .iter()
            .filter(|c| c.reaches(&tile.info, margin))
            .collect();
        let points = points_in_view(tile.samples_m, camera, &view_from_world);
        let mut picked = choose_for_points(&reaching, &points, eye_m, settings);
        // The slots the points leave go to the scans most reliable at the centre: a
        // scan's box is a loose stand-in for what it saw, and the scans drawn show
        // through every tile, not only this one.
        let centre =
            [0, 1, 2].map(|a| 0.5 * (tile.info.bounds_min_m[a] + tile.info.bounds_max_m[a]));
        for id in ranked_at(&reaching, centre, eye_m, settings.scans_per_tile) {
            if picked.len() >= settings.scans_per_tile {
                break;
            }
            if !picked.contains(&id) {
                picked.push(id);
            }
        }
        chosen.extend(picked);
    }
    chosen
}

/// The surface points the camera sees in its image (in front of it, projecting
/// inside the frame), each with its weight: how many pixels the surface around it
/// covers goes as the inverse square of its distance.
fn points_in_view(
    samples_m: &[[f64; 3]],
    camera: &VirtualCamera,
    view_from_world: &Pose,
) -> Vec<([f64; 3], f64)> {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    samples_m
        .iter()
        .filter_map(|p| {
            let v = view_from_world * Point3::new(p[0], p[1], p[2]);
            let [x, y] = camera.project_view(&v.coords)?;
            let inside = (0.0..=w).contains(&x) && (0.0..=h).contains(&y);
            // Guard: a point at the eye (weights stay finite, at most 100 per m²).
            let weight = 1.0 / v.coords.norm_squared().max(0.01);
            (inside && weight.is_finite()).then_some((*p, weight))
        })
        .collect()
}

/// The scans, at most `settings.scans_per_tile`, that blending would pick at the
/// points: per point the `settings.scans_per_point` most reliable scans holding it
/// ([`view_reliability`]), then greedily the scan whose points gain most, each
/// point's gain shrinking with every scan of its own already chosen
/// (`weight · reliability / (1 + chosen)`), so a scan seeing only what the chosen
/// ones see loses to one seeing what they miss. Empty when no scan holds a point.
fn choose_for_points(
    candidates: &[&Candidate],
    points: &[([f64; 3], f64)],
    eye_m: [f64; 3],
    settings: &HybridSettings,
) -> Vec<ScanId> {
    let margin = settings.margin_m.max(0.0);
    let per_point = settings.scans_per_point.max(1);
    // Step 1: per point, the most reliable scans holding it (index into candidates).
    let tops: Vec<(f64, Vec<(usize, f64)>)> = points
        .iter()
        .map(|(p, weight)| {
            let mut top: Vec<(usize, f64)> = candidates
                .iter()
                .enumerate()
                .filter(|(_, c)| c.holds(*p, margin))
                .map(|(i, c)| (i, view_reliability(c.cop, eye_m, *p)))
                .filter(|(_, r)| *r > 0.0)
                .collect();
            top.sort_by(|a, b| {
                b.1.total_cmp(&a.1)
                    .then(candidates[a.0].eye_d2.total_cmp(&candidates[b.0].eye_d2))
                    .then(candidates[a.0].id.cmp(&candidates[b.0].id))
            });
            top.truncate(per_point);
            (*weight, top)
        })
        .collect();
    // Step 2: greedy cover with diminishing gain per point.
    let mut chosen = vec![false; candidates.len()];
    let mut count_at = vec![0u32; tops.len()];
    let mut out = Vec::new();
    while out.len() < settings.scans_per_tile {
        let mut gain = vec![0.0f64; candidates.len()];
        for ((weight, top), n) in tops.iter().zip(&count_at) {
            for (i, r) in top {
                if !chosen[*i] {
                    gain[*i] += weight * r / f64::from(1 + n);
                }
            }
        }
        let best = (0..candidates.len())
            .filter(|i| !chosen[*i] && gain[*i] > 0.0)
            .max_by(|a, b| {
                gain[*a]
                    .total_cmp(&gain[*b])
                    .then(candidates[*b].eye_d2.total_cmp(&candidates[*a].eye_d2))
                    .then(candidates[*b].id.cmp(&candidates[*a].id))
            });
        let Some(best) = best else {
            break;
        };
        chosen[best] = true;
        out.push(candidates[best].id);
        for ((_, top), n) in tops.iter().zip(count_at.iter_mut()) {
            if top.iter().any(|(i, _)| *i == best) {
                *n += 1;
            }
        }
    }
    out
}

/// The `count` scans most reliable for the view of one point (ties to the nearest
/// acquisition, then the lower id).
fn ranked_at(
    candidates: &[&Candidate],
    at_m: [f64; 3],
    eye_m: [f64; 3],
    count: usize,
) -> Vec<ScanId> {
    let mut ranked: Vec<(f64, f64, ScanId)> = candidates
        .iter()
        .map(|c| (view_reliability(c.cop, eye_m, at_m), c.eye_d2, c.id))
        .collect();
    ranked.sort_by(|a, b| {
        b.0.total_cmp(&a.0)
            .then(a.1.total_cmp(&b.1))
            .then(a.2.cmp(&b.2))
    });
    ranked
        .into_iter()
        .take(count)
        .map(|(_, _, id)| id)
        .collect()
}

#[cfg(test)]
mod tests;
