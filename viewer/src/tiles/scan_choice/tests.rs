#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
use super::*;
use texel::model::ScanListing;

fn scan(id: u64, x_m: f64) -> ModelScan {
    ModelScan {
        id,
        scan: None,
        listing: ScanListing {
            timestamp_ns: 0,
            bounds_min_m: [-1.0, -1.0, 1.0],
            bounds_max_m: [1.0, 1.0, 5.0],
            cop_m: [0.0; 3],
            priority: 0.0,
            encoded_bytes: 0,
        },
        world_from_scan: Pose::translation(x_m, 0.0, 0.0),
        revisions: 0,
    }
}

/// A camera 30 m behind the scans' centres at `x_m`, looking the way they look
/// (+z), 90 degrees across.
fn camera(x_m: f64) -> VirtualCamera {
    VirtualCamera::new(Pose::translation(x_m, 0.0, -30.0), 90.0, 100, 100).unwrap()
}

/// A tile without surface points: chosen at its centre.
fn tile(x0: f64, x1: f64) -> ShownTile<'static> {
    ShownTile {
        info: TileInfo {
            bounds_min_m: [x0, -5.0, 0.0],
            bounds_max_m: [x1, 5.0, 6.0],
            geometric_error_m: 0.05,
        },
        samples_m: &[],
        demand: &[],
    }
}

#[test]
fn each_tile_gets_the_scans_reaching_it_most_reliable_for_the_view() {
    let scans: Vec<ModelScan> = (0..20u32)
        .map(|i| scan(u64::from(i), f64::from(i)))
        .collect();
    let settings = HybridSettings {
        scans_per_tile: 3,
        margin_m: 0.0,
        ..HybridSettings::default()
    };
    // Scans at x = 0..19, each 2 m wide: the tile [10, 12] is reached by 9..=13.
    let got = scans_below(&[tile(10.0, 12.0)], &scans, &camera(30.0), &settings);
    assert_eq!(got, BTreeSet::from([11u64, 12, 13]));
    let got = scans_below(&[tile(10.0, 12.0)], &scans, &camera(0.0), &settings);
    assert_eq!(got, BTreeSet::from([9u64, 10, 11]));
    // Two tiles: the union.
    let got = scans_below(
        &[tile(0.0, 1.0), tile(10.0, 12.0)],
        &scans,
        &camera(0.0),
        &settings,
    );
    assert_eq!(got.len(), 6);
    assert!(scans_below(&[], &scans, &camera(0.0), &settings).is_empty());
    // Scans the renderer would cull are never chosen: one behind the camera, one
    // looking back at it (the camera sees its back); all reach a tall tile.
    let tall = ShownTile {
        info: TileInfo {
            bounds_min_m: [10.0, -5.0, -50.0],
            bounds_max_m: [12.0, 5.0, 50.0],
            geometric_error_m: 0.05,
        },
        samples_m: &[],
        demand: &[],
    };
    let mut behind = scan(40, 11.0);
    behind.world_from_scan = Pose::translation(11.0, 0.0, -40.0);
    let mut back = scan(41, 11.0);
    back.world_from_scan = Pose::from_parts(
        nalgebra::Translation3::new(11.0, 0.0, 20.0),
        nalgebra::UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
    );
    let cam = camera(11.0);
    for (s, want) in [
        (&behind, Visibility::OutsideFrustum),
        (&back, Visibility::FacingAway),
    ] {
        let bounds = ScanBounds::of_listing(&s.listing).unwrap();
        let cop = DVec3::from_array(s.listing.cop_m.map(f64::from));
        assert_eq!(classify(&bounds, cop, &s.world_from_scan, &cam), want);
    }
    let got = scans_below(&[tall], &[behind, back, scan(42, 11.0)], &cam, &settings);
    assert_eq!(got, BTreeSet::from([42u64]));
}

