//! Scan retirement on synthetic scans of a few planes: retirement never removes the
//! only scan covering a surface cell, follows pose revisions, and keeps one of
//! identical duplicates.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::collections::BTreeSet;
use std::sync::Arc;

use nalgebra::{Point3, Vector3};
use proptest::prelude::*;
use texel::coverage::{CoverageConfig, MemoryShelf, Retirement, ScanCoverage, Shelf, ShelfError};
use texel::model::ScanId;
use texel::pose::look_at;
use texel::scan::{NO_VERTEX, TexelScan, TriangleFlags};
use texel::{EoFrame, Pose, RangeNoise};

/// World planes `n . x = c`: the floor and two walls.
const PLANES: [([f64; 3], f64); 3] = [
    ([0.0, 0.0, 1.0], 0.0),
    ([0.0, 1.0, 0.0], 3.0),
    ([1.0, 0.0, 0.0], 3.0),
];

/// A `size` x `size` lidar scan (60 degree field of view) of the planes from
/// `world_from_scan`, in the scan frame; the nearest plane along each ray is hit.
fn synthetic_scan(world_from_scan: &Pose, size: u32) -> TexelScan {
    let n = size as usize;
    let focal = (size as f64 / 2.0) / 30f64.to_radians().tan();
    let origin = world_from_scan.translation.vector;
    let mut vertices = Vec::new();
    let mut pixel_vertex = vec![NO_VERTEX; n * n];
    let mut vertex_pixel = Vec::new();
    let mut vertex_plane = Vec::new();
    for y in 0..n {
        for x in 0..n {
            let d = Vector3::new(
                (x as f64 + 0.5 - n as f64 / 2.0) / focal,
                (y as f64 + 0.5 - n as f64 / 2.0) / focal,
                1.0,
            );
            let dw = world_from_scan.rotation * d;
            let hit = PLANES
                .iter()
                .enumerate()
                .filter_map(|(i, (pn, c))| {
                    let pn = Vector3::from(*pn);
                    let t = (c - pn.dot(&origin)) / pn.dot(&dw);
                    (t.is_finite() && t > 0.05 && t < 20.0).then_some((t, i))
                })
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((t, plane)) = hit {
                let p = d * t;
                pixel_vertex[y * n + x] = vertices.len() as u32;
                vertex_pixel.push((y * n + x) as u32);
                vertices.push([p.x as f32, p.y as f32, p.z as f32]);
                vertex_plane.push(plane);
            }
        }
    }
    let (mut triangles, mut accuracy, mut flags) = (Vec::new(), Vec::new(), Vec::new());
    for y in 0..n.saturating_sub(1) {
        for x in 0..n.saturating_sub(1) {
            let q = [
                pixel_vertex[y * n + x],
                pixel_vertex[y * n + x + 1],
                pixel_vertex[(y + 1) * n + x],
                pixel_vertex[(y + 1) * n + x + 1],
            ];
            if q.contains(&NO_VERTEX) {
                continue;
            }
            let planes: BTreeSet<usize> = q.iter().map(|&v| vertex_plane[v as usize]).collect();
            let stretched = planes.len() > 1;
            for tri in [[q[0], q[2], q[1]], [q[1], q[2], q[3]]] {
                let v = |i: u32| Vector3::from(vertices[i as usize].map(f64::from));
                let (a, b, c) = (v(tri[0]), v(tri[1]), v(tri[2]));
                let normal = (b - a).cross(&(c - a));
                let centre = (a + b + c) / 3.0;
                let acc = if normal.norm() > 1e-12 && centre.norm() > 1e-12 {
                    normal.normalize().dot(&(-centre.normalize())).abs()
                } else {
                    0.0
                };
                triangles.push(tri);
                accuracy.push(acc as f32);
                flags.push(TriangleFlags(if stretched {
                    TriangleFlags::STRETCHED
                } else {
                    0
                }));
            }
        }
    }
    let count = vertices.len();
    TexelScan {
        timestamp_ns: 0,
        seq: 0,
        grid_width: size,
        grid_height: size,
        vertices,
        tex_coords: vec![[0.0, 0.0]; count],
        vertex_textured: vec![false; count],
        vertex_pixel,
        pixel_vertex,
        triangles,
        triangle_accuracy: accuracy,
        triangle_flags: flags,
        texture: Arc::new(EoFrame {
            width: 1,
            height: 1,
            rgb: vec![0; 3],
            timestamp_ns: 0,
            exposure: None,
        }),
        cop_m: [0.0; 3],
        scan_from_lidar: Pose::identity(),
        range_noise: RangeNoise::default(),
    }
}

