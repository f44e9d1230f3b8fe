//! Selection on a real hierarchy (a street): for any view and any set of resident
//! tiles the drawn set has no hole and no overlap, draws only resident tiles in view,
//! and asks only for missing ones; an overview draws the root, a close view draws
//! leaves where it looks; hysteresis holds a refined tile at the threshold.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![allow(clippy::needless_range_loop)] // x, y and z side by side read clearer indexed

mod support;

use std::collections::BTreeSet;
use std::sync::OnceLock;

use proptest::prelude::*;
use texel_lod::select::{in_frustum, projected_error_px};
use texel_lod::{Hierarchy, Lens, LodConfig, SelectConfig, TileId, TileIndex, View, select};

fn street() -> &'static Hierarchy {
    static STREET: OnceLock<Hierarchy> = OnceLock::new();
    STREET.get_or_init(|| {
        support::street(
            120.0,
            [0.0; 3],
            &LodConfig {
                tile_voxels: 64,
                tile_triangle_budget: 2_000,
                ..LodConfig::default()
            },
        )
    })
}

const LENS: Lens = Lens {
    fov_y_rad: 1.0,
    aspect: 1.5,
    near_m: 0.1,
    far_m: 5_000.0,
    viewport_height_px: 720.0,
};

fn view(eye: [f64; 3], target: [f64; 3]) -> View {
    View::looking_at(eye, target, [0.0, 0.0, 1.0], &LENS).unwrap()
}

/// Checks the invariants of Liu §4.3.2 for one selection.
fn check(h: &Hierarchy, v: &View, resident: &BTreeSet<TileId>, config: &SelectConfig) {
    let sel = select(h, v, &|id| resident.contains(&id), &BTreeSet::new(), config);
    for id in &sel.draw {
        assert!(resident.contains(id), "{id:?} drawn but not resident");
        assert!(
            in_frustum(v, &h.tile(*id).unwrap()),
            "{id:?} drawn out of view"
        );
    }
    for a in &sel.draw {
        for b in &sel.draw {
            assert!(a == b || !a.is_within(*b), "{a:?} drawn inside {b:?}");
        }
    }
    for id in &sel.wanted {
        assert!(!resident.contains(id), "{id:?} wanted but resident");
    }
    // No hole: every leaf in view is covered by exactly one drawn tile (itself or an
    // ancestor), as long as the top tiles are in.
    for leaf in h.nodes.keys().filter(|id| id.lod == 0) {
        if !in_frustum(v, &h.tile(*leaf).unwrap()) {
            continue;
        }
        let covering = sel.draw.iter().filter(|d| leaf.is_within(**d)).count();
        assert_eq!(covering, 1, "leaf {leaf:?} covered {covering} times");
    }
}

#[test]
fn an_overview_draws_the_root_and_a_close_view_draws_leaves_where_it_looks() {
    let h = street();
    let all: BTreeSet<TileId> = h.nodes.keys().copied().collect();
    let config = SelectConfig::default();
    let far = view([60.0, -3_000.0, 2_000.0], [60.0, 0.0, 0.0]);
    let sel = select(h, &far, &|id| all.contains(&id), &BTreeSet::new(), &config);
    assert_eq!(sel.draw, h.roots());
    let close = view([60.0, 0.0, 1.6], [70.0, 0.0, 1.6]);
    let sel = select(
        h,
        &close,
        &|id| all.contains(&id),
        &BTreeSet::new(),
        &config,
    );
    // The tile under the eye is a leaf; far down the street coarser tiles stand in.
    assert!(sel.draw.iter().any(|id| id.lod == 0));
    assert!(sel.draw.iter().any(|id| id.lod > 0), "{:?}", sel.draw);
    check(h, &close, &all, &config);
}

#[test]
fn a_parent_stays_until_every_child_in_view_is_resident() {
    let h = street();
    let close = view([60.0, 0.0, 1.6], [70.0, 0.0, 1.6]);
    let config = SelectConfig::default();
    // Only the top two levels are in: they are drawn, the level below is wanted.
    let top = h.top_lod;
    assert!(top >= 2);
    let resident: BTreeSet<TileId> = h
        .nodes
        .keys()
        .filter(|id| id.lod + 1 >= top)
        .copied()
        .collect();
    let sel = select(
        h,
        &close,
        &|id| resident.contains(&id),
        &BTreeSet::new(),
        &config,
    );
    assert!(sel.draw.iter().all(|id| id.lod + 1 >= top));
    assert!(sel.wanted.iter().all(|id| id.lod + 2 == top) && !sel.wanted.is_empty());
    check(h, &close, &resident, &config);
    // With nothing in, only the top tiles in view are wanted.
    let sel = select(h, &close, &|_| false, &BTreeSet::new(), &config);
    assert!(sel.draw.is_empty());
    assert!(!sel.wanted.is_empty());
    assert!(
        sel.wanted.iter().all(|id| id.lod == top),
        "{:?}",
        sel.wanted
    );
}

