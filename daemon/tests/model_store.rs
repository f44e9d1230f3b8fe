//! The hub as a model store: memory within its budget whatever the number of scans,
//! frames read back from the on-disk store byte for byte, redundant scans kept out of
//! the served model and brought back by a pose revision, fetched scans never landing
//! with a stale pose or after their withdrawal.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::sync::Arc;

use bytes::Bytes;
use texel::coverage::{CoverageConfig, ScanCoverage};
use texel::model::ScanListing;
use texel::wire::{Limits, Message, decode_frame};
use texel::{FuseConfig, Pose, Sensor, TexelScan, fuse};
use texel_daemon::hub::{FetchError, Hub, HubError, ModelOptions};
use texel_daemon::pipeline::encode::encode_scan;
use texel_daemon::shelf::ShelfFiles;
use texel_daemon::store::Store;
use texel_e2e::captures;

fn scan(i: u32) -> Arc<TexelScan> {
    let m = captures::sensor();
    let (range, eo) = captures::frame(&m, i, captures::timestamp(i, 50_000_000));
    Arc::new(fuse(&range, eo, &Sensor::new(m), &FuseConfig::default()).unwrap())
}

fn frame(id: u64, scan: &TexelScan, pose: Pose) -> Bytes {
    encode_scan(id, scan, pose, texel::wire::TextureFormat::Rgb8, 0).unwrap()
}

fn decode(frame: &[u8]) -> Message {
    decode_frame(frame, &Limits::FROM_SERVER)
        .unwrap()
        .unwrap()
        .0
}

#[test]
fn memory_stays_within_the_budget_and_evicted_frames_read_back_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::create(&dir.path().join("m.scans")).unwrap());
    let s = scan(0);
    let one = frame(0, &s, Pose::identity()).len() as u64;
    let hub = Hub::with_model(
        16,
        ModelOptions {
            memory_budget_bytes: 3 * one + one / 2,
            store: Some(Arc::clone(&store)),
            coverage: None,
            shelf: None,
            ..ModelOptions::default()
        },
    );
    let mut frames = Vec::new();
    for id in 0..10u64 {
        let pose = Pose::translation(id as f64, 0.0, 0.0);
        let f = frame(id, &s, pose);
        store.append(id, &f).unwrap();
        hub.add_scan(
            id,
            ScanListing::of_scan(&s, f.len() as u64, 1.0),
            pose,
            f.clone(),
            true,
            None,
        )
        .unwrap();
        frames.push(f);
        let status = hub.status();
        assert!(status.in_memory <= 3, "{status:?}");
    }
    let status = hub.status();
    assert_eq!((status.scans, status.served, status.in_memory), (10, 10, 3));
    assert_eq!(status.on_disk, 7);
    // The newest three are in memory: asking for them reads nothing.
    for id in 7..10u64 {
        assert_eq!(
            hub.fetch_scan(id).unwrap(),
            frames[id as usize],
            "scan {id}"
        );
    }
    assert_eq!(hub.status().store_reads, 0);
    // The oldest left memory; asking reads them back, exactly as served.
    for id in 0..7u64 {
        assert_eq!(
            hub.fetch_scan(id).unwrap(),
            frames[id as usize],
            "scan {id}"
        );
        assert!(hub.status().in_memory <= 3);
    }
    assert_eq!(hub.status().store_reads, 7);
    // The least recently requested went to make room: 7, 8 and 9 now read back too.
    hub.fetch_scan(7).unwrap();
    assert_eq!(hub.status().store_reads, 8);
    assert!(matches!(hub.fetch_scan(99), Err(FetchError::Unknown(99))));
}

/// A shelf for retired scans' entries in `dir`, when `on`.
fn shelf(dir: &std::path::Path, on: bool) -> Option<Arc<ShelfFiles>> {
    on.then(|| ShelfFiles::create_in(dir).unwrap())
}

#[test]
fn a_redundant_scan_is_not_served_until_a_revision_makes_it_useful() {
    for shelved in [false, true] {
        redundant_scan_returns(shelved);
    }
}

