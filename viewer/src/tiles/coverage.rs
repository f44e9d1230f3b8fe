//! Coverage feedback for the scans below the finest tiles: where a frame still showed
//! a tile over ground whose scans were asked for, the surface points there (read
//! back from the tile pass's depth), kept per tile as demand for the next choice
//! (`scan_choice.rs`), each with the scans already drawn that did not cover it.
//!
//! Why: a tile's scans are chosen from points spread over its surface before the
//! frame is drawn, and a scan's box is only a loose stand-in for what it saw, so
//! some of the view's pixels stay with the coarser tile although some scan saw them
//! (the render the viewer shows with every scan would draw them from that scan).
//! The frame itself says which pixels those are, as a virtual-texturing feedback
//! buffer says which pages a frame missed. Points, not scans, are remembered: the
//! choice stays a function of the view and the points, so a scan chosen for a point
//! keeps its place once it covers it, instead of being dropped on the next frame
//! because nothing asks for it any more.

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{Point3, Vector3};
use texel::model::ScanId;
use texel_lod::{TileId, TileInfo};

use crate::camera::VirtualCamera;

/// A scan drawn while a point still showed the tile did not cover it; after this
/// many such scans the point is given up (no scan sees it, or the tile lies in front
/// of what they saw), which bounds what a point keeps. Generous on purpose: a
/// scan's box holds far more than it saw, so dozens of drawn scans may hold a point
/// none of them covers, and giving up after a few dozen left grazing strips that
/// only scans taken right beside them saw to the tile.
pub const MAX_TRIED: usize = 256;

/// Demand points a tile keeps; the oldest go first.
pub const MAX_POINTS_PER_TILE: usize = 2048;

/// A surface point where the tile showed though its scans were asked for.
#[derive(Debug, Clone, PartialEq)]
pub struct DemandPoint {
    /// World metres.
    pub at_m: [f64; 3],
    /// Scans drawn while the point still showed the tile, whose box holds it.
    pub tried: Vec<ScanId>,
    /// When it was last seen uncovered (the feedback round's number).
    pub seen: u64,
}

impl DemandPoint {
    /// Whether every scan worth trying has been: the point asks for nothing more.
    pub fn exhausted(&self) -> bool {
        self.tried.len() >= MAX_TRIED
    }
}

/// The demand points of the finest tiles whose scans are shown.
#[derive(Debug, Clone, Default)]
pub struct CoverageFeedback {
    tiles: BTreeMap<TileId, TileDemand>,
    round: u64,
}

/// One tile's demand: one point per cell of the grid of `cell_m`, in cell order
/// (`keys[i]` is `points[i]`'s cell), so [`CoverageFeedback::points`] lends them as
/// they are kept.
#[derive(Debug, Clone, Default)]
struct TileDemand {
    keys: Vec<[i64; 3]>,
    points: Vec<DemandPoint>,
}

/// A pixel of the tile pass's depth: where a tile drew, reverse z (`near / z`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthSample {
    pub x: u32,
    pub y: u32,
    pub depth: f32,
}

impl CoverageFeedback {
    /// Forgets the tiles no longer showing their scans.
    pub fn retain_tiles(&mut self, shown: &BTreeSet<TileId>) {
        self.tiles.retain(|id, _| shown.contains(id));
    }

    /// The demand points of a tile (empty when it has none).
    pub fn points(&self, id: TileId) -> &[DemandPoint] {
        self.tiles.get(&id).map_or(&[], |t| &t.points)
    }

    /// Feedback rounds recorded so far (the next round's number).
    pub fn round(&self) -> u64 {
        self.round
    }

    /// Demand points over all tiles, and those given up.
    pub fn counts(&self) -> (usize, usize) {
        let all = self.tiles.values().map(|t| t.points.len()).sum();
        let exhausted = self
            .tiles
            .values()
            .flat_map(|t| &t.points)
            .filter(|p| p.exhausted())
            .count();
        (all, exhausted)
    }

