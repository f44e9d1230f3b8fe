//! The compositing math of Killpack & Budge (2016), Sec. 4 / Algorithm 2, on the CPU:
//! the reference the GPU composite is tested against. Pure, no GPU.
//!
//! Per pixel: drop empty and zero-reliability fragments; keep only those within
//! `2 max(σ_f, σ_near)` of the nearest (range compliance); rank by reliability (ties:
//! lower scan id first); keep the top `k`; show the best, or blend those within
//! `blend_threshold` of the best, weighted by reliability. `composite.wgsl` implements
//! the same steps in the same order.

/// At most this many fragments are kept per pixel (the k-buffer's depth).
pub const MAX_K: u32 = 8;

/// Range compliance window in standard deviations (Sec. 4: "beyond two times the
/// standard noise deviation").
pub const COMPLIANCE_SIGMAS: f32 = 2.0;

/// What the renderer shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Mode {
    /// Plain depth-tested textured meshes: the baseline the paper improves on.
    Painter,
    /// The most reliable range-compliant fragment.
    Best,
    /// Reliability-weighted blend of the fragments near the best.
    #[default]
    Blended,
    /// A unique colour per scan: which scan wins each pixel.
    ScanColour,
    /// Heat map of the winning fragment's reliability.
    Reliability,
}

impl Mode {
    pub const ALL: [Mode; 5] = [
        Mode::Painter,
        Mode::Best,
        Mode::Blended,
        Mode::ScanColour,
        Mode::Reliability,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Mode::Painter => "painter",
            Mode::Best => "best",
            Mode::Blended => "blended",
            Mode::ScanColour => "scan-colour",
            Mode::Reliability => "reliability",
        }
    }

    /// The code the shaders switch on.
    pub fn code(self) -> u32 {
        match self {
            Mode::Painter => 0,
            Mode::Best => 1,
            Mode::Blended => 2,
            Mode::ScanColour => 3,
            Mode::Reliability => 4,
        }
    }
}

impl std::str::FromStr for Mode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Mode::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                let names: Vec<_> = Mode::ALL.iter().map(|m| m.name()).collect();
                format!("unknown mode {s:?}; expected one of {}", names.join(", "))
            })
    }
}

impl std::fmt::Display for Mode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One scan's fragment at a pixel, as the scan pass writes it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fragment {
    /// Texture colour, components in [0, 1].
    pub colour: [f32; 3],
    /// Accumulated reliability in [0, 1]; 0 means "do not use".
    pub reliability: f32,
    /// Euclidean distance to the virtual camera's centre of projection, metres.
    pub distance_m: f32,
    /// The scan's range noise standard deviation at this point's acquisition range.
    pub sigma_m: f32,
    pub scan: u32,
}

/// The knobs of compositing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompositeSettings {
    pub mode: Mode,
    /// Fragments whose reliability is within this of the best are blended.
    pub blend_threshold: f32,
    /// At most this many fragments are ranked and blended (1..=[`MAX_K`]).
    pub k: u32,
    pub background: [f32; 3],
}

impl Default for CompositeSettings {
    fn default() -> Self {
        Self {
            mode: Mode::Blended,
            blend_threshold: 0.15,
            k: 4,
            background: [0.0, 0.0, 0.0],
        }
    }
}

impl CompositeSettings {
    /// `k` clamped into 1..=MAX_K, as the shaders see it.
    pub fn effective_k(&self) -> usize {
        self.k.clamp(1, MAX_K) as usize
    }

    /// A threshold that is finite and not negative (NaN counts as 0: best only).
    pub fn effective_threshold(&self) -> f32 {
        if self.blend_threshold.is_finite() {
            self.blend_threshold.max(0.0)
        } else if self.blend_threshold == f32::INFINITY {
            f32::MAX
        } else {
            0.0
        }
    }
}

/// True when `a` ranks before `b`: higher reliability, then lower scan id.
#[inline]
pub fn ranks_before(a: &Fragment, b: &Fragment) -> bool {
    a.reliability > b.reliability || (a.reliability == b.reliability && a.scan < b.scan)
}

/// Step 1 of Algorithm 2: a fragment is valid when it exists and its reliability is
/// positive (and, for robustness, every value is finite).
#[inline]
pub fn is_valid(f: &Fragment) -> bool {
    f.reliability > 0.0 && f.reliability.is_finite() && f.distance_m.is_finite()
}

