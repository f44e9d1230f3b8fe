//! The residency planner's properties: never over budget, never leaves a needed scan
//! out while a merely kept one stays or while it would fit, stable under an unchanged
//! camera, and a scan at the edge of the view is kept but not fetched.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::collections::BTreeSet;

use proptest::prelude::*;
use texel::Pose;
use texel::model::ScanListing;
use texel::pose::pose_from_parts;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::residency::{DataState, Plan, PlanOptions, PlanScan, plan};

fn listing(half_m: f32, depth_m: f32, priority: f32) -> ScanListing {
    ScanListing {
        timestamp_ns: 0,
        bounds_min_m: [-half_m, -half_m, depth_m],
        bounds_max_m: [half_m, half_m, depth_m + half_m],
        cop_m: [0.0; 3],
        priority,
        encoded_bytes: 0,
    }
}

/// A scan looking along +z from (x, y, z), yawed by `yaw` radians.
fn placed(x: f64, y: f64, z: f64, yaw: f64) -> Pose {
    let (s, c) = (0.5 * yaw).sin_cos();
    pose_from_parts([x, y, z], [0.0, s, 0.0, c]).unwrap()
}

fn state_of(k: u8) -> DataState {
    match k % 4 {
        0 => DataState::OnGpu,
        1 => DataState::Held,
        2 => DataState::InFlight,
        _ => DataState::Absent,
    }
}

fn scans_strategy() -> impl Strategy<Value = Vec<PlanScan>> {
    prop::collection::vec(
        (
            (-8.0f64..8.0, -2.0f64..2.0, -8.0f64..8.0, -3.2f64..3.2),
            (
                0.2f32..3.0,
                0.5f32..6.0,
                prop_oneof![Just(0.0f32), 0.1f32..10.0],
            ),
            (1u64..120, 0u8..4),
        ),
        0..40,
    )
    .prop_map(|v| {
        v.into_iter()
            .enumerate()
            .map(
                |(i, ((x, y, z, yaw), (half, depth, priority), (bytes, state)))| PlanScan {
                    id: i as u64 * 3 + 1,
                    listing: listing(half, depth, priority),
                    world_from_scan: placed(x, y, z, yaw),
                    bytes,
                    state: state_of(state),
                },
            )
            .collect()
    })
}

fn camera_strategy() -> impl Strategy<Value = VirtualCamera> {
    (-6.0f64..6.0, -6.0f64..6.0, -3.2f64..3.2, 20.0f64..90.0).prop_map(|(x, z, yaw, fov)| {
        VirtualCamera::new(placed(x, 0.0, z, yaw), fov, 160, 120).unwrap()
    })
}

/// The states after a plan is carried out and every fetch has arrived.
fn carried_out(scans: &[PlanScan], p: &Plan) -> Vec<PlanScan> {
    let selected: BTreeSet<u64> = p.selected.iter().copied().collect();
    scans
        .iter()
        .map(|s| PlanScan {
            state: if selected.contains(&s.id) {
                DataState::OnGpu
            } else if s.state == DataState::InFlight {
                DataState::InFlight
            } else {
                DataState::Absent
            },
            ..*s
        })
        .collect()
}