    /// Records one frame's feedback: every `samples` pixel where a tile drew is put
    /// back into the world through `camera`; a point inside a `shown` tile's bounds
    /// (grown by its geometric error) becomes demand of that tile, one per cell of
    /// `cell_m`, and the scans `holding(point)` that were drawn are added to what it
    /// tried. Returns the points recorded.
    pub fn record(
        &mut self,
        samples: &[DepthSample],
        camera: &VirtualCamera,
        shown: &[(TileId, TileInfo)],
        cell_m: f64,
        holding: impl Fn([f64; 3]) -> Vec<ScanId>,
    ) -> usize {
        self.round += 1;
        // Guard: a cell of nothing or of NaN would put every point in its own cell
        // (or none); a centimetre is finer than any tile's error.
        let cell_m = if cell_m.is_finite() {
            cell_m.max(0.01)
        } else {
            0.1
        };
        let mut recorded = 0;
        for s in samples {
            let Some(at_m) = world_point(camera, *s) else {
                continue;
            };
            let Some((id, _)) = shown.iter().find(|(_, info)| inside(info, at_m)) else {
                continue;
            };
            let key = at_m.map(|c| (c / cell_m).floor() as i64);
            let point = self.tiles.entry(*id).or_default().point_at(key, at_m);
            point.seen = self.round;
            for scan in holding(point.at_m) {
                if point.tried.len() < MAX_TRIED && !point.tried.contains(&scan) {
                    point.tried.push(scan);
                }
            }
            recorded += 1;
        }
        for tile in self.tiles.values_mut() {
            tile.trim();
        }
        recorded
    }
}

impl TileDemand {
    /// The point of cell `key`, made at `at_m` when the cell has none yet.
    fn point_at(&mut self, key: [i64; 3], at_m: [f64; 3]) -> &mut DemandPoint {
        let i = match self.keys.binary_search(&key) {
            Ok(i) => i,
            Err(i) => {
                self.keys.insert(i, key);
                let point = DemandPoint {
                    at_m,
                    tried: Vec::new(),
                    seen: 0,
                };
                self.points.insert(i, point);
                i
            }
        };
        &mut self.points[i]
    }

    /// Keeps at most `MAX_POINTS_PER_TILE` points: the most recently seen, ties in
    /// cell order, so the cut is deterministic.
    fn trim(&mut self) {
        if self.points.len() <= MAX_POINTS_PER_TILE {
            return;
        }
        let mut order: Vec<usize> = (0..self.points.len()).collect();
        order.sort_unstable_by(|a, b| {
            self.points[*b]
                .seen
                .cmp(&self.points[*a].seen)
                .then(self.keys[*a].cmp(&self.keys[*b]))
        });
        let mut keep = vec![false; self.points.len()];
        for i in &order[..MAX_POINTS_PER_TILE] {
            keep[*i] = true;
        }
        let mut k = keep.iter();
        self.keys.retain(|_| k.next().copied().unwrap_or(false));
        let mut k = keep.iter();
        self.points.retain(|_| k.next().copied().unwrap_or(false));
    }
}

/// The world point a depth sample shows: `z = near / depth` along the pixel's ray
/// (`VirtualCamera::clip_from_view`). `None` where nothing drew (depth 0, the far
/// plane at infinity) or the depth is not a number.
pub fn world_point(camera: &VirtualCamera, s: DepthSample) -> Option<[f64; 3]> {
    let depth = f64::from(s.depth);
    // Guard: depth 0 is the cleared far plane; a tiny one an absurd distance.
    if !(depth.is_finite() && depth > 1e-9) {
        return None;
    }
    let z = camera.near_m / depth;
    let f = camera.focal_px();
    if !(z.is_finite() && f > 0.0) {
        return None;
    }
    let view = Vector3::new(
        (f64::from(s.x) + 0.5 - f64::from(camera.width) * 0.5) / f * z,
        (f64::from(s.y) + 0.5 - f64::from(camera.height) * 0.5) / f * z,
        z,
    );
    let p = camera.world_from_eo * Point3::from(view);
    let out = [p.x, p.y, p.z];
    out.iter().all(|c| c.is_finite()).then_some(out)
}

/// Whether a point lies in a tile's bounds grown by its geometric error.
fn inside(info: &TileInfo, p: [f64; 3]) -> bool {
    let grow = if info.geometric_error_m.is_finite() {
        info.geometric_error_m.max(0.0)
    } else {
        0.0
    };
    (0..3).all(|a| p[a] >= info.bounds_min_m[a] - grow && p[a] <= info.bounds_max_m[a] + grow)
}

/// Every `stride`-th pixel across and down of a depth image (row-major, `width`
/// wide) where a tile drew (depth above 0), at the offset in each stride block that
/// [`grid_offset`] gives the feedback round.
pub fn depth_samples(
    depth: &[f32],
    width: u32,
    height: u32,
    stride: u32,
    round: u64,
) -> Vec<DepthSample> {
    let stride = stride.max(1);
    let mut out = Vec::new();
    let (offset_x, offset_y) = grid_offset(stride, round);
    let mut y = offset_y.min(height.saturating_sub(1));
    while y < height {
        let mut x = offset_x.min(width.saturating_sub(1));
        while x < width {
            let i = y as usize * width as usize + x as usize;
            if let Some(&d) = depth.get(i)
                && d > 0.0
                && d.is_finite()
            {
                out.push(DepthSample { x, y, depth: d });
            }
            x += stride;
        }
        y += stride;
    }
    out
}