fn config() -> CoverageConfig {
    CoverageConfig {
        cell_m: 0.5,
        sample_stride_px: 2,
        angle_tolerance_deg: 20.0,
        ..CoverageConfig::default()
    }
}

fn pose(eye: [f64; 3], target: [f64; 3]) -> Pose {
    look_at(Point3::from(eye), Point3::from(target), Vector3::z())
}

/// The cells of every scan of `ids`, at their current poses.
fn cells(index: &Retirement, ids: impl Iterator<Item = ScanId>) -> BTreeSet<[i64; 3]> {
    ids.flat_map(|id| index.cells_of(id)).collect()
}

/// Every retired scan's cells are covered by served scans, and its witnesses are
/// served; the union of served cells is the union of all cells.
fn check_invariants(index: &Retirement, n: u64) {
    let all = cells(index, 0..n);
    let served = cells(index, (0..n).filter(|&i| !index.is_retired(i)));
    assert_eq!(all, served, "a cell lost its only served scan");
    for id in (0..n).filter(|&i| index.is_retired(i)) {
        let witnesses = index.witnesses_of_retired(id);
        assert!(witnesses.iter().all(|&w| !index.is_retired(w)));
        let witness_cells = cells(index, witnesses.into_iter());
        for c in index.cells_of(id) {
            assert!(
                witness_cells.contains(&c),
                "scan {id}: cell {c:?} unwitnessed"
            );
        }
    }
    assert_eq!(
        index.served() + index.retired(),
        n as usize,
        "served and retired counts"
    );
}