/// The nearest valid fragment (ties: lower scan id), whose distance and noise anchor
/// range compliance.
pub fn nearest(fragments: &[Fragment]) -> Option<Fragment> {
    fragments
        .iter()
        .filter(|f| is_valid(f))
        .copied()
        .reduce(|best, f| {
            if f.distance_m < best.distance_m
                || (f.distance_m == best.distance_m && f.scan < best.scan)
            {
                f
            } else {
                best
            }
        })
}

/// Step 2 of Algorithm 2: within `2 max(σ_f, σ_near)` of the nearest surface.
#[inline]
pub fn is_range_compliant(f: &Fragment, near_distance_m: f32, near_sigma_m: f32) -> bool {
    f.distance_m - near_distance_m <= COMPLIANCE_SIGMAS * f.sigma_m.max(near_sigma_m)
}

/// Steps 1-3: the valid, range-compliant fragments ranked by reliability, at most `k`.
pub fn ranked(fragments: &[Fragment], k: usize) -> Vec<Fragment> {
    let Some(near) = nearest(fragments) else {
        return Vec::new();
    };
    let mut kept: Vec<Fragment> = fragments
        .iter()
        .filter(|f| is_valid(f) && is_range_compliant(f, near.distance_m, near.sigma_m))
        .copied()
        .collect();
    kept.sort_by(|a, b| {
        if ranks_before(a, b) {
            std::cmp::Ordering::Less
        } else if ranks_before(b, a) {
            std::cmp::Ordering::Greater
        } else {
            std::cmp::Ordering::Equal
        }
    });
    kept.truncate(k);
    kept
}

/// Step 4: the pixel's colour from its ranked fragments (best first).
pub fn shade(top: &[Fragment], settings: &CompositeSettings) -> [f32; 3] {
    let Some(best) = top.first() else {
        return settings.background;
    };
    match settings.mode {
        // Painter is not a composite; from ranked fragments it is shown as `best`.
        Mode::Painter | Mode::Best => best.colour,
        Mode::Blended => {
            let floor = best.reliability - settings.effective_threshold();
            let mut sum = [0.0f32; 3];
            let mut weight = 0.0f32;
            for f in top.iter().filter(|f| f.reliability >= floor) {
                for (s, c) in sum.iter_mut().zip(f.colour) {
                    *s += f.reliability * c;
                }
                weight += f.reliability;
            }
            // weight >= best.reliability > 0 (valid fragments only).
            sum.map(|s| s / weight)
        }
        Mode::ScanColour => scan_colour(best.scan),
        Mode::Reliability => heat(best.reliability),
    }
}

/// The k-buffer strategy on the CPU: the nearest valid fragment is found first (the
/// pre-pass), then fragments arrive `batch` at a time in scan order and each compliant
/// one is inserted into a ranked list of at most `k` (as `merge.wgsl` does). Gives the
/// same list as [`ranked`] for every batch size.
pub fn ranked_incrementally(fragments: &[Fragment], k: usize, batch: usize) -> Vec<Fragment> {
    let Some(near) = nearest(fragments) else {
        return Vec::new();
    };
    let k = k.max(1);
    let mut top: Vec<Fragment> = Vec::with_capacity(k + 1);
    for chunk in fragments.chunks(batch.max(1)) {
        for f in chunk
            .iter()
            .filter(|f| is_valid(f) && is_range_compliant(f, near.distance_m, near.sigma_m))
        {
            let pos = top.iter().take_while(|t| ranks_before(t, f)).count();
            if pos < k {
                top.insert(pos, *f);
                top.truncate(k);
            }
        }
    }
    top
}

/// Algorithm 2 for one pixel.
pub fn composite_pixel(fragments: &[Fragment], settings: &CompositeSettings) -> [f32; 3] {
    shade(&ranked(fragments, settings.effective_k()), settings)
}

/// The unique colour of a scan: hues spaced by the golden angle, so neighbours in
/// id differ strongly. Scans merged from several cameras (ids `camera << 24 | id`,
/// `texel_client::zenoh_gateway`) take their camera's colour instead, so each
/// camera's model shows in its own. Same formula as `scan_colour` in `common.wgsl`.
pub fn scan_colour(scan: u32) -> [f32; 3] {
    let camera = scan >> 24;
    let hue = if camera != 0 {
        (camera as f32 * 0.618_034 + 0.1).fract()
    } else {
        (scan as f32 * 0.618_034).fract()
    };
    hsv_to_rgb(hue, 0.75, 0.95)
}

