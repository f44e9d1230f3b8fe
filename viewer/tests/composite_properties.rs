//! Properties of the CPU reference compositing (Algorithm 2) over random fragment
//! sets: order independence, what `best` and `blended` may return, range compliance,
//! and the k-buffer's incremental ranking equal to the full sort.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use proptest::prelude::*;
use texel_viewer::composite::{
    CompositeSettings, Fragment, Mode, composite_pixel, is_range_compliant, nearest, ranked,
    ranked_incrementally,
};

fn fragment() -> impl Strategy<Value = Fragment> {
    (
        prop::array::uniform3(0u8..=255),
        prop_oneof![Just(0.0f32), Just(0.5f32), 0.0f32..=1.0],
        prop_oneof![Just(3.0f32), 1.0f32..10.0],
        0.001f32..0.05,
        0u32..6,
    )
        .prop_map(|(c, reliability, distance_m, sigma_m, scan)| Fragment {
            colour: c.map(|v| f32::from(v) / 255.0),
            reliability,
            distance_m,
            sigma_m,
            scan,
        })
}

/// One fragment per scan, as the layers give them.
fn pixel() -> impl Strategy<Value = Vec<Fragment>> {
    prop::collection::vec(fragment(), 0..7).prop_map(|mut v| {
        v.sort_by_key(|f| f.scan);
        v.dedup_by_key(|f| f.scan);
        v
    })
}

fn settings(mode: Mode) -> impl Strategy<Value = CompositeSettings> {
    (0.0f32..0.6, 1u32..=8).prop_map(move |(t, k)| CompositeSettings {
        mode,
        blend_threshold: t,
        k,
        background: [0.25, 0.5, 0.75],
    })
}

proptest! {
    #[test]
    fn order_of_the_layers_does_not_matter(px in pixel(), s in settings(Mode::Blended), seed in 0usize..100) {
        let mut shuffled = px.clone();
        if !shuffled.is_empty() {
            let n = shuffled.len();
            shuffled.rotate_left(seed % n);
            shuffled.swap(0, seed % n);
        }
        prop_assert_eq!(composite_pixel(&px, &s), composite_pixel(&shuffled, &s));
    }

    #[test]
    fn best_is_the_most_reliable_compliant_fragment(px in pixel(), s in settings(Mode::Best)) {
        let got = composite_pixel(&px, &s);
        match nearest(&px) {
            None => prop_assert_eq!(got, s.background),
            Some(n) => {
                let compliant: Vec<_> = px.iter().filter(|f| f.reliability > 0.0 && is_range_compliant(f, n.distance_m, n.sigma_m)).collect();
                let best = compliant.iter().copied().copied().reduce(|a, b| {
                    if b.reliability > a.reliability || (b.reliability == a.reliability && b.scan < a.scan) { b } else { a }
                }).unwrap();
                prop_assert_eq!(got, best.colour);
            }
        }
    }

    #[test]
    fn blended_stays_within_the_blended_colours(px in pixel(), s in settings(Mode::Blended)) {
        let got = composite_pixel(&px, &s);
        prop_assert!(got.iter().all(|c| c.is_finite()));
        let top = ranked(&px, s.effective_k());
        if let Some(best) = top.first() {
            let set: Vec<_> = top.iter().filter(|f| f.reliability >= best.reliability - s.blend_threshold).collect();
            for (ch, value) in got.iter().enumerate() {
                let lo = set.iter().map(|f| f.colour[ch]).fold(f32::INFINITY, f32::min);
                let hi = set.iter().map(|f| f.colour[ch]).fold(f32::NEG_INFINITY, f32::max);
                prop_assert!(*value >= lo - 1e-6 && *value <= hi + 1e-6);
            }
        } else {
            prop_assert_eq!(got, s.background);
        }
    }

    /// A surface far behind the nearest one never changes the pixel, however reliable.
    #[test]
    fn far_surfaces_do_not_show_through(px in pixel(), s in settings(Mode::Blended), rel in 0.0f32..=1.0) {
        let Some(n) = nearest(&px) else { return Ok(()); };
        let mut more = px.clone();
        more.push(Fragment { colour: [1.0, 0.0, 1.0], reliability: rel, distance_m: n.distance_m + 1.0, sigma_m: 0.05, scan: 99 });
        prop_assert_eq!(composite_pixel(&px, &s), composite_pixel(&more, &s));
    }

    /// The k-buffer's batched insertion ranks exactly like the full sort.
    #[test]
    fn incremental_ranking_equals_the_sort(px in pixel(), k in 1usize..=8, batch in 1usize..=5) {
        prop_assert_eq!(ranked_incrementally(&px, k, batch), ranked(&px, k));
    }
}
