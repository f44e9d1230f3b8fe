//! Where a tile's charts go in its atlas: the finest texel size (doubling from the
//! finest asked for) at which every chart's rectangle, gutter included, shelf-packs
//! into the largest atlas allowed.

use super::{AtlasParams, Chart, GUTTER_PX, MAX_ATLAS_PX};

/// Most times the texel size is doubled looking for a fit (2^40 of a leaf voxel is far
/// beyond any tile).
const MAX_DOUBLINGS: u32 = 40;

/// The finest texel size (from `params.texel_m`, doubling) whose charts fit the
/// largest atlas, with the charts and the atlas's size.
pub(super) fn pack_at_fitting_texel(
    sizes_m: &[[f64; 2]],
    params: &AtlasParams,
) -> Option<(f64, Vec<Chart>, u32, u32)> {
    let max_area = u64::from(params.max_px) * u64::from(params.max_px);
    let mut texel_m = params.texel_m;
    for _ in 0..MAX_DOUBLINGS {
        let sizes: Vec<[u32; 2]> = sizes_m.iter().map(|s| chart_size(*s, texel_m)).collect();
        let area: u64 = sizes
            .iter()
            .map(|s| u64::from(s[0]) * u64::from(s[1]))
            .sum();
        let fits_side = sizes
            .iter()
            .all(|s| s[0] <= params.max_px && s[1] <= params.max_px);
        if fits_side && area <= max_area {
            // Square-ish first, widening to the limit before giving up this size.
            let mut width = (area as f64 * 1.1).sqrt().ceil() as u32;
            width = width
                .max(sizes.iter().map(|s| s[0]).max().unwrap_or(1))
                .next_power_of_two()
                .min(params.max_px);
            loop {
                let (charts, height) = shelf_pack(&sizes, width);
                if height <= params.max_px && height > 0 {
                    return Some((texel_m, charts, width, height));
                }
                if width >= params.max_px {
                    break;
                }
                width = (width * 2).min(params.max_px);
            }
        }
        if sizes.iter().all(|s| *s == [1 + 2 * GUTTER_PX; 2]) {
            // Every chart is already the smallest there is: a coarser texel cannot help.
            return None;
        }
        texel_m *= 2.0;
    }
    None
}

/// A chart's size at `texel_m`: the triangle's extent in whole texels (at least one)
/// and the gutter each side.
pub(super) fn chart_size(size_m: [f64; 2], texel_m: f64) -> [u32; 2] {
    size_m.map(|s| {
        let texels = (s / texel_m).ceil();
        // Guard: NaN or huge extents clamp; a chart never has fewer than one texel.
        let texels = if texels.is_finite() {
            texels.clamp(1.0, f64::from(MAX_ATLAS_PX) * 2.0)
        } else {
            f64::from(MAX_ATLAS_PX) * 2.0
        };
        texels as u32 + 2 * GUTTER_PX
    })
}

/// Shelf packing, tallest first (ties by triangle order, so the layout is
/// deterministic): each chart's place, and the atlas height used.
pub(super) fn shelf_pack(sizes: &[[u32; 2]], width: u32) -> (Vec<Chart>, u32) {
    let mut order: Vec<usize> = (0..sizes.len()).collect();
    order.sort_by_key(|&i| (std::cmp::Reverse(sizes[i][1]), i));
    let mut charts = vec![
        Chart {
            x: 0,
            y: 0,
            width: 0,
            height: 0,
        };
        sizes.len()
    ];
    let (mut x, mut y, mut shelf) = (0u32, 0u32, 0u32);
    for i in order {
        let [w, h] = sizes[i];
        if x + w > width {
            y = y.saturating_add(shelf);
            x = 0;
            shelf = 0;
        }
        charts[i] = Chart {
            x,
            y,
            width: w,
            height: h,
        };
        x += w;
        shelf = shelf.max(h);
    }
    (charts, y.saturating_add(shelf))
}
