// tile.wgsl: draws level-of-detail tiles (texel-lod): f32 positions relative to each
// tile's origin, placed relative to the virtual camera (composed in f64 on the CPU),
// coloured per vertex or by the tile's atlas, both display (sRGB-encoded) values. A
// cross-fade is a screen door: each pixel's ordered-dither threshold picks one of the
// selections ("cuts") being faded between, and only that cut's tiles are kept at the
// pixel, so no sorting is needed and the depth buffer stays valid.

const MAX_CUTS: u32 = 8u;

struct Fade {
    // Where each cut's share of the pixels ends, oldest cut first (ends[0].x is cut
    // 0, ends[1].w cut 7); unused cuts end at 1.
    ends: array<vec4<f32>, 2>,
}

struct Tile {
    view_from_tile: mat4x4<f32>,
    // x: bit i set when the tile belongs to cut i
    cuts: vec4<u32>,
    // x: share of the tile's pixels where scans on its surface win over it; y: the
    // same-surface tolerance, metres; z: 1 when the scan pass fills the holes its
    // scans enclose (composite_kbuffer.wgsl)
    scans: vec4<f32>,
}

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<uniform> fade: Fade;
// The scans drawn beneath (the scan renderer's pre-pass): per pixel the nearest valid
// scan fragment's distance from the eye and its range sigma (bit patterns of f32);
// +infinity where no scan drew. 1 x 1 when no scans are drawn.
@group(0) @binding(2) var scan_nearest: texture_2d<u32>;
@group(1) @binding(0) var<uniform> tile: Tile;
// The tile's atlas, display values like the vertex colours (which are white where it
// holds the colour; a tile coloured per vertex binds a 1 x 1 white atlas instead).
@group(1) @binding(1) var atlas: texture_2d<f32>;
@group(1) @binding(2) var atlas_sampler: sampler;

struct TileIn {
    @location(0) position: vec3<f32>,
    @location(1) colour: vec4<f32>,
    @location(2) uv: vec2<f32>,
}

struct TileOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) colour: vec3<f32>,
    @location(1) p_view: vec3<f32>,
    @location(2) uv: vec2<f32>,
}

@vertex
fn vs_tile(v: TileIn) -> TileOut {
    let p = tile.view_from_tile * vec4<f32>(v.position, 1.0);
    var out: TileOut;
    out.clip = frame.clip_from_view * vec4<f32>(p.xyz, 1.0);
    out.colour = v.colour.rgb;
    out.uv = v.uv;
    out.p_view = p.xyz;
    return out;
}

// The 8x8 Bayer threshold of a pixel, in (0, 1): the bits of (x ^ y) and y
// interleaved and reversed (same as `tiles::fade::dither_threshold`).
fn bayer8(pixel: vec2<u32>) -> f32 {
    let y = pixel.y & 7u;
    let v = (pixel.x & 7u) ^ y;
    let m = ((v & 1u) << 5u) | ((y & 1u) << 4u) | ((v & 2u) << 2u) | ((y & 2u) << 1u)
        | ((v & 4u) >> 1u) | ((y & 4u) >> 2u);
    return (f32(m) + 0.5) / 64.0;
}

// The cut whose share holds threshold `b`.
fn cut_at(b: f32) -> u32 {
    for (var i = 0u; i < MAX_CUTS; i = i + 1u) {
        if b < fade.ends[i / 4u][i % 4u] {
            return i;
        }
    }
    return MAX_CUTS - 1u;
}

@fragment
fn fs_tile(in: TileOut) -> @location(0) vec4<f32> {
    // Sampled before any discard: implicit derivatives need uniform control flow.
    let texel = textureSample(atlas, atlas_sampler, in.uv).rgb;
    let slant = ray_slant(in.p_view);
    let cut = cut_at(bayer8(vec2<u32>(in.clip.xy)));
    if ((tile.cuts.x >> cut) & 1u) == 0u {
        discard;
    }
    if gives_way_to_scans(vec2<u32>(in.clip.xy), length(in.p_view), slant) {
        discard;
    }
    return to_target(in.colour * texel);
}

// How much longer along the ray than across the surface an offset between two
// near-parallel surfaces is: 1 / |cos| of the angle between the ray and the tile's
// normal (from the screen-space derivatives of the view position), at most 8 (76
// degrees from face-on), 8 where the derivatives are degenerate.
fn ray_slant(p_view: vec3<f32>) -> f32 {
    let n = cross(dpdx(p_view), dpdy(p_view));
    let ln = length(n);
    let lp = length(p_view);
    if ln <= 1e-30 || lp <= 1e-30 {
        return 8.0;
    }
    let c = abs(dot(n, p_view)) / (ln * lp);
    return 1.0 / max(c, 0.125);
}