fn bytes_of(scans: &[PlanScan], id: u64) -> u64 {
    scans.iter().find(|s| s.id == id).unwrap().bytes
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn plans_respect_the_budget_and_the_need(
        scans in scans_strategy(),
        camera in camera_strategy(),
        budget in 0u64..600,
    ) {
        let options = PlanOptions::new(budget);
        let p = plan(&scans, &camera, &options);
        let sum: u64 = p.selected.iter().map(|&id| bytes_of(&scans, id)).sum();
        prop_assert_eq!(sum, p.selected_bytes);
        prop_assert!(p.selected_bytes <= budget, "{} > {budget}", p.selected_bytes);
        let selected: BTreeSet<u64> = p.selected.iter().copied().collect();
        prop_assert_eq!(selected.len(), p.selected.len());
        // The needed scans come first; any scan after them is merely kept, and none
        // is while a needed scan is left out.
        let needed_fit = p.needed - p.left_out.len();
        prop_assert!(p.selected.len() >= needed_fit);
        if !p.left_out.is_empty() {
            prop_assert_eq!(p.selected.len(), needed_fit);
        }
        // Nothing needed is left out that would still fit.
        for &id in &p.left_out {
            prop_assert!(!selected.contains(&id));
            prop_assert!(p.selected_bytes + bytes_of(&scans, id) > budget);
        }
        // Evictions are of held scans not selected; fetches of absent selected ones.
        for &id in &p.evict {
            let s = scans.iter().find(|s| s.id == id).unwrap();
            prop_assert!(matches!(s.state, DataState::OnGpu | DataState::Held));
            prop_assert!(!selected.contains(&id));
        }
        for s in &scans {
            if matches!(s.state, DataState::OnGpu | DataState::Held) && !selected.contains(&s.id) {
                prop_assert!(p.evict.contains(&s.id));
            }
        }
        let in_flight = scans.iter().filter(|s| s.state == DataState::InFlight).count();
        prop_assert!(p.fetch.len() + in_flight <= options.max_in_flight.max(in_flight));
        for &id in &p.fetch {
            prop_assert!(selected.contains(&id));
            prop_assert_eq!(scans.iter().find(|s| s.id == id).unwrap().state, DataState::Absent);
        }
        // Deterministic.
        prop_assert_eq!(&plan(&scans, &camera, &options), &p);
    }

    #[test]
    fn plans_are_stable_under_an_unchanged_camera(
        scans in scans_strategy(),
        camera in camera_strategy(),
        budget in 0u64..600,
    ) {
        let options = PlanOptions::new(budget);
        let first = plan(&scans, &camera, &options);
        let after = carried_out(&scans, &first);
        let second = plan(&after, &camera, &options);
        // Carrying a plan out and planning again changes nothing: the same scans,
        // nothing evicted, nothing fetched.
        let a: BTreeSet<u64> = first.selected.iter().copied().collect();
        let b: BTreeSet<u64> = second.selected.iter().copied().collect();
        prop_assert_eq!(a, b);
        prop_assert!(second.evict.is_empty(), "{:?}", second.evict);
        prop_assert!(second.fetch.is_empty(), "{:?}", second.fetch);
        let third = plan(&carried_out(&after, &second), &camera, &options);
        prop_assert_eq!(third, second);
    }
}

/// A scan just outside the view: fetched while the widened view holds it, kept (not
/// evicted) a little further out, and neither fetched nor kept far out.
#[test]
fn a_scan_at_the_edge_is_kept_but_not_fetched() {
    let scan = |state| PlanScan {
        id: 7,
        // A small box 6 m ahead, acquired from where the camera is.
        listing: listing(0.3, 6.0, 1.0),
        world_from_scan: Pose::identity(),
        bytes: 10,
        state,
    };
    let options = PlanOptions::new(1000);
    // Camera at the origin looking along +z, yawed so the box is at `angle_deg`
    // off-axis (horizontal field of view ~ 66 deg: half 33 deg).
    let at = |angle_deg: f64| {
        VirtualCamera::new(
            placed(0.0, 0.0, 0.0, angle_deg.to_radians()),
            50.0,
            160,
            120,
        )
        .unwrap()
    };
    let selected = |angle: f64, state| plan(&[scan(state)], &at(angle), &options).selected;
    // In view, and in the widened view: fetched.
    assert_eq!(selected(20.0, DataState::Absent), vec![7]);
    assert_eq!(
        plan(&[scan(DataState::Absent)], &at(20.0), &options).fetch,
        vec![7]
    );
    assert_eq!(selected(39.0, DataState::Absent), vec![7]);
    // Beyond the widened view but within the keep band: kept if here, not fetched.
    assert_eq!(selected(48.0, DataState::OnGpu), vec![7]);
    assert!(selected(48.0, DataState::Absent).is_empty());
    // Far out: evicted.
    let far = plan(&[scan(DataState::OnGpu)], &at(90.0), &options);
    assert!(far.selected.is_empty());
    assert_eq!(far.evict, vec![7]);
}

/// Two scans the view needs and room for one: the one held stays against a newcomer
/// that ranks higher by less than the stickiness, and gives way to a clearly better
/// one.
#[test]
fn a_held_scan_gives_way_only_to_a_clearly_better_one() {
    let camera = VirtualCamera::new(Pose::identity(), 50.0, 160, 120).unwrap();
    let options = PlanOptions::new(10);
    let scan = |id, priority, state| PlanScan {
        id,
        listing: listing(0.5, 5.0, priority),
        world_from_scan: Pose::identity(),
        bytes: 10,
        state,
    };
    let held = scan(1, 1.0, DataState::OnGpu);
    let p = plan(&[held, scan(2, 1.2, DataState::Absent)], &camera, &options);
    assert_eq!((p.selected, p.left_out), (vec![1], vec![2]));
    assert!(p.evict.is_empty() && p.fetch.is_empty());
    let p = plan(&[held, scan(2, 1.5, DataState::Absent)], &camera, &options);
    assert_eq!((p.selected, p.evict, p.fetch), (vec![2], vec![1], vec![2]));
}