/// HSV (all in [0, 1]) to RGB.
pub fn hsv_to_rgb(h: f32, s: f32, v: f32) -> [f32; 3] {
    let k = |n: f32| {
        let kk = (n + h * 6.0) % 6.0;
        v - v * s * (kk.min(4.0 - kk).clamp(0.0, 1.0))
    };
    [k(5.0), k(3.0), k(1.0)]
}

/// Heat map of a reliability in [0, 1]: blue (cool, unreliable) through cyan, green
/// and yellow to red (warm, reliable), as in the paper's Fig. 5. Same formula as
/// `heat` in `common.wgsl`.
pub fn heat(reliability: f32) -> [f32; 3] {
    let t = reliability.clamp(0.0, 1.0) * 4.0;
    let r = (t - 2.0).clamp(0.0, 1.0);
    let g = if t < 3.0 {
        t.clamp(0.0, 1.0)
    } else {
        (4.0 - t).clamp(0.0, 1.0)
    };
    let b = if t < 1.0 {
        1.0
    } else {
        (2.0 - t).clamp(0.0, 1.0)
    };
    [r, g, b]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frag(scan: u32, rel: f32, d: f32) -> Fragment {
        Fragment {
            colour: [scan as f32 / 10.0, 0.5, 0.0],
            reliability: rel,
            distance_m: d,
            sigma_m: 0.01,
            scan,
        }
    }

    #[test]
    fn nearer_surface_hides_a_more_reliable_far_one() {
        let s = CompositeSettings {
            mode: Mode::ScanColour,
            ..Default::default()
        };
        let px = [frag(0, 0.3, 3.0), frag(1, 0.9, 6.0)];
        assert_eq!(composite_pixel(&px, &s), scan_colour(0));
        // Within 2 sigma the more reliable one wins.
        let px = [frag(0, 0.3, 3.0), frag(1, 0.9, 3.015)];
        assert_eq!(composite_pixel(&px, &s), scan_colour(1));
    }

    #[test]
    fn zero_reliability_is_background_and_does_not_anchor_compliance() {
        let s = CompositeSettings {
            background: [0.1, 0.2, 0.3],
            ..Default::default()
        };
        assert_eq!(composite_pixel(&[frag(0, 0.0, 1.0)], &s), [0.1, 0.2, 0.3]);
        assert_eq!(composite_pixel(&[], &s), [0.1, 0.2, 0.3]);
        let px = [frag(0, 0.0, 1.0), frag(1, 0.5, 5.0)];
        assert_eq!(ranked(&px, 4)[0].scan, 1);
    }

    #[test]
    fn ties_go_to_the_lower_scan_id() {
        let px = [frag(3, 0.5, 2.0), frag(1, 0.5, 2.0), frag(2, 0.5, 2.0)];
        let r = ranked(&px, 4);
        assert_eq!(r.iter().map(|f| f.scan).collect::<Vec<_>>(), [1, 2, 3]);
    }

    #[test]
    fn blend_weights_by_reliability_within_threshold() {
        let s = CompositeSettings {
            mode: Mode::Blended,
            blend_threshold: 0.2,
            k: 4,
            background: [0.0; 3],
        };
        let mut a = frag(0, 0.8, 2.0);
        a.colour = [1.0, 0.0, 0.0];
        let mut b = frag(1, 0.6, 2.0);
        b.colour = [0.0, 1.0, 0.0];
        let mut c = frag(2, 0.5, 2.0);
        c.colour = [0.0, 0.0, 1.0];
        let got = composite_pixel(&[a, b, c], &s);
        let want = [0.8 / 1.4, 0.6 / 1.4, 0.0];
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{got:?}");
        }
        // k = 1 blends nothing.
        let got = composite_pixel(&[a, b, c], &CompositeSettings { k: 1, ..s });
        assert_eq!(got, [1.0, 0.0, 0.0]);
    }

    #[test]
    fn palette_and_heat_stay_in_range() {
        for id in 0..100 {
            assert!(scan_colour(id).iter().all(|c| (0.0..=1.0).contains(c)));
        }
        assert_eq!(heat(0.0), [0.0, 0.0, 1.0]);
        assert_eq!(heat(1.0), [1.0, 0.0, 0.0]);
        assert_ne!(scan_colour(0), scan_colour(1));
        // Merged cameras: one colour per camera, different cameras apart.
        assert_eq!(scan_colour(1 << 24), scan_colour((1 << 24) | 77));
        assert_ne!(scan_colour(1 << 24), scan_colour(2 << 24));
    }
}
