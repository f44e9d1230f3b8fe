// tile.wgsl: draws level-of-detail tiles (texel-lod): f32 positions relative to each
// tile's origin, placed relative to the virtual camera (composed in f64 on the CPU),
// coloured per vertex with display (sRGB-encoded) values. A cross-fade is a screen
// door: each pixel's ordered-dither threshold picks one of the selections ("cuts")
// being faded between, and only that cut's tiles are kept at the pixel, so no sorting
// is needed and the depth buffer stays valid.

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
}

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<uniform> fade: Fade;
@group(1) @binding(0) var<uniform> tile: Tile;

struct TileIn {
    @location(0) position: vec3<f32>,
    @location(1) colour: vec4<f32>,
}

struct TileOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) colour: vec3<f32>,
}

@vertex
fn vs_tile(v: TileIn) -> TileOut {
    let p = tile.view_from_tile * vec4<f32>(v.position, 1.0);
    var out: TileOut;
    out.clip = frame.clip_from_view * vec4<f32>(p.xyz, 1.0);
    out.colour = v.colour.rgb;
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
    let cut = cut_at(bayer8(vec2<u32>(in.clip.xy)));
    if ((tile.cuts.x >> cut) & 1u) == 0u {
        discard;
    }
    return to_target(in.colour);
}