#[test]
fn reliability_is_the_view_and_range_confidence() {
    let at = [0.0, 0.0, 0.0];
    // Seen from where it was acquired: 1.
    assert!((view_reliability([0.0, 0.0, 5.0], [0.0, 0.0, 5.0], at) - 1.0).abs() < 1e-12);
    // Acquired twice as far: half (range confidence); closer: still 1.
    assert!((view_reliability([0.0, 0.0, 10.0], [0.0, 0.0, 5.0], at) - 0.5).abs() < 1e-12);
    assert!((view_reliability([0.0, 0.0, 2.0], [0.0, 0.0, 5.0], at) - 1.0).abs() < 1e-12);
    // 60 degrees apart: cos = 0.5; from behind: 0.
    let side = [
        5.0 * 60f64.to_radians().sin(),
        0.0,
        5.0 * 60f64.to_radians().cos(),
    ];
    assert!((view_reliability(side, [0.0, 0.0, 5.0], at) - 0.5).abs() < 1e-12);
    assert_eq!(view_reliability([0.0, 0.0, -5.0], [0.0, 0.0, 5.0], at), 0.0);
    // Degenerate: a centre on the point, or not finite.
    assert_eq!(view_reliability(at, [0.0, 0.0, 5.0], at), 0.0);
    assert_eq!(view_reliability([f64::NAN; 3], [0.0, 0.0, 5.0], at), 0.0);
    assert_eq!(
        view_reliability([0.0, 0.0, f64::INFINITY], [0.0, 0.0, 5.0], at),
        0.0
    );
}

#[test]
fn a_scan_with_a_broken_listing_is_never_chosen() {
    let mut bad = scan(1, 10.0);
    bad.listing.bounds_min_m = [f32::NAN, 0.0, 0.0];
    let mut inverted = scan(2, 10.0);
    inverted.listing.bounds_min_m = [2.0, 2.0, 2.0];
    let got = scans_below(
        &[tile(0.0, 20.0)],
        &[bad, inverted, scan(3, 10.0)],
        &camera(10.0),
        &HybridSettings::default(),
    );
    assert_eq!(got, BTreeSet::from([3u64]));
}

/// Points on a wall 4 m ahead of the scans (z = 4), every 0.25 m from x0 to x1.
fn wall(x0: f64, x1: f64) -> Vec<[f64; 3]> {
    let n = ((x1 - x0) / 0.25).round() as usize;
    (0..=n).map(|i| [x0 + 0.25 * i as f64, 0.0, 4.0]).collect()
}

#[test]
fn the_points_seen_by_no_chosen_scan_draw_the_next_choice() {
    // Ten scans a centimetre apart see the wall at x 1..3; one more sees 7..9.
    let mut scans: Vec<ModelScan> = (0..10u32)
        .map(|i| scan(u64::from(i), 2.0 + 0.01 * f64::from(i)))
        .collect();
    scans.push(scan(100, 8.0));
    let settings = HybridSettings {
        scans_per_tile: 3,
        scans_per_point: 2,
        margin_m: 0.0,
        ..HybridSettings::default()
    };
    let samples = wall(1.0, 9.0);
    let info = TileInfo {
        bounds_min_m: [0.0, -5.0, 0.0],
        bounds_max_m: [7.5, 5.0, 6.0],
        geometric_error_m: 0.05,
    };
    let with_points = ShownTile {
        info,
        samples_m: &samples,
        demand: &[],
    };
    let got = scans_below(&[with_points], &scans, &camera(5.0), &settings);
    assert_eq!(got.len(), 3, "{got:?}");
    assert!(
        got.contains(&100),
        "the only scan of x 7..9 is left out: {got:?}"
    );
    // Ranked at the tile's centre instead, the ten near-twins take every slot.
    let at_centre = ShownTile {
        info,
        samples_m: &[],
        demand: &[],
    };
    let got = scans_below(&[at_centre], &scans, &camera(5.0), &settings);
    assert_eq!(got.len(), 3);
    assert!(!got.contains(&100));
}