fn redundant_scan_returns(shelved: bool) {
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::create(&dir.path().join("m.scans")).unwrap());
    let config = CoverageConfig::default();
    let hub = Hub::with_model(
        64,
        ModelOptions {
            memory_budget_bytes: u64::MAX,
            store: Some(Arc::clone(&store)),
            coverage: Some(config),
            shelf: shelf(dir.path(), shelved),
            ..ModelOptions::default()
        },
    );
    let mut sub = hub.subscribe().unwrap();
    let s = scan(3);
    let add = |id: u64, pose: Pose| {
        let f = frame(id, &s, pose);
        store.append(id, &f).unwrap();
        let coverage = ScanCoverage::of(&s, &config);
        let listing = ScanListing::of_scan(&s, f.len() as u64, coverage.score() as f32);
        hub.add_scan(id, listing, pose, f, true, Some(coverage))
            .unwrap();
    };
    // The same view twice: the second adds nothing.
    add(0, Pose::identity());
    add(1, Pose::identity());
    assert!(hub.is_served(0) && !hub.is_served(1));
    let status = hub.status();
    assert_eq!((status.served, status.retired), (1, 1));
    assert_eq!(hub.shelved(), if shelved { (1, 1) } else { (0, 0) });
    assert!(matches!(
        hub.add_scan(
            1,
            ScanListing::of_scan(&s, 1, 1.0),
            Pose::identity(),
            Bytes::new(),
            true,
            None
        ),
        Err(HubError::Duplicate(1))
    ));
    // Viewers saw scan 0 only; a request for scan 1 is refused.
    assert!(matches!(decode(&sub.live.try_recv().unwrap()), Message::ScanAdded(w) if w.id == 0));
    assert!(sub.live.try_recv().is_err());
    assert!(matches!(hub.fetch_scan(1), Err(FetchError::Withdrawn(1))));
    let snapshot = hub.subscribe().unwrap().snapshot;
    assert_eq!(snapshot.len(), 3, "reset, one listing, complete");

    // Scan 0 turns out to be elsewhere: scan 1 is the only view of its surfaces again.
    hub.revise_pose(0, Pose::translation(50.0, 0.0, 0.0))
        .unwrap();
    let mut listed = false;
    while let Ok(f) = sub.live.try_recv() {
        if let Message::ScanListed { id: 1, .. } = decode(&f) {
            listed = true;
        }
    }
    assert!(listed, "scan 1 was listed again");
    assert!(hub.is_served(1));
    assert_eq!(
        hub.shelved(),
        (0, 0),
        "a scan served again leaves the shelf"
    );
    // It is served from the store, then with its pose.
    let fetched = hub.fetch_scan(1).unwrap();
    assert_eq!(fetched, frame(1, &s, Pose::identity()));
}

#[test]
fn a_retired_scans_signature_is_read_back_from_the_store_on_a_revision() {
    for shelved in [false, true] {
        signature_read_back(shelved);
    }
}

fn signature_read_back(shelved: bool) {
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::create(&dir.path().join("m.scans")).unwrap());
    let config = CoverageConfig::default();
    let hub = Hub::with_model(
        64,
        ModelOptions {
            memory_budget_bytes: u64::MAX,
            store: Some(Arc::clone(&store)),
            coverage: Some(config),
            shelf: shelf(dir.path(), shelved),
            ..ModelOptions::default()
        },
    );
    let s = scan(3);
    let add = |id: u64, in_store: bool| {
        let f = frame(id, &s, Pose::identity());
        if in_store {
            store.append(id, &f).unwrap();
        }
        let coverage = ScanCoverage::of(&s, &config);
        let listing = ScanListing::of_scan(&s, f.len() as u64, coverage.score() as f32);
        hub.add_scan(id, listing, Pose::identity(), f, true, Some(coverage))
            .unwrap();
    };
    add(0, true);
    add(1, true);
    add(2, false);
    assert!(hub.is_served(0) && !hub.is_served(1) && !hub.is_served(2));
    // Revised where they were: scan 1's signature comes back from the store and it
    // stays redundant; scan 2's frame is in no store, so it cannot be judged and is
    // served again rather than left out on a guess.
    hub.revise_pose(1, Pose::identity()).unwrap();
    assert!(!hub.is_served(1), "scan 1 judged on its stored signature");
    hub.revise_pose(2, Pose::identity()).unwrap();
    assert!(
        hub.is_served(2),
        "scan 2 served again without its signature"
    );
}

