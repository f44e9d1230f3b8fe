//! The residency planner: pure and deterministic. From what is known of every scan
//! (listing, pose, bytes, whether its data is here), the camera and a byte budget, it
//! chooses the scans to hold: those the current view and nearby views need, best
//! first, as many as fit. Everything else is evicted; what is chosen and missing is
//! fetched.

use std::collections::BTreeSet;

use glam::DVec3;
use texel::Pose;
use texel::model::{ScanId, ScanListing};

use crate::camera::{MAX_FOV_DEG, VirtualCamera};
use crate::cull::{ScanBounds, Visibility, classify};
use crate::gpu::pose_relative;

/// Where a scan's data is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DataState {
    /// Uploaded: drawn when visible.
    OnGpu,
    /// Here on the CPU (arrived or loadable at once) but not uploaded.
    Held,
    /// Asked for; not here yet.
    InFlight,
    /// Must be fetched.
    Absent,
}

impl DataState {
    /// Whether the data is here or coming (no request needed).
    fn present(self) -> bool {
        self != DataState::Absent
    }
}

/// One scan as the planner sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanScan {
    pub id: ScanId,
    pub listing: ScanListing,
    pub world_from_scan: Pose,
    /// GPU bytes: exact once the data was seen, else estimated from the listing.
    pub bytes: u64,
    pub state: DataState,
}

/// The planner's knobs.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanOptions {
    pub budget_bytes: u64,
    /// The view is widened by this factor (on the tangent of the half field of view)
    /// to decide what is needed: a small turn does not wait for a fetch.
    pub widen: f64,
    /// A held scan is kept while inside the view widened by this larger factor
    /// (when budget allows): a scan at the edge does not go and come back.
    pub keep_widen: f64,
    /// Scans whose bounding sphere comes this close to the camera are needed whatever
    /// the direction (the views a step or a turn away).
    /// (Held scans are kept within `near_m * keep_widen`.)
    pub near_m: f64,
    /// A scan whose data is here or coming ranks this many times higher, so a newcomer
    /// must be clearly better to displace it.
    pub stickiness: f64,
    /// At most this many fetches outstanding.
    pub max_in_flight: usize,
    /// Scans switched off by the user: never needed.
    pub hidden: BTreeSet<ScanId>,
    /// Only these scans can be needed (`None`: any): the scans below the finest
    /// level-of-detail tiles, when tiles draw the rest.
    pub only: Option<BTreeSet<ScanId>>,
}

impl PlanOptions {
    pub fn new(budget_bytes: u64) -> Self {
        Self {
            budget_bytes,
            widen: 1.25,
            keep_widen: 1.6,
            near_m: 1.0,
            stickiness: 1.25,
            max_in_flight: 4,
            hidden: BTreeSet::new(),
            only: None,
        }
    }
}

/// What to hold, evict and fetch.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Plan {
    /// The scans to hold, best first: the needed ones that fit, then kept ones.
    pub selected: Vec<ScanId>,
    /// Their bytes (never above the budget).
    pub selected_bytes: u64,
    /// Held or uploaded scans not selected: drop them.
    pub evict: Vec<ScanId>,
    /// Selected, absent scans to ask for now, best first (within the in-flight limit).
    pub fetch: Vec<ScanId>,
    /// Selected and absent beyond the in-flight limit.
    pub fetch_later: usize,
    /// Scans the view needs (in the widened view or near the camera).
    pub needed: usize,
    /// Needed scans that do not fit the budget, best first.
    pub left_out: Vec<ScanId>,
}

/// How much a scan matters to the view, or `None` when it is not wanted.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Want {
    /// In the widened view or near the camera: `score` ranks it.
    Needed { score: f64 },
    /// Only within the keep band: held if room is left.
    Band { score: f64 },
}