// Whether the scan pass filled this pixel as a hole its scans enclose
// (composite_kbuffer.wgsl: at least FILL_MIN_NEIGHBOURS neighbours `encloses` it) with
// the tile on their surface or behind it: the tile gives way there as it does to the
// scans themselves.
fn in_filled_hole(at: vec2<u32>, size: vec2<u32>, tile_distance: f32, slant: f32) -> bool {
    let here = nearest_scan(at).x;
    var enclosing = 0u;
    var under = 0u;
    for (var k = 0u; k < 8u; k = k + 1u) {
        let q = neighbour(at, k, size);
        if q.x < 0 {
            continue;
        }
        let near = nearest_scan(vec2<u32>(q));
        if encloses(here, near.x, near.y) {
            enclosing = enclosing + 1u;
            if tile_distance >= near.x - same_surface_tolerance(near.y, slant) {
                under = under + 1u;
            }
        }
    }
    return enclosing >= FILL_MIN_NEIGHBOURS && under >= FILL_MIN_NEIGHBOURS;
}

// The scans' nearest surface at a pixel: its distance from the eye (+infinity where
// no scan drew) and its range sigma.
fn nearest_scan(at: vec2<u32>) -> vec2<f32> {
    return bitcast<vec2<f32>>(textureLoad(scan_nearest, at, 0).xy);
}

// How far along the ray a tile and a scan surface `sigma` apart in range may lie and
// still be one surface: the tile's tolerance across the surface, `slant` times that
// along the ray, or 3 sigma of the scan's range noise.
fn same_surface_tolerance(sigma: f32, slant: f32) -> f32 {
    return max(tile.scans.y * slant, 3.0 * sigma);
}

// Whether the scans drawn beneath show at this pixel instead of the tile: they lie in
// front of it, or on the same surface (within the tile's tolerance across the surface,
// `slant` times that along the ray, or 3 sigma of their range noise) in the share of
// pixels the tile gives way (a screen door, decorrelated from the cut's by an offset).
// A tile in front of the scans covers them, except at the edge of a surface the
// scans show beside the pixel (`scans_show_beside`).
fn gives_way_to_scans(pixel: vec2<u32>, tile_distance: f32, slant: f32) -> bool {
    let size = textureDimensions(scan_nearest);
    let at = min(pixel, max(size, vec2<u32>(1u)) - vec2<u32>(1u));
    let near = nearest_scan(at);
    let scan_distance = near.x;
    // A hole the scan pass filled from the scans around it, the tile on their
    // surface: the fill shows in the share of pixels the switch has faded in.
    if tile.scans.z > 0.5 && in_filled_hole(at, size, tile_distance, slant) {
        return bayer8(pixel + vec2<u32>(4u, 2u)) < tile.scans.x;
    }
    // No scan here (+infinity), or not a number: the tile stays.
    if !(scan_distance < 3.0e38) {
        return false;
    }
    let tolerance = same_surface_tolerance(near.y, slant);
    if tile_distance > scan_distance + tolerance {
        return true;
    }
    let screen_door = bayer8(pixel + vec2<u32>(4u, 2u)) < tile.scans.x;
    if tile_distance >= scan_distance - tolerance {
        return screen_door;
    }
    // The tile in front of the scans: an occluder they lack covers them, but the
    // tile's own surface, where the scans show it beside this pixel, is only its
    // coarser edge reaching past theirs (a voxel rounds a corner outward).
    return screen_door && scans_show_beside(at, size, tile_distance, slant);
}

// Neighbours (of 8) whose scans must show the tile's surface for a tile in front of
// the scans to be taken for that surface's edge: a straight edge leaves at least 2
// on the surface's side; one could be a stray fragment.
const EDGE_MIN_NEIGHBOURS: u32 = 2u;

// Whether at least EDGE_MIN_NEIGHBOURS of the pixel's neighbours hold a scan surface
// at the tile's distance (within the same tolerance as the same-surface test).
fn scans_show_beside(at: vec2<u32>, size: vec2<u32>, tile_distance: f32, slant: f32) -> bool {
    var on_surface = 0u;
    for (var k = 0u; k < 8u; k = k + 1u) {
        let q = neighbour(at, k, size);
        if q.x < 0 {
            continue;
        }
        let near = nearest_scan(vec2<u32>(q));
        // No scan there: +infinity, which no finite distance is within reach of.
        if near.x < 3.0e38 && abs(tile_distance - near.x) <= same_surface_tolerance(near.y, slant) {
            on_surface = on_surface + 1u;
        }
    }
    return on_surface >= EDGE_MIN_NEIGHBOURS;
}
