//! Residency on the GPU: under a budget that holds what the view needs, evicting and
//! fetching renders the image an unlimited budget renders; under one that does not,
//! the image is partial, the most reliable scans are the ones kept and the left-out
//! count says so.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use std::collections::BTreeSet;

use support::*;
use texel::Pose;
use texel::model::{Model, ModelEvent};
use texel_viewer::composite::Mode;
use texel_viewer::gpu::{RenderSettings, Renderer, scan_gpu_bytes};
use texel_viewer::residency::Residency;
use texel_viewer::scenes;

/// The box scene (scans 0-2, priorities 100, 10, 1) and the same scene again 60 m
/// behind the box camera, turned round (scans 3-5): neither site is in view of the
/// other's camera.
fn two_sites() -> (Model, Pose) {
    let sensor = scenes::test_sensor();
    let scene = scenes::box_scene();
    let poses = scenes::box_scene_poses();
    let away = texel::pose::pose_from_parts([0.0, 0.0, -60.0], [0.0, 1.0, 0.0, 0.0]).unwrap();
    let mut model = scenes::model_of(&scene, &sensor, &poses, &Pose::identity());
    let other = scenes::model_of(&scene, &sensor, &poses, &away);
    for s in other.scans() {
        model
            .apply(ModelEvent::ScanAdded {
                id: model.next_id(),
                scan: s.scan.clone().unwrap(),
                world_from_scan: s.world_from_scan,
            })
            .unwrap();
    }
    for (id, priority) in [(0, 100.0), (1, 10.0), (2, 1.0)] {
        let s = model.get(id).unwrap();
        let mut listing = s.listing;
        listing.priority = priority;
        let world_from_scan = s.world_from_scan;
        model
            .apply(ModelEvent::ScanListed {
                id,
                listing,
                world_from_scan,
            })
            .unwrap();
    }
    (model, away)
}

fn bytes(model: &Model, id: u64) -> u64 {
    scan_gpu_bytes(model.get(id).unwrap().scan.as_ref().unwrap())
}

/// Pixels that are not the (black) background.
fn covered(img: &image::RgbaImage) -> usize {
    img.pixels()
        .filter(|p| p[0] != 0 || p[1] != 0 || p[2] != 0)
        .count()
}

/// A renderer holding exactly the scans `ids` of `model`.
fn renderer_of(model: &Model, ids: &[u64]) -> Renderer {
    let mut r = Renderer::new(gpu());
    for &id in ids {
        let s = model.get(id).unwrap();
        r.add_scan(id, s.scan.as_ref().unwrap(), s.world_from_scan)
            .unwrap();
    }
    r
}

#[test]
fn eviction_and_fetch_within_budget_render_the_unlimited_image() {
    let (full, away) = two_sites();
    let all: Vec<u64> = (0..6).collect();
    let mut unlimited = renderer_of(&full, &all);
    // Room for one site (three scans) but not for a fourth scan.
    let site_bytes: u64 = (0..3).map(|id| bytes(&full, id)).sum();
    let smallest = (0..6).map(|id| bytes(&full, id)).min().unwrap();
    let budget = site_bytes.max((3..6).map(|id| bytes(&full, id)).sum()) + smallest / 2;
    let mut model = full.clone();
    let mut residency = Residency::over_model(budget, &mut model);
    assert_eq!(model.resident_len(), 0);
    let mut r = Renderer::new(gpu());
    // First the other site: its scans come in.
    let there = box_camera(&away);
    let stats = residency.step(&mut model, &mut r, &there);
    assert_eq!(r.scan_ids().collect::<Vec<_>>(), vec![3, 4, 5]);
    assert_eq!((stats.left_out, stats.resident), (0, 3));
    assert!(stats.used_bytes <= budget);
    // The renderer's count of an upload is the one the planner was given.
    for id in 3..6 {
        assert_eq!(r.scan_bytes(id), Some(bytes(&full, id)));
    }
    // Then the box: the other site is evicted (GPU and CPU copies), the box fetched.
    let here = box_camera(&Pose::identity());
    let stats = residency.step(&mut model, &mut r, &here);
    assert_eq!(r.scan_ids().collect::<Vec<_>>(), vec![0, 1, 2]);
    assert_eq!(stats.left_out, 0);
    assert!(
        stats.used_bytes <= budget,
        "{} > {budget}",
        stats.used_bytes
    );
    assert_eq!(stats.evictions, 3);
    let held: BTreeSet<u64> = model.resident().map(|(s, _)| s.id).collect();
    assert_eq!(held, BTreeSet::from([0, 1, 2]));
    assert_eq!(model.len(), 6, "evicted scans stay listed");
    for mode in [Mode::Blended, Mode::ScanColour, Mode::Painter] {
        let s = RenderSettings::with_mode(mode);
        let (want, _) = unlimited.render_to_image(&here, &s).unwrap();
        let (got, frame) = r.render_to_image(&here, &s).unwrap();
        assert_eq!(frame.drawn, 3);
        let within = fraction_within(&want, &got, 2);
        assert!(within >= 0.99, "{mode}: {within}");
    }
    // The same camera again: nothing moves.
    let again = residency.step(&mut model, &mut r, &here);
    assert_eq!(
        (again.evictions, again.uploads),
        (stats.evictions, stats.uploads)
    );
}

#[test]
fn an_insufficient_budget_keeps_the_most_reliable_scans() {
    let (full, _) = two_sites();
    let mut unlimited = renderer_of(&full, &[0, 1, 2, 3, 4, 5]);
    // Room for scans 0 and 1 (the most reliable), not for scan 2 as well.
    let budget = bytes(&full, 0) + bytes(&full, 1) + bytes(&full, 2) / 2;
    let mut model = full.clone();
    let mut residency = Residency::over_model(budget, &mut model);
    let mut r = Renderer::new(gpu());
    let here = box_camera(&Pose::identity());
    let stats = residency.step(&mut model, &mut r, &here);
    assert_eq!(r.scan_ids().collect::<Vec<_>>(), vec![0, 1]);
    assert_eq!((stats.needed, stats.left_out), (3, 1));
    assert!(stats.used_bytes <= budget);
    assert!(
        stats.describe().contains("1 left out"),
        "{}",
        stats.describe()
    );
    let s = RenderSettings::with_mode(Mode::ScanColour);
    let (whole, _) = unlimited.render_to_image(&here, &s).unwrap();
    let (partial, frame) = r.render_to_image(&here, &s).unwrap();
    assert_eq!(frame.drawn, 2);
    let (a, b) = (covered(&whole), covered(&partial));
    assert!(b < a, "partial {b} px, whole {a} px");
    // What is shown is what the two kept scans alone show.
    let (two, _) = renderer_of(&full, &[0, 1])
        .render_to_image(&here, &s)
        .unwrap();
    let within = fraction_within(&two, &partial, 2);
    assert!(within >= 0.99, "{within}");
}