/// Plans residency for `camera`. Deterministic: ties rank by lower id.
pub fn plan(scans: &[PlanScan], camera: &VirtualCamera, options: &PlanOptions) -> Plan {
    let wide = widened(camera, options.widen.max(1.0));
    let wider = widened(camera, options.keep_widen.max(options.widen).max(1.0));
    let mean_priority = mean_known_priority(scans);
    let view_from_world = camera.view_from_world();
    let mut needed: Vec<(f64, &PlanScan)> = Vec::new();
    let mut band: Vec<(f64, &PlanScan)> = Vec::new();
    for s in scans {
        let left_out = options
            .only
            .as_ref()
            .is_some_and(|only| !only.contains(&s.id));
        if left_out || options.hidden.contains(&s.id) {
            continue;
        }
        let want = want(s, &view_from_world, &wide, &wider, options, mean_priority);
        let boost = if s.state.present() {
            options.stickiness.max(1.0)
        } else {
            1.0
        };
        match want {
            Some(Want::Needed { score }) => needed.push((score * boost, s)),
            Some(Want::Band { score }) if s.state.present() => band.push((score * boost, s)),
            _ => {}
        }
    }
    let by_rank =
        |a: &(f64, &PlanScan), b: &(f64, &PlanScan)| b.0.total_cmp(&a.0).then(a.1.id.cmp(&b.1.id));
    needed.sort_by(by_rank);
    band.sort_by(by_rank);
    let mut out = Plan {
        needed: needed.len(),
        ..Default::default()
    };
    let mut selected = BTreeSet::new();
    for (_, s) in &needed {
        if fits(out.selected_bytes, s.bytes, options.budget_bytes) {
            out.selected_bytes += s.bytes;
            out.selected.push(s.id);
            selected.insert(s.id);
        } else {
            out.left_out.push(s.id);
        }
    }
    // The band only fills room that no needed scan wanted: a needed scan is never
    // left out while a merely kept one stays.
    if out.left_out.is_empty() {
        for (_, s) in &band {
            if fits(out.selected_bytes, s.bytes, options.budget_bytes) {
                out.selected_bytes += s.bytes;
                out.selected.push(s.id);
                selected.insert(s.id);
            }
        }
    }
    let mut in_flight = scans
        .iter()
        .filter(|s| s.state == DataState::InFlight)
        .count();
    let by_id: std::collections::BTreeMap<ScanId, &PlanScan> =
        scans.iter().map(|s| (s.id, s)).collect();
    for id in &out.selected {
        if by_id.get(id).is_some_and(|s| s.state == DataState::Absent) {
            if in_flight < options.max_in_flight {
                out.fetch.push(*id);
                in_flight += 1;
            } else {
                out.fetch_later += 1;
            }
        }
    }
    out.evict = scans
        .iter()
        .filter(|s| {
            matches!(s.state, DataState::OnGpu | DataState::Held) && !selected.contains(&s.id)
        })
        .map(|s| s.id)
        .collect();
    out
}

fn fits(used: u64, bytes: u64, budget: u64) -> bool {
    used.checked_add(bytes).is_some_and(|total| total <= budget)
}

/// The same camera with a wider field of view (the tangent scaled by `factor`).
fn widened(camera: &VirtualCamera, factor: f64) -> VirtualCamera {
    let tan = camera.tan_half_fov_y() * factor;
    let fov_deg = (2.0 * tan.atan()).to_degrees().min(MAX_FOV_DEG);
    VirtualCamera::new(camera.world_from_eo, fov_deg, camera.width, camera.height)
        .unwrap_or(*camera)
}

/// The mean of the positive, finite priorities (what an unknown priority counts as);
/// 1 when none is known.
fn mean_known_priority(scans: &[PlanScan]) -> f64 {
    let (sum, n) = scans
        .iter()
        .map(|s| f64::from(s.listing.priority))
        .filter(|p| p.is_finite() && *p > 0.0)
        .fold((0.0, 0usize), |(sum, n), p| (sum + p, n + 1));
    if n == 0 { 1.0 } else { sum / n as f64 }
}

fn want(
    s: &PlanScan,
    view_from_world: &Pose,
    wide: &VirtualCamera,
    wider: &VirtualCamera,
    options: &PlanOptions,
    mean_priority: f64,
) -> Option<Want> {
    let bounds = ScanBounds::of_listing(&s.listing)?;
    let cop = DVec3::from_array(s.listing.cop_m.map(f64::from));
    let view_from_scan = pose_relative(view_from_world, &s.world_from_scan);
    let centre = view_from_scan.transform_point3(bounds.centre_scan);
    let distance_m = centre.length();
    // Gap between the camera and the sphere (0 inside it).
    let gap_m = (distance_m - bounds.radius_m).max(0.0);
    // How large it appears: the sphere's angular radius, squared (a solid-angle
    // proxy in (0, 1]; 1 when the camera is inside the sphere).
    let size = if distance_m > bounds.radius_m && distance_m > 0.0 {
        (bounds.radius_m / distance_m).powi(2)
    } else {
        1.0
    };
    let priority = match f64::from(s.listing.priority) {
        p if p.is_finite() && p > 0.0 => p,
        _ => mean_priority,
    };
    let score = priority * size;
    let near = options.near_m.max(0.0);
    if classify(&bounds, cop, &s.world_from_scan, wide) == Visibility::Visible {
        return Some(Want::Needed { score });
    }
    if gap_m <= near {
        // Out of this view but a step or a turn away: ranked below what is in view
        // of the same size.
        return Some(Want::Needed {
            score: score * 0.25,
        });
    }
    let keep = options.keep_widen.max(1.0);
    if gap_m <= near * keep
        || classify(&bounds, cop, &s.world_from_scan, wider) == Visibility::Visible
    {
        return Some(Want::Band { score });
    }
    None
}