fn arb_pose() -> impl Strategy<Value = Pose> {
    (
        (-1.0..2.0f64, -1.0..2.0f64, 0.6..2.0f64),
        (0.5..3.0f64, 0.5..3.0f64, 0.0..1.5f64),
    )
        .prop_map(|((x, y, z), (tx, ty, tz))| pose([x, y, z], [tx, ty, tz]))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn retirement_never_removes_the_only_scan_of_a_cell(
        poses in prop::collection::vec(arb_pose(), 2..12),
        duplicates in prop::collection::vec(0usize..12, 0..4),
        revisions in prop::collection::vec((0usize..16, arb_pose()), 0..6),
        nudges in prop::collection::vec((0usize..16, -0.003..0.003f64, -0.003..0.003f64), 0..8),
        angle_deg in 0.0..40.0f64,
        margin in 0.0..0.3f64,
        budget in 1usize..40,
        strongest in any::<bool>(),
    ) {
        let config = CoverageConfig {
            angle_tolerance_deg: angle_deg,
            reliability_margin: margin,
            max_checks_per_call: budget,
            strongest_candidates_first: strongest,
            ..config()
        };
        let mut all_poses = poses.clone();
        all_poses.extend(duplicates.iter().map(|&i| poses[i % poses.len()]));
        let scans: Vec<TexelScan> = all_poses.iter().map(|p| synthetic_scan(p, 12)).collect();
        let mut index = Retirement::new(config);
        for (i, (scan, p)) in scans.iter().zip(&all_poses).enumerate() {
            index.add(i as ScanId, ScanCoverage::of(scan, &config), p);
            check_invariants(&index, i as u64 + 1);
        }
        let n = scans.len() as u64;
        for (i, p) in &revisions {
            index.revise(*i as u64 % n, p);
            all_poses[*i % scans.len()] = *p;
            check_invariants(&index, n);
        }
        // Millimetre revisions, as a loop closure makes: revalidation keeps most
        // retired scans' witnesses, and must never keep one that no longer holds.
        for (i, dx, dz) in &nudges {
            let k = *i % scans.len();
            let mut p = all_poses[k];
            p.translation.vector.x += dx;
            p.translation.vector.z += dz;
            index.revise(k as u64, &p);
            all_poses[k] = p;
            check_invariants(&index, n);
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// An index that sheds retired scans' signatures and loads them back on a
    /// revision decides exactly as one that keeps every signature, loads only for
    /// scans it shed, and holds no retired scan's signature between calls. One that
    /// also shelves its retired scans decides the same again, and holds no retired
    /// scan in memory between calls.
    #[test]
    fn shedding_signatures_changes_no_decision(
        poses in prop::collection::vec(arb_pose(), 2..10),
        duplicates in prop::collection::vec(0usize..10, 0..4),
        revisions in prop::collection::vec((0usize..14, arb_pose()), 1..8),
        budget in 1usize..40,
    ) {
        let config = CoverageConfig { max_checks_per_call: budget, ..config() };
        let mut all_poses = poses.clone();
        all_poses.extend(duplicates.iter().map(|&i| poses[i % poses.len()]));
        let signatures: Vec<ScanCoverage> = all_poses
            .iter()
            .map(|p| ScanCoverage::of(&synthetic_scan(p, 12), &config))
            .collect();
        let mut keeping = Retirement::new(config);
        let mut shedding = Retirement::new(config);
        shedding.shed_retired_signatures(true);
        let mut shelving = Retirement::new(config);
        shelving.set_shelf(Box::new(MemoryShelf::default()), Box::new(MemoryShelf::default()));
        let n = signatures.len() as u64;
        let check_shelving = |shedding: &Retirement, shelving: &Retirement, upto: u64| {
            for id in 0..upto {
                prop_assert_eq!(shedding.is_retired(id), shelving.is_retired(id));
                prop_assert_eq!(shedding.cells_of(id), shelving.cells_of(id));
                prop_assert_eq!(
                    shedding.witnesses_of_retired(id),
                    shelving.witnesses_of_retired(id)
                );
            }
            prop_assert_eq!(shelving.retired(), shelving.shelved(), "retired scans left in memory");
            prop_assert_eq!(shelving.counts(), shedding.counts());
            Ok(())
        };
        let check = |keeping: &Retirement, shedding: &Retirement, upto: u64| {
            for id in 0..upto {
                prop_assert_eq!(keeping.is_retired(id), shedding.is_retired(id));
                prop_assert_eq!(keeping.cells_of(id), shedding.cells_of(id));
                if shedding.is_retired(id) {
                    prop_assert!(!shedding.holds_signature(id), "scan {} kept its signature", id);
                }
            }
            Ok(())
        };
        for (i, (c, p)) in signatures.iter().zip(&all_poses).enumerate() {
            let id = i as ScanId;
            let changes = shedding.add(id, c.clone(), p);
            prop_assert_eq!(&keeping.add(id, c.clone(), p), &changes);
            prop_assert_eq!(shelving.add(id, c.clone(), p), changes);
            check(&keeping, &shedding, id + 1)?;
            check_shelving(&shedding, &shelving, id + 1)?;
        }
        prop_assert!(keeping.heap_bytes() >= shedding.heap_bytes());
        for (i, p) in &revisions {
            let id = *i as u64 % n;
            let held = shedding.holds_signature(id);
            let mut loads = 0;
            let shed_changes = shedding.revise_with(id, p, || {
                loads += 1;
                signatures.get(id as usize).cloned()
            });
            prop_assert_eq!(loads, usize::from(!held));
            prop_assert_eq!(keeping.revise(id, p), shed_changes.clone());
            let shelved_changes = shelving.revise_with(id, p, || signatures.get(id as usize).cloned());
            prop_assert_eq!(shelved_changes, shed_changes);
            check(&keeping, &shedding, n)?;
            check_shelving(&shedding, &shelving, n)?;
            check_invariants(&shedding, n);
            check_invariants(&shelving, n);
        }
    }
}

#[test]
fn a_scan_whose_signature_cannot_be_loaded_is_served_again() {
    let config = config();
    let p = pose([0.0, 0.0, 1.5], [2.0, 2.0, 0.5]);
    let coverage = ScanCoverage::of(&synthetic_scan(&p, 16), &config);
    let mut index = Retirement::new(config);
    index.shed_retired_signatures(true);
    index.add(0, coverage.clone(), &p);
    assert_eq!(index.add(1, coverage, &p).retired, vec![1]);
    assert!(!index.holds_signature(1) && index.holds_signature(0));
    // Revised a few centimetres, scan 1 would still be redundant; with its signature
    // lost it is served again rather than judged on a guess.
    let moved = Pose::translation(0.03, 0.0, 0.0) * p;
    let changes = index.revise_with(1, &moved, || None);
    assert_eq!(changes.restored, vec![1]);
    assert!(!index.is_retired(1));
    assert!(!index.cells_of(1).is_empty(), "moved offers still place it");
    check_invariants(&index, 2);
}

/// A shelf that can be made to fail its commits or to damage what it gives back.
#[derive(Default)]
struct FaultyShelf {
    inner: MemoryShelf,
    fail_commits: Arc<std::sync::atomic::AtomicBool>,
    damage_reads: Arc<std::sync::atomic::AtomicBool>,
}

impl Shelf for FaultyShelf {
    fn get(&self, ids: &[ScanId]) -> Vec<Result<Option<Vec<u8>>, ShelfError>> {
        let mut found = self.inner.get(ids);
        if self.damage_reads.load(std::sync::atomic::Ordering::Relaxed) {
            for bytes in found.iter_mut().flatten().flatten() {
                if let Some(b) = bytes.get_mut(3) {
                    *b ^= 0x40;
                }
            }
        }
        found
    }

    fn commit(&mut self, puts: &[(ScanId, Vec<u8>)], removes: &[ScanId]) -> Result<(), ShelfError> {
        if self.fail_commits.load(std::sync::atomic::Ordering::Relaxed) {
            return Err(ShelfError("disk full".into()));
        }
        self.inner.commit(puts, removes)
    }

    fn heap_bytes(&self) -> usize {
        self.inner.heap_bytes()
    }
}

#[test]
fn a_failing_shelf_loses_no_scan_and_a_damaged_one_serves_its_scans_again() {
    use std::sync::atomic::Ordering::Relaxed;
    let config = config();
    let p = pose([0.0, 0.0, 1.5], [2.0, 2.0, 0.5]);
    let coverage = ScanCoverage::of(&synthetic_scan(&p, 16), &config);
    let shelf = FaultyShelf::default();
    let (fail, damage) = (
        Arc::clone(&shelf.fail_commits),
        Arc::clone(&shelf.damage_reads),
    );
    let mut index = Retirement::new(config);
    index.set_shelf(Box::new(shelf), Box::new(MemoryShelf::default()));
    index.add(0, coverage.clone(), &p);
    assert_eq!(index.add(1, coverage.clone(), &p).retired, vec![1]);
    assert_eq!(index.shelved(), 1);
    // Commits fail: the copy retired now stays in memory, counted once.
    fail.store(true, Relaxed);
    assert_eq!(index.add(2, coverage.clone(), &p).retired, vec![2]);
    assert_eq!((index.retired(), index.shelved()), (2, 1));
    assert!(index.counts().shelf_errors >= 1);
    check_invariants(&index, 3);
    // The disk comes back: the next call shelves what was left behind too.
    fail.store(false, Relaxed);
    assert_eq!(index.add(3, coverage.clone(), &p).retired, vec![3]);
    assert_eq!((index.retired(), index.shelved()), (3, 3));
    check_invariants(&index, 4);
    // The shelf gives back damaged entries: the witness moves, its dependents
    // cannot be judged, and are served again rather than kept retired on a guess.
    damage.store(true, Relaxed);
    let moved = Pose::translation(0.01, 0.0, 0.0) * p;
    let changes = index.revise_with(0, &moved, || Some(coverage.clone()));
    assert_eq!(changes.restored, vec![1, 2, 3]);
    assert_eq!(index.counts().restored_unreadable, 3);
    assert_eq!(index.shelved(), 0);
    assert!(!index.is_retired(1) && !index.is_retired(2) && !index.is_retired(3));
}

#[test]
fn the_strongest_offers_are_the_candidates_when_many_scans_see_a_cell() {
    // Ten distant views of one patch of floor, then a near view of it, then the near
    // view again: the copy is redundant (its twin dominates every cell of it) even
    // though the ten weaker scans offering those cells came first and fill the
    // candidate cap.
    let arrival = CoverageConfig {
        max_candidates_per_cell: 4,
        ..config()
    };
    let config = CoverageConfig {
        strongest_candidates_first: true,
        ..arrival
    };
    let target = [1.5, 2.0, 0.0];
    let mut index = Retirement::new(config);
    for i in 0u32..10 {
        let eye = [-1.5 + 0.35 * f64::from(i), -1.0, 2.2];
        let p = pose(eye, target);
        index.add(
            i.into(),
            ScanCoverage::of(&synthetic_scan(&p, 16), &config),
            &p,
        );
    }
    let near = pose([1.5, 1.2, 1.0], target);
    let coverage = ScanCoverage::of(&synthetic_scan(&near, 16), &config);
    index.add(10, coverage.clone(), &near);
    assert!(!index.is_retired(10), "the near view adds detail");
    let served_before = index.served();
    assert!(served_before > 5, "most far views stay: {served_before}");
    let changes = index.add(11, coverage.clone(), &near);
    assert_eq!(changes.retired, vec![11]);
    assert_eq!(index.witnesses_of_retired(11), vec![10]);
    check_invariants(&index, 12);

    // In arrival order the ten far views fill the cap and the copy stays served.
    let mut index = Retirement::new(arrival);
    for i in 0u32..10 {
        let eye = [-1.5 + 0.35 * f64::from(i), -1.0, 2.2];
        let p = pose(eye, target);
        index.add(
            i.into(),
            ScanCoverage::of(&synthetic_scan(&p, 16), &arrival),
            &p,
        );
    }
    index.add(10, coverage.clone(), &near);
    assert!(index.add(11, coverage, &near).retired.is_empty());
    check_invariants(&index, 12);
}

#[test]
fn identical_duplicates_keep_exactly_one() {
    let config = config();
    let p = pose([0.0, 0.0, 1.5], [2.0, 2.0, 0.5]);
    let scan = synthetic_scan(&p, 16);
    let coverage = ScanCoverage::of(&scan, &config);
    assert!(!coverage.is_empty());
    let mut index = Retirement::new(config);
    for id in 0..5 {
        index.add(id, coverage.clone(), &p);
    }
    assert_eq!(index.served(), 1);
    assert_eq!(index.retired(), 4);
    assert!(
        !index.is_retired(0),
        "the first of the duplicates stays served"
    );
}

#[test]
fn a_retired_scan_returns_when_its_witness_moves_away() {
    let config = config();
    let p = pose([0.0, 0.0, 1.5], [2.0, 2.0, 0.5]);
    let coverage = ScanCoverage::of(&synthetic_scan(&p, 16), &config);
    let mut index = Retirement::new(config);
    assert_eq!(
        index.add(0, coverage.clone(), &p).retired,
        Vec::<ScanId>::new()
    );
    assert_eq!(index.add(1, coverage.clone(), &p).retired, vec![1]);
    assert_eq!(index.witnesses_of_retired(1), vec![0]);
    // Scan 0 is moved 50 m away: scan 1 is the only one left over its cells.
    let away = Pose::translation(50.0, 0.0, 0.0) * p;
    let changes = index.revise(0, &away);
    assert_eq!(changes.restored, vec![1]);
    assert!(changes.retired.is_empty());
    assert!(!index.is_retired(0) && !index.is_retired(1));
    // Moved back, scan 0 duplicates scan 1 again: the one moved is retired.
    let changes = index.revise(0, &p);
    assert_eq!(changes.retired, vec![0]);
    assert_eq!(index.served(), 1);
}

#[test]
fn range_confidence_and_accuracy_decide_who_stands_in() {
    // The same floor seen from 4 m and from 2 m along one line of sight: the far
    // scan's offer has half the near one's range confidence from close viewpoints,
    // so it stands in for the near scan only when the margin absorbs that.
    let target = [1.0, 1.0, 0.0];
    let near = pose([1.0, 1.0, 2.0], target);
    let far = pose([1.0, 1.0, 4.0], target);
    let near_scan = synthetic_scan(&near, 32);
    let far_scan = synthetic_scan(&far, 32);
    for (margin, near_retired) in [(0.05, false), (0.6, true)] {
        let config = CoverageConfig {
            reliability_margin: margin,
            ..config()
        };
        let mut index = Retirement::new(config);
        index.add(0, ScanCoverage::of(&far_scan, &config), &far);
        let changes = index.add(1, ScanCoverage::of(&near_scan, &config), &near);
        assert_eq!(index.is_retired(1), near_retired, "margin {margin}");
        assert!(
            !index.is_retired(0),
            "the far scan shows floor the near one does not"
        );
        assert_eq!(changes.retired.is_empty(), !near_retired);
    }
    // A scan with worse normals at the same pose is retired by a better one added
    // after it.
    let config = config();
    let mut worse = far_scan.clone();
    worse.triangle_accuracy.iter_mut().for_each(|a| *a *= 0.5);
    let mut index = Retirement::new(config);
    index.add(0, ScanCoverage::of(&worse, &config), &far);
    let changes = index.add(1, ScanCoverage::of(&far_scan, &config), &far);
    assert_eq!(changes.retired, vec![0]);
    assert_eq!(index.witnesses_of_retired(0), vec![1]);
    assert!(!index.is_retired(1));
}

#[test]
fn degenerate_scans_cover_nothing_and_are_retired() {
    let config = config();
    let p = pose([0.0, 0.0, 1.5], [2.0, 2.0, 0.5]);
    let mut empty = synthetic_scan(&p, 0);
    assert!(ScanCoverage::of(&empty, &config).is_empty());
    // Zero-length normals: every triangle degenerate with accuracy 0.
    let mut flat = synthetic_scan(&p, 16);
    for (f, a) in flat
        .triangle_flags
        .iter_mut()
        .zip(flat.triangle_accuracy.iter_mut())
    {
        *f = TriangleFlags(TriangleFlags::DEGENERATE);
        *a = 0.0;
    }
    assert!(ScanCoverage::of(&flat, &config).is_empty());
    // Non-finite vertices and centre of projection.
    empty.cop_m = [f64::NAN; 3];
    assert!(ScanCoverage::of(&empty, &config).is_empty());
    let mut index = Retirement::new(config);
    let changes = index.add(0, ScanCoverage::of(&flat, &config), &p);
    assert_eq!(changes.retired, vec![0]);
    assert_eq!(index.retired(), 1);
}

#[test]
fn the_default_signature_fits_in_four_kilobytes() {
    let config = CoverageConfig::default();
    let p = pose([0.0, 0.0, 1.5], [2.0, 2.0, 0.5]);
    let coverage = ScanCoverage::of(&synthetic_scan(&p, 128), &config);
    assert!(coverage.samples.len() <= 256, "{}", coverage.samples.len());
    assert!(coverage.samples.len() > 200, "{}", coverage.samples.len());
    assert!(coverage.heap_bytes() <= 4096, "{}", coverage.heap_bytes());
    assert!(coverage.score() > 0.0 && coverage.score().is_finite());
    let toml_text = "cell_m = 0.3\nangle_tolerance_deg = 5.0\n";
    let parsed: CoverageConfig = toml::from_str(toml_text).unwrap();
    assert_eq!(parsed.cell_m, 0.3);
    assert_eq!(parsed.sample_stride_px, config.sample_stride_px);
    assert!(toml::from_str::<CoverageConfig>("cell_size = 1.0").is_err());
}

#[test]
fn a_retired_scan_keeps_its_offers_packed_and_its_links_alone() {
    let config = CoverageConfig::default();
    let p = pose([0.0, 0.0, 1.5], [2.0, 2.0, 0.5]);
    let coverage = ScanCoverage::of(&synthetic_scan(&p, 128), &config);
    let mut index = Retirement::new(config);
    index.shed_retired_signatures(true);
    index.add(0, coverage.clone(), &p);
    let cells = index.cells_of(0).len();
    assert!(cells > 20, "{cells} cells");
    let one = index.heap_bytes();
    let retired = 1000;
    for id in 1..=retired {
        index.add(id, coverage.clone(), &p);
    }
    assert_eq!(index.retired(), retired as usize);
    assert!(!index.holds_signature(1));
    assert_eq!(
        index.cells_of(1),
        index.cells_of(0),
        "packing keeps every cell"
    );
    let per_retired = (index.heap_bytes() - one) / retired as usize;
    // Open offers take 32 bytes a cell; packed ones about 11. The rest is the
    // entry (with the map's spare capacity) and one link each way.
    assert!(
        per_retired <= cells * 12 + 512,
        "{per_retired} bytes a retired scan of {cells} cells"
    );
}

#[test]
fn a_witness_revised_in_place_keeps_more_dependents_than_one_call_can_test() {
    // Cells of 0.7 m: no wall lies on a cell boundary, where any motion at all
    // moves samples from cell to cell.
    let config = CoverageConfig {
        max_checks_per_call: 4,
        cell_m: 0.7,
        ..config()
    };
    let p = pose([0.0, 0.0, 1.5], [2.0, 2.0, 0.5]);
    let coverage = ScanCoverage::of(&synthetic_scan(&p, 16), &config);
    let mut index = Retirement::new(config);
    for id in 0..20 {
        index.add(id, coverage.clone(), &p);
    }
    assert_eq!(index.served(), 1);
    // A loop closure revises the witness by a tenth of a millimetre: its offers
    // still dominate its 19 dependents, more than the call's 4 tests could examine.
    let mut moved = p;
    moved.translation.vector.x += 1.0e-4;
    let changes = index.revise(0, &moved);
    assert!(changes.restored.is_empty(), "{changes:?}");
    assert_eq!(index.served(), 1);
    check_invariants(&index, 20);
    // A retired scan revised where its witness still stands in for it stays retired.
    assert_eq!(index.revise(7, &moved), Default::default());
    assert!(index.is_retired(7));
    check_invariants(&index, 20);
    // Moved away, the witness no longer stands in for them: the first is tested
    // and served, the next three are tested and witnessed by it, and the rest,
    // past the call's 4 tests, are served again unexamined (the safe outcome).
    let far = pose([40.0, 0.0, 1.5], [42.0, 2.0, 0.5]);
    let changes = index.revise(0, &far);
    assert_eq!(changes.restored.len(), 16, "{changes:?}");
    assert_eq!(index.witnesses_of_retired(2), vec![1]);
    check_invariants(&index, 20);
}
