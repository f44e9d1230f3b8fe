//! Which scans to draw below the finest tiles ([`scans_below`]): per tile, the scans
//! view-dependent blending would pick at points spread over the tile's surface
//! (Killpack & Budge 2016 §3's point-of-view and range confidences, taken per point),
//! chosen greedily so that the few a tile may show cover as much of what the view
//! sees of it as they can. Scans acquired a frame apart see nearly the same ground:
//! ranking them at one point would spend every slot on such near-twins and leave the
//! rest of the tile to the coarser tile mesh. Then, from the frames already drawn,
//! the points where the tile still showed (`coverage.rs`): each asks for a scan
//! holding it that has not been drawn there in vain.

use std::collections::BTreeSet;

use glam::DVec3;
use nalgebra::Point3;
use texel::Pose;
use texel::model::{ModelScan, ScanId};
use texel_lod::TileInfo;

use super::coverage::DemandPoint;
use super::hybrid::HybridSettings;
use crate::camera::VirtualCamera;
use crate::cull::{ScanBounds, Visibility, classify};

/// A finest tile whose scans are shown: its bounds and points on its surface (world
/// metres; empty when the tile is not resident, and then its centre stands in).
#[derive(Debug, Clone, Copy)]
pub struct ShownTile<'a> {
    pub info: TileInfo,
    pub samples_m: &'a [[f64; 3]],
    /// Where earlier frames still showed the tile (`coverage.rs`).
    pub demand: &'a [DemandPoint],
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
/// surface points in view, then the most reliable at its centre; and beyond those,
/// at most `settings.feedback_scans_per_tile` that [`choose_for_demand`] picks for
/// the tile's demand points in view.
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
        let demand = demand_in_view(tile.demand, camera, &view_from_world);
        // Scans other tiles chose are drawn too: a point they hold is covered.
        let mut drawn = picked.clone();
        drawn.extend(chosen.iter().copied());
        let extra = choose_for_demand(&reaching, &demand, &drawn, eye_m, settings);
        chosen.extend(picked);
        chosen.extend(extra);
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
    samples_m
        .iter()
        .filter_map(|p| Some((*p, weight_in_view(*p, camera, view_from_world)?)))
        .collect()
}

/// A point's weight when the camera sees it in its image (in front of it,
/// projecting inside the frame): how many pixels the surface around it covers goes
/// as the inverse square of its distance. `None` out of the image.
fn weight_in_view(p: [f64; 3], camera: &VirtualCamera, view_from_world: &Pose) -> Option<f64> {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let v = view_from_world * Point3::new(p[0], p[1], p[2]);
    let [x, y] = camera.project_view(&v.coords)?;
    let inside = (0.0..=w).contains(&x) && (0.0..=h).contains(&y);
    // Guard: a point at the eye (weights stay finite, at most 100 per m²).
    let weight = 1.0 / v.coords.norm_squared().max(0.01);
    (inside && weight.is_finite()).then_some(weight)
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
    let tops: Vec<PointTop> = points
        .iter()
        .map(|(p, weight)| PointTop {
            weight: *weight,
            top: most_reliable(candidates, *p, eye_m, per_point, |c| c.holds(*p, margin)),
            covered: 0,
        })
        .collect();
    // Step 2: greedy cover with diminishing gain per point.
    greedy_cover(
        candidates,
        tops,
        vec![false; candidates.len()],
        settings.scans_per_tile,
    )
}

/// A point's most reliable scans (index into the candidates, reliability), its
/// weight, and how many of them are chosen already.
struct PointTop {
    weight: f64,
    top: Vec<(usize, f64)>,
    covered: u32,
}

/// The `count` candidates `eligible` for a point that are most reliable for the view
/// of it ([`view_reliability`] above 0; ties to the nearest acquisition, then the
/// lower id), as (index, reliability).
fn most_reliable(
    candidates: &[&Candidate],
    at_m: [f64; 3],
    eye_m: [f64; 3],
    count: usize,
    eligible: impl Fn(&Candidate) -> bool,
) -> Vec<(usize, f64)> {
    let mut top: Vec<(usize, f64)> = candidates
        .iter()
        .enumerate()
        .filter(|(_, c)| eligible(c))
        .map(|(i, c)| (i, view_reliability(c.cop, eye_m, at_m)))
        .filter(|(_, r)| *r > 0.0)
        .collect();
    top.sort_by(|a, b| {
        b.1.total_cmp(&a.1)
            .then(candidates[a.0].eye_d2.total_cmp(&candidates[b.0].eye_d2))
            .then(candidates[a.0].id.cmp(&candidates[b.0].id))
    });
    top.truncate(count);
    top
}