#[test]
fn with_a_shelf_retired_scans_leave_memory_and_keep_their_poses() {
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::create(&dir.path().join("m.scans")).unwrap());
    let config = CoverageConfig::default();
    let index_bytes = |shelved: bool, copies: u64| {
        let hub = Hub::with_model(
            64,
            ModelOptions {
                memory_budget_bytes: u64::MAX,
                store: Some(Arc::clone(&store)),
                coverage: Some(config),
                shelf: shelf(dir.path(), shelved),
                ..ModelOptions::default()
            },
        );
        let s = scan(3);
        let coverage = ScanCoverage::of(&s, &config);
        for id in 0..=copies {
            // Copies a millimetre apart: each redundant, each with its own pose.
            let pose = Pose::translation(id as f64 * 1e-3, 0.0, 0.0);
            let f = frame(id, &s, pose);
            store.append(id, &f).unwrap();
            let listing = ScanListing::of_scan(&s, f.len() as u64, coverage.score() as f32);
            hub.add_scan(id, listing, pose, f, true, Some(coverage.clone()))
                .unwrap();
        }
        let status = hub.status();
        assert_eq!(status.scans, copies + 1);
        assert!(status.served <= 3, "{status:?}");
        assert_eq!(status.retired, copies + 1 - status.served);
        if shelved {
            assert_eq!(hub.shelved(), (status.retired, status.retired));
            assert_eq!(status.on_disk, status.retired);
        }
        // A revision of a shelved scan reaches it, and it stays retired; the first
        // scan moved far away brings one copy back with its own pose.
        hub.revise_pose(copies, Pose::translation(copies as f64 * 1e-3, 0.0, 1e-4))
            .unwrap();
        assert!(!hub.is_served(copies));
        let index_bytes = hub.memory_bytes().0;
        let mut sub = hub.subscribe().unwrap();
        hub.revise_pose(0, Pose::translation(80.0, 0.0, 0.0))
            .unwrap();
        let mut relisted = Vec::new();
        while let Ok(f) = sub.live.try_recv() {
            if let Message::ScanListed {
                id,
                world_from_scan,
                ..
            } = decode(&f)
            {
                let expected =
                    Pose::translation(id as f64 * 1e-3, 0.0, if id == copies { 1e-4 } else { 0.0 });
                assert_eq!(world_from_scan, expected, "scan {id}'s pose came back");
                relisted.push(id);
            }
        }
        assert!(!relisted.is_empty(), "a copy stands in for the moved scan");
        assert_eq!(hub.scan_count() as u64, copies + 1);
        (index_bytes, status.served, relisted)
    };
    // The shelf changes no decision. In memory the index grows with the retired
    // scans' entries; with the shelf only with their links to their witnesses (8
    // bytes each) and the shelf's index pages, which fill up to a fixed number of
    // pages (16 bytes a scan until then, then nothing).
    let kept = (index_bytes(false, 40), index_bytes(false, 400));
    let shelved = (index_bytes(true, 40), index_bytes(true, 400));
    assert_eq!((&kept.0.1, &kept.0.2), (&shelved.0.1, &shelved.0.2));
    assert_eq!((&kept.1.1, &kept.1.2), (&shelved.1.1, &shelved.1.2));
    assert!(kept.1.0 > kept.0.0 + 360 * 200, "in memory: {kept:?}");
    assert!(shelved.1.0 < shelved.0.0 + 360 * 64, "shelved: {shelved:?}");
    assert!(
        shelved.1.0 - shelved.0.0 < (kept.1.0 - kept.0.0) / 4,
        "{kept:?} {shelved:?}"
    );
}

#[test]
fn a_fetched_scan_carries_its_current_pose() {
    let hub = Hub::new(16);
    let s = scan(1);
    let f = frame(0, &s, Pose::identity());
    hub.add_scan(
        0,
        ScanListing::of_scan(&s, 1, 1.0),
        Pose::identity(),
        f.clone(),
        false,
        None,
    )
    .unwrap();
    let fetched = hub.fetch_scan(0).unwrap();
    assert_eq!(
        hub.finish_fetch(0, fetched.clone()).unwrap(),
        vec![f.clone()]
    );
    let moved = Pose::translation(0.0, 2.0, 0.0);
    hub.revise_pose(0, moved).unwrap();
    let frames = hub.finish_fetch(0, fetched).unwrap();
    assert_eq!(frames.len(), 2);
    assert!(matches!(
        decode(&frames[1]),
        Message::PoseRevised { id: 0, world_from_scan } if world_from_scan == moved
    ));
}