#[test]
fn points_out_of_view_do_not_count() {
    // The wall the scans see, but every point behind the camera: the tile is chosen
    // for at its centre, as without points.
    let scans: Vec<ModelScan> = (0..6u32)
        .map(|i| scan(u64::from(i), 2.0 * f64::from(i)))
        .collect();
    let settings = HybridSettings {
        scans_per_tile: 2,
        margin_m: 0.0,
        ..HybridSettings::default()
    };
    let behind: Vec<[f64; 3]> = wall(0.0, 10.0)
        .into_iter()
        .map(|p| [p[0], p[1], -40.0])
        .collect();
    let shown = |samples_m| ShownTile {
        info: tile(0.0, 10.0).info,
        samples_m,
        demand: &[],
    };
    let cam = camera(0.0);
    let without = scans_below(&[shown(&[])], &scans, &cam, &settings);
    assert_eq!(
        scans_below(&[shown(&behind)], &scans, &cam, &settings),
        without
    );
    // Points in view that no scan holds: also the centre's choice.
    assert_eq!(without.len(), 2);
    let nowhere = vec![[5.0, 0.0, 20.0]];
    assert_eq!(
        scans_below(&[shown(&nowhere)], &scans, &cam, &settings),
        without
    );
    // Degenerate points (at the eye, not finite) neither panic nor count.
    let odd = vec![[0.0, 0.0, -30.0], [f64::NAN, 0.0, 4.0], [f64::INFINITY; 3]];
    assert_eq!(
        scans_below(&[shown(&odd)], &scans, &cam, &settings),
        without
    );
}

#[test]
fn demand_points_bring_in_an_untried_scan_holding_them_beyond_the_tile_s_slots() {
    use crate::tiles::coverage::{DemandPoint, MAX_TRIED};
    // Scans at x = 0..19, each 2 m wide; the camera at x = 0 ranks the near ones
    // first, so the tile's two slots go to scans far from x = 15.5.
    let scans: Vec<ModelScan> = (0..20u32)
        .map(|i| scan(u64::from(i), f64::from(i)))
        .collect();
    let settings = HybridSettings {
        scans_per_tile: 2,
        feedback_scans_per_tile: 1,
        margin_m: 0.0,
        ..HybridSettings::default()
    };
    let cam = camera(0.0);
    let base = scans_below(&[tile(0.0, 20.0)], &scans, &cam, &settings);
    assert_eq!(base.len(), 2);
    assert!(!base.contains(&15) && !base.contains(&16), "{base:?}");
    let point = |tried: Vec<u64>| DemandPoint {
        at_m: [15.5, 0.0, 3.0],
        tried,
        seen: 1,
    };
    let with = |demand: &[DemandPoint]| {
        let shown = ShownTile {
            info: tile(0.0, 20.0).info,
            samples_m: &[],
            demand,
        };
        scans_below(&[shown], &scans, &cam, &settings)
    };
    // Scans 15 and 16 hold the point; one more slot brings the more reliable in.
    let got = with(&[point(vec![])]);
    assert_eq!(got.len(), 3, "{got:?}");
    let extra: Vec<u64> = got.difference(&base).copied().collect();
    assert!(extra == vec![15] || extra == vec![16], "{extra:?}");
    // That one drawn in vain: the other.
    let other = if extra == vec![15] { 16 } else { 15 };
    let got = with(&[point(extra.clone())]);
    assert_eq!(
        got.difference(&base).copied().collect::<Vec<_>>(),
        vec![other]
    );
    // Both tried, or the point given up: nothing more.
    assert_eq!(with(&[point(vec![15, 16])]), base);
    assert_eq!(
        with(&[point((100..100 + MAX_TRIED as u64).collect())]),
        base
    );
    // Out of view, or the feedback off: nothing more.
    let mut behind = point(vec![]);
    behind.at_m[2] = -40.0;
    assert_eq!(with(&[behind]), base);
    let off = HybridSettings {
        feedback_scans_per_tile: 0,
        ..settings
    };
    let shown = ShownTile {
        info: tile(0.0, 20.0).info,
        samples_m: &[],
        demand: &[point(vec![])],
    };
    assert_eq!(scans_below(&[shown], &scans, &cam, &off), base);
}

#[test]
fn drawn_holding_lists_the_drawn_scans_whose_box_holds_a_point() {
    let scans: Vec<ModelScan> = (0..5u32)
        .map(|i| scan(u64::from(i), 2.0 * f64::from(i)))
        .collect();
    let holding = drawn_holding(&scans, &BTreeSet::from([1u64, 2, 3]), 0.0);
    // x = 3.5 lies in scan 2's box only (x 3..5); scan 1 (1..3) ends before it.
    assert_eq!(holding([3.5, 0.0, 3.0]), vec![2]);
    // x = 1.5 lies in scans 0 and 1; 0 was not drawn.
    assert_eq!(holding([1.5, 0.0, 3.0]), vec![1]);
    assert!(holding([1.5, 0.0, 9.0]).is_empty());
    assert!(holding([f64::NAN, 0.0, 3.0]).is_empty());
}
