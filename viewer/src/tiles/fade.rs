//! Cross-fading between selections, so a switch between a parent and its children
//! (either way) does not pop: the tiles that enter fade in and the tiles that leave
//! fade out over `fade_s`, both drawn meanwhile.
//!
//! **Blend, not geomorph.** A geomorph moves each vertex of the finer mesh from its
//! place on the coarser one; that needs the vertices to correspond across levels. Here
//! every tile is cut from its own level's field and simplified on its own (surface
//! nets, then quadric collapse), so nothing relates a child's vertices to its parent's:
//! the two can only be blended as images.
//!
//! **A screen door over whole selections.** The state is a short list of selections
//! ("cuts", each a set of tiles that covers the view once), oldest first, with shares
//! that sum to 1; a new selection enters with share 0 and takes share from the oldest
//! at `1 / fade_s` a second. Each pixel's ordered-dither threshold (8x8 Bayer) falls in
//! one cut's share and the pixel keeps only that cut's tiles. So each pixel shows one
//! complete selection (no hole, nothing drawn twice where selections overlap), no
//! sorting is needed and the depth buffer stays valid. A tile that only comes into
//! view (nothing it overlaps is drawn) joins every cut at once: there is nothing to
//! fade from, and a dissolve at the screen's edge would itself be a hole. Tiles out
//! of view leave every cut.

use std::collections::{BTreeMap, BTreeSet};

use texel_lod::TileId;

/// Most selections faded between at once; past it the oldest gives its share to the
/// next at once.
pub const MAX_CUTS: usize = 8;

/// The 8x8 Bayer threshold of a pixel, in (0, 1) (`bayer8` in `tile.wgsl`).
pub fn dither_threshold(x: u32, y: u32) -> f32 {
    let y = y & 7;
    let v = (x & 7) ^ y;
    let m = ((v & 1) << 5)
        | ((y & 1) << 4)
        | ((v & 2) << 2)
        | ((y & 2) << 1)
        | ((v & 4) >> 1)
        | ((y & 4) >> 2);
    (m as f32 + 0.5) / 64.0
}

#[derive(Debug, Clone, PartialEq)]
struct Cut {
    tiles: BTreeSet<TileId>,
    share: f64,
}

/// What to draw this frame.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FadeFrame {
    /// Where each cut's share ends, oldest first; unused cuts end at 1.
    pub ends: [f32; MAX_CUTS],
    /// Every tile of any cut, with bit `i` set for each cut `i` it belongs to.
    pub tiles: BTreeMap<TileId, u32>,
    /// More than one cut: a fade is under way.
    pub fading: bool,
}

/// The cross-fade state.
#[derive(Debug, Clone, Default)]
pub struct CrossFade {
    cuts: Vec<Cut>,
    last_s: Option<f64>,
}

fn overlaps(a: TileId, b: TileId) -> bool {
    a.is_within(b) || b.is_within(a)
}

impl CrossFade {
    pub fn new() -> Self {
        Self::default()
    }

    /// Whether a fade is under way.
    pub fn is_fading(&self) -> bool {
        self.cuts.len() > 1
    }

    /// Takes this frame's selection `draw` at time `now_s` (seconds, any origin;
    /// going back counts as no time). `visible` says whether a tile is in view.
    /// `fade_s` of 0 (or not finite) switches at once.
    pub fn update(
        &mut self,
        draw: &[TileId],
        visible: &dyn Fn(TileId) -> bool,
        now_s: f64,
        fade_s: f64,
    ) -> FadeFrame {
        let dt_s = match self.last_s {
            Some(last) if now_s.is_finite() && now_s > last => now_s - last,
            _ => 0.0,
        };
        if now_s.is_finite() {
            self.last_s = Some(self.last_s.map_or(now_s, |l| l.max(now_s)));
        }
        let selected: BTreeSet<TileId> = draw.iter().copied().collect();
        if !(fade_s.is_finite() && fade_s > 0.0) {
            self.cuts = vec![Cut {
                tiles: selected,
                share: 1.0,
            }];
            return self.frame();
        }
        for cut in &mut self.cuts {
            cut.tiles.retain(|t| selected.contains(t) || visible(*t));
        }
        // Tiles that replace nothing in a cut join it: nothing to fade from.
        for t in &selected {
            for cut in &mut self.cuts {
                if !cut.tiles.iter().any(|u| overlaps(*t, *u)) {
                    cut.tiles.insert(*t);
                }
            }
        }
        match self.cuts.last() {
            Some(newest) if newest.tiles == selected => {}
            Some(_) => self.cuts.push(Cut {
                tiles: selected,
                share: 0.0,
            }),
            None => self.cuts.push(Cut {
                tiles: selected,
                share: 1.0,
            }),
        }
        // The newest takes share from the oldest.
        let mut give = dt_s / fade_s;
        let newest = self.cuts.len() - 1;
        for i in 0..newest {
            let take = give.min(self.cuts[i].share);
            self.cuts[i].share -= take;
            self.cuts[newest].share += take;
            give -= take;
            if give <= 0.0 {
                break;
            }
        }
        let n = self.cuts.len();
        let mut kept: Vec<Cut> = Vec::with_capacity(n);
        for (i, cut) in std::mem::take(&mut self.cuts).into_iter().enumerate() {
            if i + 1 < n && cut.share <= 1e-9 {
                continue;
            }
            kept.push(cut);
        }
        while kept.len() > MAX_CUTS {
            let oldest = kept.remove(0);
            kept[0].share += oldest.share;
        }
        // Shares sum to 1 (rounding aside); the newest takes any remainder.
        let others: f64 = kept.iter().rev().skip(1).map(|c| c.share).sum();
        if let Some(last) = kept.last_mut() {
            last.share = (1.0 - others).clamp(0.0, 1.0);
        }
        self.cuts = kept;
        self.frame()
    }