/// Where in each `stride` x `stride` block round `round` samples: the middle first
/// (a coarse grid is then not biased to the top-left), then along the block's
/// diagonals, one diagonal every `stride` rounds, so each such run samples every row
/// and every column of the block once and `stride`² rounds every pixel: a strip one
/// pixel wide, such as a facade seen edge-on, is found within a few rounds wherever
/// it lies.
pub fn grid_offset(stride: u32, round: u64) -> (u32, u32) {
    let s = u64::from(stride.max(1));
    let k = round % (s * s);
    let (diagonal, along) = (k / s, k % s);
    let middle = s / 2;
    (
        ((along + middle) % s) as u32,
        ((along + diagonal + middle) % s) as u32,
    )
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;
    use texel::Pose;

    fn camera() -> VirtualCamera {
        VirtualCamera::new(Pose::translation(1.0, 2.0, -10.0), 60.0, 64, 48).unwrap()
    }

    fn info(lo: [f64; 3], hi: [f64; 3]) -> TileInfo {
        TileInfo {
            bounds_min_m: lo,
            bounds_max_m: hi,
            geometric_error_m: 0.1,
        }
    }

    #[test]
    fn a_depth_sample_goes_back_to_the_point_that_projects_there() {
        let cam = camera();
        // A world point in front of the camera, projected and put back.
        let p = Point3::new(1.7, 1.4, -3.0);
        let v = cam.view_from_world() * p;
        let [px, py] = cam.project_view(&v.coords).unwrap();
        let (x, y) = (px.floor() as u32, py.floor() as u32);
        // The depth of the pixel centre's ray at the point's z.
        let depth = (cam.near_m / v.z) as f32;
        let back = world_point(&cam, DepthSample { x, y, depth }).unwrap();
        // Within a pixel's footprint at 7 m (the sample is at the pixel centre).
        let footprint = v.z / cam.focal_px();
        for a in 0..3 {
            assert!(
                (back[a] - p[a]).abs() < 1.5 * footprint,
                "{back:?} vs {p:?}"
            );
        }
        // Nothing drawn, or not a number: no point.
        for depth in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            assert!(world_point(&cam, DepthSample { x, y, depth }).is_none());
        }
    }

    #[test]
    fn samples_skip_where_nothing_drew_and_keep_the_stride() {
        let (w, h) = (8u32, 4u32);
        let mut depth = vec![0.0f32; (w * h) as usize];
        depth[(w + 1) as usize] = 0.5; // (1, 1): on the stride-2 grid
        depth[(2 * w + 2) as usize] = 0.5; // (2, 2): off it
        depth[(3 * w + 5) as usize] = f32::NAN; // (5, 3): on it, not a number
        // Round 0 samples the middle of each 2 x 2 block, (1, 1) among them.
        let s = depth_samples(&depth, w, h, 2, 0);
        assert_eq!(
            s,
            vec![DepthSample {
                x: 1,
                y: 1,
                depth: 0.5
            }]
        );
        // Round 1 the block's opposite corner, (2, 2) among them.
        assert_eq!(grid_offset(2, 1), (0, 0));
        let s = depth_samples(&depth, w, h, 2, 1);
        assert_eq!(s.len(), 1);
        assert_eq!((s[0].x, s[0].y), (2, 2));
        assert_eq!(depth_samples(&depth, w, h, 1, 7).len(), 2);
        assert!(depth_samples(&[], 0, 0, 0, 0).is_empty());
        assert!(depth_samples(&depth[..3], w, h, 1, 0).is_empty());
    }

    #[test]
    fn the_grid_offset_visits_every_pixel_of_a_block_and_each_row_and_column_in_turn() {
        for stride in 1..=6u32 {
            let n = u64::from(stride * stride);
            // Round 0 is the middle of the block.
            assert_eq!(grid_offset(stride, 0), (stride / 2, stride / 2));
            let offsets: Vec<(u32, u32)> = (0..n).map(|r| grid_offset(stride, r)).collect();
            let distinct: BTreeSet<(u32, u32)> = offsets.iter().copied().collect();
            assert_eq!(distinct.len() as u64, n, "stride {stride}: {offsets:?}");
            assert!(offsets.iter().all(|(x, y)| *x < stride && *y < stride));
            // Each run of `stride` rounds covers every row and every column.
            for start in (0..n).step_by(stride as usize) {
                let run: Vec<(u32, u32)> = (start..start + u64::from(stride))
                    .map(|r| grid_offset(stride, r))
                    .collect();
                let rows: BTreeSet<u32> = run.iter().map(|p| p.1).collect();
                let columns: BTreeSet<u32> = run.iter().map(|p| p.0).collect();
                assert_eq!(rows.len() as u32, stride, "stride {stride} from {start}");
                assert_eq!(columns.len() as u32, stride, "stride {stride} from {start}");
            }
            // The walk repeats after stride² rounds, and a huge round is no trouble.
            assert_eq!(grid_offset(stride, n + 3), grid_offset(stride, 3));
            assert!(grid_offset(stride, u64::MAX).0 < stride);
        }
        // A stride of 0 reads every pixel.
        assert_eq!(grid_offset(0, 5), (0, 0));
    }

    #[test]
    fn demand_lands_in_the_tile_holding_it_one_per_cell_and_remembers_tries() {
        let cam = VirtualCamera::new(Pose::identity(), 60.0, 64, 48).unwrap();
        // Depth 0.01 at near 0.05: 5 m ahead. Two neighbouring pixels land in one
        // 0.5 m cell; a third, far off to the side, in another.
        let d = (cam.near_m / 5.0) as f32;
        let samples = [
            DepthSample {
                x: 32,
                y: 24,
                depth: d,
            },
            DepthSample {
                x: 33,
                y: 24,
                depth: d,
            },
            DepthSample {
                x: 2,
                y: 24,
                depth: d,
            },
        ];
        let a = TileId { lod: 0, x: 0, y: 0 };
        let b = TileId { lod: 0, x: 1, y: 0 };
        // Tile a holds the centre; tile b nothing the camera sees.
        let shown = [
            (a, info([-1.0, -1.0, 4.0], [1.0, 1.0, 6.0])),
            (b, info([50.0, 50.0, 50.0], [51.0, 51.0, 51.0])),
        ];
        let mut fb = CoverageFeedback::default();
        let n = fb.record(&samples, &cam, &shown, 0.5, |_| vec![7, 9]);
        assert_eq!(n, 2, "the third pixel's point lies outside both tiles");
        assert_eq!(fb.points(a).len(), 1);
        assert!(fb.points(b).is_empty());
        assert_eq!(fb.points(a)[0].tried, vec![7, 9]);
        // Seen again with another scan drawn: tried grows, no duplicate.
        fb.record(&samples[..1], &cam, &shown, 0.5, |_| vec![9, 11]);
        assert_eq!(fb.points(a)[0].tried, vec![7, 9, 11]);
        // Tries are bounded; then the point is given up.
        for round in 0..2 * MAX_TRIED as u64 {
            fb.record(&samples[..1], &cam, &shown, 0.5, |_| vec![100 + round]);
        }
        assert_eq!(fb.points(a)[0].tried.len(), MAX_TRIED);
        assert!(fb.points(a)[0].exhausted());
        assert_eq!(fb.counts(), (1, 1));
        // A tile that stops showing its scans forgets its demand.
        fb.retain_tiles(&BTreeSet::from([b]));
        assert!(fb.points(a).is_empty());
        // A bad cell size still records.
        assert_eq!(fb.record(&samples, &cam, &shown, f64::NAN, |_| vec![]), 2);
    }

    #[test]
    fn a_tile_keeps_at_most_its_share_of_points_the_latest_seen() {
        let cam = VirtualCamera::new(Pose::identity(), 90.0, 200, 200).unwrap();
        let a = TileId { lod: 0, x: 0, y: 0 };
        let shown = [(a, info([-100.0, -100.0, 0.0], [100.0, 100.0, 100.0]))];
        let d = (cam.near_m / 10.0) as f32;
        let all: Vec<DepthSample> = (0..200u32)
            .flat_map(|y| (0..200u32).map(move |x| DepthSample { x, y, depth: d }))
            .collect();
        let mut fb = CoverageFeedback::default();
        // 40,000 pixels, each its own 1 cm cell at 10 m (a pixel is 5 cm there).
        fb.record(&all, &cam, &shown, 0.01, |_| vec![]);
        assert_eq!(fb.points(a).len(), MAX_POINTS_PER_TILE);
        // The latest seen stay: one more round over a few pixels keeps them all.
        fb.record(&all[..10], &cam, &shown, 0.01, |_| vec![]);
        let latest = fb.points(a).iter().filter(|p| p.seen == 2).count();
        assert_eq!(latest, 10);
        assert_eq!(fb.points(a).len(), MAX_POINTS_PER_TILE);
    }
}