#[test]
fn hysteresis_holds_a_refined_tile_between_the_thresholds() {
    let h = street();
    let all: BTreeSet<TileId> = h.nodes.keys().copied().collect();
    let config = SelectConfig::default();
    let root_id = h.roots()[0];
    let root = h.tile(root_id).unwrap();
    // Walk back along a line until the root's projected error is just under the
    // threshold (but over threshold / hysteresis).
    let mut chosen = None;
    for k in 0..4_000 {
        let d = 10.0 + f64::from(k);
        let v = view([60.0, -d, d * 0.5], [60.0, 0.0, 0.0]);
        let e = projected_error_px(&v, &root, config.centre_weight);
        if e < config.max_error_px && e > config.max_error_px / config.hysteresis {
            chosen = Some(v);
            break;
        }
    }
    let v = chosen.expect("a distance between the thresholds");
    let fresh = select(h, &v, &|id| all.contains(&id), &BTreeSet::new(), &config);
    assert!(fresh.draw.contains(&root_id));
    let held = select(
        h,
        &v,
        &|id| all.contains(&id),
        &BTreeSet::from([root_id]),
        &config,
    );
    assert!(held.refined.contains(&root_id));
    assert!(!held.draw.contains(&root_id));
}

#[test]
fn finest_tiles_still_too_coarse_for_the_view_ask_for_their_scans() {
    let h = street();
    let all: BTreeSet<TileId> = h.nodes.keys().copied().collect();
    let config = SelectConfig::default();
    let far = view([60.0, -3_000.0, 2_000.0], [60.0, 0.0, 0.0]);
    let sel = select(h, &far, &|id| all.contains(&id), &BTreeSet::new(), &config);
    assert!(sel.below_finest.is_empty(), "{:?}", sel.below_finest);
    let close = view([60.0, 0.0, 1.6], [70.0, 0.0, 1.6]);
    let sel = select(
        h,
        &close,
        &|id| all.contains(&id),
        &BTreeSet::new(),
        &config,
    );
    assert!(!sel.below_finest.is_empty());
    for id in &sel.below_finest {
        assert_eq!(id.lod, 0, "{id:?}");
        assert!(sel.draw.contains(id), "{id:?} wants scans but is not drawn");
        assert!(sel.refined.contains(id), "{id:?} not held by hysteresis");
        let e = projected_error_px(&close, &h.tile(*id).unwrap(), config.centre_weight);
        assert!(e > config.max_error_px, "{id:?}: {e} px");
    }
    // Every drawn leaf over the threshold is there: none is left to its tile alone.
    for id in sel.draw.iter().filter(|id| id.lod == 0) {
        let e = projected_error_px(&close, &h.tile(*id).unwrap(), config.centre_weight);
        assert_eq!(
            e > config.max_error_px,
            sel.below_finest.contains(id),
            "{id:?}"
        );
    }
    // Between the thresholds a leaf already showing its scans keeps them.
    let held = select(h, &close, &|id| all.contains(&id), &sel.refined, &config);
    assert!(held.below_finest.is_superset(&sel.below_finest));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn any_view_and_any_residency_gives_no_hole_and_no_overlap(
        eye in (-100.0f64..220.0, -200.0f64..200.0, 0.5f64..400.0),
        target in (0.0f64..120.0, -6.0f64..6.0, 0.0f64..8.0),
        keep in prop::collection::vec(any::<bool>(), 256),
        max_error_px in 0.5f64..20.0,
    ) {
        let h = street();
        let v = View::looking_at([eye.0, eye.1, eye.2], [target.0, target.1, target.2], [0.0, 0.0, 1.0], &LENS);
        prop_assume!(v.is_some());
        let v = v.unwrap();
        let resident: BTreeSet<TileId> = h
            .nodes
            .keys()
            .enumerate()
            .filter(|(i, id)| id.lod == h.top_lod || keep[i % keep.len()])
            .map(|(_, id)| *id)
            .collect();
        let config = SelectConfig { max_error_px, ..SelectConfig::default() };
        check(h, &v, &resident, &config);
    }
}