    fn frame(&self) -> FadeFrame {
        let mut out = FadeFrame {
            ends: [1.0; MAX_CUTS],
            tiles: BTreeMap::new(),
            fading: self.cuts.len() > 1,
        };
        let mut end = 0.0f64;
        for (i, cut) in self.cuts.iter().enumerate().take(MAX_CUTS) {
            end += cut.share;
            out.ends[i] = if i + 1 == self.cuts.len() {
                1.0
            } else {
                end.clamp(0.0, 1.0) as f32
            };
            for t in &cut.tiles {
                *out.tiles.entry(*t).or_insert(0) |= 1 << i;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    fn id(lod: u8, x: i64, y: i64) -> TileId {
        TileId { lod, x, y }
    }

    #[test]
    fn the_dither_is_a_permutation_of_64_levels() {
        let mut seen: Vec<u32> = (0..8)
            .flat_map(|y| (0..8).map(move |x| (dither_threshold(x, y) * 64.0) as u32))
            .collect();
        seen.sort();
        assert_eq!(seen, (0..64).collect::<Vec<_>>());
    }

    /// Every pixel threshold picks one cut; in that cut each ground point is covered
    /// once: a parent fading into its children, interrupted and sent back, and a
    /// grandchild switch mid-fade.
    #[test]
    fn every_threshold_shows_one_whole_selection() {
        let parent = id(2, 0, 0);
        let children: Vec<TileId> = parent.children().unwrap().to_vec();
        let grand: Vec<TileId> = children[0].children().unwrap().to_vec();
        let all = |_| true;
        let mut f = CrossFade::new();
        let check = |frame: &FadeFrame| {
            for k in 0..64 {
                let b = (k as f32 + 0.5) / 64.0;
                let cut = frame
                    .ends
                    .iter()
                    .position(|e| b < *e)
                    .unwrap_or(MAX_CUTS - 1);
                let kept: Vec<TileId> = frame
                    .tiles
                    .iter()
                    .filter(|(_, m)| *m >> cut & 1 == 1)
                    .map(|(t, _)| *t)
                    .collect();
                // Every finest tile under the parent covered exactly once.
                for leaf in grand.iter().chain(&children[1..]) {
                    let n = kept.iter().filter(|t| leaf.is_within(**t)).count();
                    assert_eq!(n, 1, "{leaf:?} at {b}: {kept:?}");
                }
            }
        };
        let fr = f.update(&[parent], &all, 0.0, 0.25);
        assert!(!fr.fading);
        check(&fr);
        let fr = f.update(&children, &all, 0.1, 0.25);
        assert!(fr.fading);
        check(&fr);
        let mut mixed = grand.clone();
        mixed.extend(&children[1..]);
        let fr = f.update(&mixed, &all, 0.15, 0.25);
        check(&fr);
        let fr = f.update(&[parent], &all, 0.2, 0.25);
        check(&fr);
        for k in 1..20 {
            check(&f.update(&[parent], &all, 0.2 + 0.05 * f64::from(k), 0.25));
        }
        assert!(!f.is_fading());
        let fr = f.update(&[parent], &all, 5.0, 0.25);
        assert_eq!(fr.tiles.keys().copied().collect::<Vec<_>>(), vec![parent]);
    }

    #[test]
    fn shares_move_at_one_over_fade_time_and_zero_switches_at_once() {
        let parent = id(1, 0, 0);
        let children: Vec<TileId> = parent.children().unwrap().to_vec();
        let all = |_| true;
        let mut f = CrossFade::new();
        f.update(&[parent], &all, 0.0, 0.5);
        f.update(&[parent], &all, 0.9, 0.5);
        // The switch takes the time since the last frame: 0.1 s of 0.5 s.
        let fr = f.update(&children, &all, 1.0, 0.5);
        assert!((fr.ends[0] - 0.8).abs() < 1e-6, "{:?}", fr.ends);
        let fr = f.update(&children, &all, 1.1, 0.5);
        assert!((fr.ends[0] - 0.6).abs() < 1e-6, "{:?}", fr.ends);
        let fr = f.update(&children, &all, 1.6, 0.5);
        assert!(!fr.fading);
        let mut g = CrossFade::new();
        g.update(&[parent], &all, 0.0, 0.0);
        let fr = g.update(&children, &all, 0.01, 0.0);
        assert!(!fr.fading);
        assert!(!fr.tiles.contains_key(&parent));
        // A tile that merely comes into view joins at once.
        let mut h = CrossFade::new();
        h.update(&children[..2], &all, 0.0, 0.5);
        let fr = h.update(&children, &all, 0.01, 0.5);
        assert!(!fr.fading);
    }
}
