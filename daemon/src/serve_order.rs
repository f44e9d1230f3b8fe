//! The order a newcomer learns of the served scans: coarse coverage first. The most
//! reliable scan of every region comes before any region's second, so a viewer that
//! fetches in this order sees the whole model early and fills in detail after,
//! instead of growing it in acquisition order.

use std::collections::HashMap;

use texel::Pose;
use texel::model::{ScanId, ScanListing};

/// Side of the regions scans are grouped by.
pub const REGION_M: f64 = 2.0;

/// One served scan as the ordering sees it.
#[derive(Debug, Clone, Copy)]
pub struct Served<'a> {
    pub id: ScanId,
    pub listing: &'a ScanListing,
    pub world_from_scan: &'a Pose,
}

/// The region of a scan: the cell of `region_m` holding the centre of its bounds in
/// the world (a scan with non-finite bounds falls in the region of its pose).
fn region(s: &Served<'_>, region_m: f64) -> [i64; 3] {
    let l = s.listing;
    let centre = nalgebra::Point3::new(
        0.5 * (f64::from(l.bounds_min_m[0]) + f64::from(l.bounds_max_m[0])),
        0.5 * (f64::from(l.bounds_min_m[1]) + f64::from(l.bounds_max_m[1])),
        0.5 * (f64::from(l.bounds_min_m[2]) + f64::from(l.bounds_max_m[2])),
    );
    let mut world = s.world_from_scan * centre;
    if !world.coords.iter().all(|c| c.is_finite()) {
        world = nalgebra::Point3::from(s.world_from_scan.translation.vector);
    }
    // `as` saturates, and a non-finite coordinate maps to 0: every scan gets a cell.
    world.coords.map(|c| (c / region_m).floor() as i64).into()
}

/// Ids of `scans` in coarse-first order: rank 0 of every region (its highest
/// priority scan), then rank 1 of every region, ...; within a rank, by priority
/// (ties by id), so the order is deterministic.
pub fn coarse_first(scans: &[Served<'_>], region_m: f64) -> Vec<ScanId> {
    // 1. Group by region.
    let mut regions: HashMap<[i64; 3], Vec<&Served<'_>>> = HashMap::new();
    for s in scans {
        regions.entry(region(s, region_m)).or_default().push(s);
    }
    // 2. Rank within each region by priority, most reliable first.
    let by_priority = |a: &&Served<'_>, b: &&Served<'_>| {
        b.listing
            .priority
            .total_cmp(&a.listing.priority)
            .then(a.id.cmp(&b.id))
    };
    let mut ranked: Vec<(usize, &Served<'_>)> = Vec::with_capacity(scans.len());
    for members in regions.values_mut() {
        members.sort_by(by_priority);
        ranked.extend(members.iter().enumerate().map(|(rank, s)| (rank, *s)));
    }
    // 3. Rank first, then priority.
    ranked.sort_by(|(ra, a), (rb, b)| ra.cmp(rb).then_with(|| by_priority(a, b)));
    ranked.into_iter().map(|(_, s)| s.id).collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    fn listing(priority: f32) -> ScanListing {
        ScanListing {
            timestamp_ns: 0,
            bounds_min_m: [-0.5, -0.5, 1.0],
            bounds_max_m: [0.5, 0.5, 2.0],
            cop_m: [0.0; 3],
            priority,
            encoded_bytes: 1,
        }
    }

    #[test]
    fn every_region_shows_before_any_region_fills_in() {
        // Three regions along x; region 0 has four scans, the others one or two.
        let poses: Vec<Pose> = [0.0, 0.1, 0.2, 0.3, 10.0, 20.0, 20.1]
            .iter()
            .map(|&x| Pose::translation(x, 0.0, 0.0))
            .collect();
        let listings: Vec<ScanListing> = [1.0, 5.0, 3.0, 2.0, 0.5, 4.0, 6.0]
            .iter()
            .map(|&p| listing(p))
            .collect();
        let scans: Vec<Served<'_>> = (0..poses.len())
            .map(|i| Served {
                id: i as ScanId,
                listing: &listings[i],
                world_from_scan: &poses[i],
            })
            .collect();
        let order = coarse_first(&scans, REGION_M);
        // Rank 0: region 2's best (6.0, id 6), region 0's best (5.0, id 1), region 1's (0.5, id 4).
        assert_eq!(&order[..3], &[6, 1, 4]);
        // Then rank 1 of regions 2 and 0, then the rest of region 0.
        assert_eq!(&order[3..], &[5, 2, 3, 0]);
    }

    #[test]
    fn non_finite_bounds_and_poses_still_get_a_place() {
        let mut l = listing(1.0);
        l.bounds_min_m = [f32::NAN; 3];
        let bad = Pose::translation(f64::INFINITY, 0.0, 0.0);
        let good = Pose::identity();
        let ll = listing(2.0);
        let scans = [
            Served {
                id: 0,
                listing: &l,
                world_from_scan: &bad,
            },
            Served {
                id: 1,
                listing: &ll,
                world_from_scan: &good,
            },
        ];
        let mut order = coarse_first(&scans, REGION_M);
        order.sort_unstable();
        assert_eq!(order, vec![0, 1]);
    }
}
