//! A registrar restored from the scans and poses an earlier run gave (a resumed
//! session) answers for every restored id at its pose, gives the next scan the next
//! id, and registers the rest of the walk as the uninterrupted registrar does.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod register_support;

use std::sync::Arc;

use register_support::*;
use texel::Pose;
use texel::pose::pose_difference;
use texel_register::{Registrar, RegistrationConfig};

const FRAMES: usize = 40;
const CUT: usize = 22;

fn walk() -> Vec<Pose> {
    (0..FRAMES)
        .map(|k| {
            let a = 0.8 + k as f64 * 0.06;
            look_at([0.3 + 1.8 * a.cos(), 1.6 * a.sin(), 1.7], [0.3, 0.0, 0.6])
        })
        .collect()
}

fn frame(scene: &Scene, s: &texel::Sensor, pose: &Pose, k: usize) -> Arc<texel::TexelScan> {
    let sc = scan(scene, s, pose, 0.005, k as u64 + 1);
    let mut sc = (*sc).clone();
    sc.timestamp_ns = k as u64 * 100_000_000;
    Arc::new(sc)
}

#[test]
fn a_restored_registrar_goes_on_like_the_uninterrupted_one() {
    let s = sensor(48, 48, 0.005);
    let scene = Scene::room();
    let truth = walk();
    let frames: Vec<_> = truth
        .iter()
        .enumerate()
        .map(|(k, t)| frame(&scene, &s, t, k))
        .collect();
    let config = RegistrationConfig::default();

    // The uninterrupted run.
    let mut whole = Registrar::with_anchor(config.clone(), truth[0]);
    for f in &frames {
        assert!(
            whole
                .register(Arc::clone(f), &s.model)
                .status
                .is_registered()
        );
    }

    // A run cut after CUT scans, restored from what it had placed (the poses it had
    // sent: here its poses at the cut), then going on.
    let mut first = Registrar::with_anchor(config.clone(), truth[0]);
    for f in &frames[..CUT] {
        first.register(Arc::clone(f), &s.model);
    }
    let placed: Vec<Pose> = (0..CUT).map(|id| first.pose(id as u64).unwrap()).collect();
    let mut resumed = Registrar::new(config);
    // Restored in an order other than the ids' (a recovered scan is recorded late).
    let mut order: Vec<usize> = (0..CUT).collect();
    order.swap(3, 5);
    for &id in &order {
        resumed.restore(Arc::clone(&frames[id]), &s.model, id as u64, placed[id]);
    }
    assert!(resumed.take_events().is_empty(), "restoring emits nothing");
    for (id, p) in placed.iter().enumerate() {
        let (angle, dist) = pose_difference(&resumed.pose(id as u64).unwrap(), p);
        assert!(angle < 1e-9 && dist < 1e-9, "scan {id}: {dist} m");
    }
    // The restored graph is this run's own: every restored scan is reported as it
    // now hangs, for the recording to derive its pose from its new keyframe's.
    let anchors = resumed.take_anchors();
    assert_eq!(anchors.len(), CUT);
    for a in &anchors {
        let keyframe = resumed.pose(a.keyframe).unwrap();
        let (angle, dist) =
            pose_difference(&(keyframe * a.keyframe_from_scan), &placed[a.id as usize]);
        assert!(angle < 1e-9 && dist < 1e-9, "scan {}: {dist} m", a.id);
        assert_eq!(a.world_from_scan, resumed.pose(a.id).unwrap());
    }
    assert!(resumed.take_anchors().is_empty(), "taken once");
    assert!(resumed.stats().keyframes >= 2, "{:?}", resumed.stats());
    for (k, f) in frames.iter().enumerate().skip(CUT) {
        let r = resumed.register(Arc::clone(f), &s.model);
        assert!(r.status.is_registered(), "frame {k}: {:?}", r.status);
        assert_eq!(r.scan_id, Some(k as u64));
    }
    let mut worst = 0.0f64;
    for (k, t) in truth.iter().enumerate().skip(CUT) {
        let (_, d) = pose_difference(
            &resumed.pose(k as u64).unwrap(),
            &whole.pose(k as u64).unwrap(),
        );
        let (_, e) = pose_difference(&resumed.pose(k as u64).unwrap(), t);
        let (_, w) = pose_difference(&whole.pose(k as u64).unwrap(), t);
        // As close to the truth as the uninterrupted run, give or take 2 cm.
        assert!(
            e < w + 0.02,
            "frame {k}: {e} m from the truth, against {w} m"
        );
        worst = worst.max(d);
    }
    assert!(worst < 0.02, "{worst} m from the uninterrupted run");
}