/// Greedy cover: at most `budget` candidates not `chosen` already, each time the one
/// whose points gain most, a point's gain `weight · reliability / (1 + covered)`
/// shrinking with every scan of its own chosen.
fn greedy_cover(
    candidates: &[&Candidate],
    mut tops: Vec<PointTop>,
    mut chosen: Vec<bool>,
    budget: usize,
) -> Vec<ScanId> {
    let mut out = Vec::new();
    while out.len() < budget {
        let mut gain = vec![0.0f64; candidates.len()];
        for t in &tops {
            for (i, r) in &t.top {
                if !chosen[*i] {
                    gain[*i] += t.weight * r / f64::from(1 + t.covered);
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
        for t in tops.iter_mut() {
            if t.top.iter().any(|(i, _)| *i == best) {
                t.covered += 1;
            }
        }
    }
    out
}

/// The demand points the camera sees in its image and that still ask for a scan
/// (not given up), with their weights as [`points_in_view`] gives them.
fn demand_in_view<'a>(
    demand: &'a [DemandPoint],
    camera: &VirtualCamera,
    view_from_world: &Pose,
) -> Vec<(&'a DemandPoint, f64)> {
    demand
        .iter()
        .filter(|d| !d.exhausted())
        .filter_map(|d| Some((d, weight_in_view(d.at_m, camera, view_from_world)?)))
        .collect()
}

/// The scans, at most `settings.feedback_scans_per_tile` and none of `picked`, for
/// points where earlier frames still showed the tile: per point the
/// `settings.scans_per_point` most reliable scans holding it that it has not tried
/// (a tried scan was drawn and did not cover it), then greedily as
/// [`choose_for_points`], a point counting as covered already by each picked scan
/// among them.
fn choose_for_demand(
    candidates: &[&Candidate],
    demand: &[(&DemandPoint, f64)],
    picked: &[ScanId],
    eye_m: [f64; 3],
    settings: &HybridSettings,
) -> Vec<ScanId> {
    let margin = settings.margin_m.max(0.0);
    let per_point = settings.scans_per_point.max(1);
    if settings.feedback_scans_per_tile == 0 || demand.is_empty() {
        return Vec::new();
    }
    // Step 1: per point, the most reliable untried scans holding it, and how many of
    // them are picked already.
    let tops: Vec<PointTop> = demand
        .iter()
        .map(|(point, weight)| {
            let top = most_reliable(candidates, point.at_m, eye_m, per_point, |c| {
                !point.tried.contains(&c.id) && c.holds(point.at_m, margin)
            });
            let covered = top
                .iter()
                .filter(|(i, _)| picked.contains(&candidates[*i].id))
                .count() as u32;
            PointTop {
                weight: *weight,
                top,
                covered,
            }
        })
        .collect();
    // Step 2: greedy cover with diminishing gain per point.
    let chosen: Vec<bool> = candidates.iter().map(|c| picked.contains(&c.id)).collect();
    greedy_cover(candidates, tops, chosen, settings.feedback_scans_per_tile)
}

/// Which of the `drawn` scans hold a point in their own-frame box (grown by
/// `margin_m`): the scans a point showing the tile has tried in vain.
pub fn drawn_holding(
    scans: &[ModelScan],
    drawn: &BTreeSet<ScanId>,
    margin_m: f64,
) -> impl Fn([f64; 3]) -> Vec<ScanId> + use<> {
    let candidates: Vec<Candidate> = scans
        .iter()
        .filter(|s| drawn.contains(&s.id))
        .filter_map(|s| Candidate::of(s, [0.0; 3]))
        .collect();
    let margin = margin_m.max(0.0);
    move |p| {
        candidates
            .iter()
            .filter(|c| c.holds(p, margin))
            .map(|c| c.id)
            .collect()
    }
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
