//! The fields paged beyond a memory budget: a street walked with its fields held to a
//! small budget builds the same tree, bit for bit, as one held wholly in memory,
//! through new scans, a revised pose and bounded rebuilds; memory stays within the
//! budget after every call; a store that refuses writes loses nothing, and one that
//! returns damaged pages costs those blocks' observations, counted, never a panic.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod support;

use proptest::prelude::*;
use texel::paged::{MemoryPages, PageError, PageStore};
use texel_lod::{LodConfig, LodModel};
use texel_surface::Sample;

fn config() -> LodConfig {
    LodConfig {
        tile_voxels: 64,
        tile_triangle_budget: 3_000,
        ..LodConfig::default()
    }
}

fn shifted(samples: &[Sample], dy_m: f64) -> Vec<Sample> {
    samples
        .iter()
        .map(|s| Sample {
            point_m: [s.point_m[0], s.point_m[1] + dy_m, s.point_m[2]],
            centre_m: [s.centre_m[0], s.centre_m[1] + dy_m, s.centre_m[2]],
            ..*s
        })
        .collect()
}

/// Walks the street: each stop fused, one placed wrong and revised a few stops
/// later, `per_round` tiles rebuilt after each; `check` sees the model after every
/// call.
fn walk(
    model: &mut LodModel,
    stops: &[Vec<Sample>],
    per_round: usize,
    check: &mut dyn FnMut(&LodModel),
) {
    for (i, stop) in stops.iter().enumerate() {
        if i == 6 {
            model.add_samples(&shifted(stop, 0.5));
        } else {
            model.add_samples(stop);
        }
        check(model);
        if i == 14 {
            model.remove_samples(&shifted(&stops[6], 0.5));
            check(model);
            model.add_samples(&stops[6]);
            check(model);
        }
        model.rebuild(per_round);
        check(model);
    }
    model.rebuild(usize::MAX);
    check(model);
}

#[test]
fn paged_fields_build_the_same_tree_within_their_budget() {
    let stops = support::street_stops(30.0, 1.0, [0.0; 3]);
    let mut whole = LodModel::new(config()).unwrap();
    let mut peak_whole = 0;
    walk(&mut whole, &stops, 3, &mut |m| {
        peak_whole = peak_whole.max(m.field_bytes());
    });

    // A tenth of what the walk holds unpaged.
    let budget = peak_whole / 10;
    let mut paged = LodModel::new(config()).unwrap();
    paged.page_fields_to(Box::new(MemoryPages::default()), budget);
    let mut peak_paged = 0;
    walk(&mut paged, &stops, 3, &mut |m| {
        peak_paged = peak_paged.max(m.field_bytes());
        assert!(
            m.field_bytes() <= budget,
            "{} bytes in memory, budget {budget}",
            m.field_bytes()
        );
    });
    let paging = paged.field_paging();
    println!("unpaged peak {peak_whole} bytes; paged peak {peak_paged}, {paging:?}");
    assert!(paging.writes > 0 && paging.reads > 0, "{paging:?}");
    assert_eq!(paging.errors, 0);
    assert_eq!(paged.hierarchy().unwrap(), whole.hierarchy().unwrap());
    assert_eq!(paged.top_lod(), whole.top_lod());
    // Memory plus pages hold the fields, nothing twice.
    assert!(paging.bytes_out > 0);
}

/// A store that fails every write, or returns every third page damaged.
struct Faulty {
    inner: MemoryPages,
    refuse_writes: bool,
}

impl PageStore for Faulty {
    fn write_page(&mut self, page: u64, bytes: &[u8]) -> Result<(), PageError> {
        if self.refuse_writes {
            return Err(PageError(format!("page {page}: the disk is full")));
        }
        self.inner.write_page(page, bytes)
    }

    fn read_page(&self, page: u64, out: &mut [u8]) -> Result<(), PageError> {
        self.inner.read_page(page, out)?;
        if page.is_multiple_of(3) {
            // A NaN where the first voxel's distance was: not a block.
            out[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
        }
        Ok(())
    }
}

#[test]
fn a_store_that_refuses_writes_keeps_the_fields_in_memory_and_loses_nothing() {
    let stops = support::street_stops(12.0, 1.0, [0.0; 3]);
    let mut whole = LodModel::new(config()).unwrap();
    walk(&mut whole, &stops, 3, &mut |_| {});
    let mut paged = LodModel::new(config()).unwrap();
    paged.page_fields_to(
        Box::new(Faulty {
            inner: MemoryPages::default(),
            refuse_writes: true,
        }),
        1 << 16,
    );
    walk(&mut paged, &stops, 3, &mut |_| {});
    let paging = paged.field_paging();
    assert!(paging.errors > 0 && paging.writes == 0, "{paging:?}");
    assert_eq!(paging.blocks_out, 0);
    assert_eq!(paged.field_bytes(), whole.field_bytes());
    assert_eq!(paged.hierarchy().unwrap(), whole.hierarchy().unwrap());
}

#[test]
fn damaged_pages_are_counted_and_cost_only_their_blocks() {
    let stops = support::street_stops(12.0, 1.0, [0.0; 3]);
    let mut paged = LodModel::new(config()).unwrap();
    paged.page_fields_to(
        Box::new(Faulty {
            inner: MemoryPages::default(),
            refuse_writes: false,
        }),
        1 << 18,
    );
    walk(&mut paged, &stops, 3, &mut |_| {});
    let paging = paged.field_paging();
    assert!(paging.errors > 0 && paging.reads > 0, "{paging:?}");
    // The tree is still built from what is left.
    let tree = paged.hierarchy().unwrap();
    assert!(!tree.nodes.is_empty());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 6, ..ProptestConfig::default() })]

    /// Any budget and any rebuild pace give the tree of the fields held whole.
    #[test]
    fn any_budget_builds_the_unpaged_tree(
        budget_blocks in 1usize..200,
        per_round in 1usize..6,
    ) {
        let stops = support::street_stops(16.0, 2.0, [0.0; 3]);
        let mut whole = LodModel::new(config()).unwrap();
        walk(&mut whole, &stops, per_round, &mut |_| {});
        let mut paged = LodModel::new(config()).unwrap();
        let budget = budget_blocks * texel_surface::BLOCK_BYTES;
        paged.page_fields_to(Box::new(MemoryPages::default()), budget);
        walk(&mut paged, &stops, per_round, &mut |_| {});
        prop_assert_eq!(paged.field_paging().errors, 0);
        prop_assert_eq!(paged.hierarchy().unwrap(), whole.hierarchy().unwrap());
    }
}
