// common.wgsl: data shared by every pass (the frame uniform) and the compositing math
// of Killpack & Budge (2016), Algorithm 2, mirrored by `composite.rs` on the CPU.

const MAX_K: u32 = 8u;
const COMPLIANCE_SIGMAS: f32 = 2.0;

const MODE_PAINTER: u32 = 0u;
const MODE_BEST: u32 = 1u;
const MODE_BLENDED: u32 = 2u;
const MODE_SCAN_COLOUR: u32 = 3u;
const MODE_RELIABILITY: u32 = 4u;

struct Frame {
    clip_from_view: mat4x4<f32>,
    // rgb: background colour (display values)
    background: vec4<f32>,
    // x: blend threshold, y: range-confidence exponent gamma, z: 1 if the target is sRGB
    params: vec4<f32>,
    // x: mode, y: k, z: layer count (naive composite), w: target width in pixels
    counts: vec4<u32>,
}

// Neighbours (of 8) that must enclose a pixel (`encloses`) for it to count as a
// sampling hole of the scans drawn in a hybrid frame (composite_kbuffer.wgsl,
// tile.wgsl).
const FILL_MIN_NEIGHBOURS: u32 = 6u;

// Whether a neighbour whose nearest scan surface lies at `neighbour` (sigma
// `neighbour_sigma`) encloses a pixel whose own nearest lies at `here` (+infinity for
// none): the neighbour holds a surface and the pixel holds nothing, or only something
// clearly behind it (beyond 3 sigma and 5 % of the distance, which a slanted surface's
// neighbouring pixels stay within).
fn encloses(here: f32, neighbour: f32, neighbour_sigma: f32) -> bool {
    if !(neighbour < 3.0e38) {
        return false;
    }
    let tolerance = max(3.0 * neighbour_sigma, 0.05 * neighbour);
    return !(here <= neighbour + tolerance);
}

// The k-th (0 to 7, row by row) of a pixel's 8 neighbours in a `size` image, or
// (-1, -1) where it falls outside.
fn neighbour(at: vec2<u32>, k: u32, size: vec2<u32>) -> vec2<i32> {
    // Index in the 3 x 3 block around the pixel, skipping its centre (4).
    let d = k + select(0u, 1u, k >= 4u);
    let q = vec2<i32>(at) + vec2<i32>(i32(d % 3u) - 1, i32(d / 3u) - 1);
    let inside = q.x >= 0 && q.y >= 0 && u32(q.x) < size.x && u32(q.y) < size.y;
    return select(vec2<i32>(-1), q, inside);
}

// One fragment of one scan at one pixel.
struct Frag {
    colour: vec3<f32>,
    reliability: f32,
    distance: f32,
    sigma: f32,
    scan: u32,
}

// A ranked fragment: what the k-buffer stores (12 bytes; colour packed RGBA8). Kept
// small because the per-pixel ranking lives in private memory.
struct Ranked {
    colour: u32,
    reliability: f32,
    scan: u32,
}

fn empty_frag() -> Frag {
    return Frag(vec3<f32>(0.0), 0.0, 0.0, 0.0, 0u);
}

// pack4x8unorm and unpack4x8unorm by hand, with their exact rounding: WebGL2's GLSL
// ES 3.0 has neither, and the browser's naive layers share this code.
fn pack_rgba8(c: vec4<f32>) -> u32 {
    let q = vec4<u32>(clamp(c, vec4<f32>(0.0), vec4<f32>(1.0)) * 255.0 + 0.5);
    return q.x | (q.y << 8u) | (q.z << 16u) | (q.w << 24u);
}

fn unpack_rgba8(p: u32) -> vec4<f32> {
    let q = vec4<u32>(p & 255u, (p >> 8u) & 255u, (p >> 16u) & 255u, p >> 24u);
    return vec4<f32>(q) / 255.0;
}

fn ranked_of(f: Frag) -> Ranked {
    return Ranked(pack_rgba8(vec4<f32>(f.colour, 1.0)), f.reliability, f.scan);
}

fn is_valid(f: Frag) -> bool {
    return f.reliability > 0.0;
}

// Higher reliability first; equal reliability: lower scan id first (deterministic).
fn ranks_before(a: Ranked, b: Ranked) -> bool {
    return a.reliability > b.reliability || (a.reliability == b.reliability && a.scan < b.scan);
}

fn is_range_compliant(f: Frag, near_distance: f32, near_sigma: f32) -> bool {
    return f.distance - near_distance <= COMPLIANCE_SIGMAS * max(f.sigma, near_sigma);
}

// Inserts `f` into the ranked list `top` (length `count`, capacity `k`), keeping the
// k best; a fragment ranking below a full list is dropped.
fn insert_ranked(top: ptr<function, array<Ranked, MAX_K>>, count: ptr<function, u32>, k: u32, f: Ranked) {
    var pos = *count;
    loop {
        if pos == 0u || !ranks_before(f, (*top)[pos - 1u]) {
            break;
        }
        pos = pos - 1u;
    }
    if pos >= k {
        return;
    }
    var i = min(*count, k - 1u);
    loop {
        if i <= pos {
            break;
        }
        (*top)[i] = (*top)[i - 1u];
        i = i - 1u;
    }
    (*top)[pos] = f;
    *count = min(*count + 1u, k);
}

fn hsv_to_rgb(h: f32, s: f32, v: f32) -> vec3<f32> {
    let n = vec3<f32>(5.0, 3.0, 1.0);
    let kk = (n + vec3<f32>(h * 6.0)) % vec3<f32>(6.0);
    return vec3<f32>(v) - v * s * clamp(min(kk, vec3<f32>(4.0) - kk), vec3<f32>(0.0), vec3<f32>(1.0));
}

// Same as `composite::scan_colour`.
// Scans merged from several cameras (ids camera << 24 | id) take their camera's.
fn scan_colour(scan: u32) -> vec3<f32> {
    let camera = scan >> 24u;
    if camera != 0u {
        return hsv_to_rgb(fract(f32(camera) * 0.618034 + 0.1), 0.75, 0.95);
    }
    return hsv_to_rgb(fract(f32(scan) * 0.618034), 0.75, 0.95);
}

// Same as `composite::heat`.
fn heat(reliability: f32) -> vec3<f32> {
    let t = clamp(reliability, 0.0, 1.0) * 4.0;
    let r = clamp(t - 2.0, 0.0, 1.0);
    var g = clamp(t, 0.0, 1.0);
    if t >= 3.0 {
        g = clamp(4.0 - t, 0.0, 1.0);
    }
    var b = 1.0;
    if t >= 1.0 {
        b = clamp(2.0 - t, 0.0, 1.0);
    }
    return vec3<f32>(r, g, b);
}

// Step 4 of Algorithm 2, from the ranked fragments (best first).
fn shade(top: ptr<function, array<Ranked, MAX_K>>, count: u32) -> vec3<f32> {
    if count == 0u {
        return frame.background.rgb;
    }
    let best = (*top)[0];
    let mode = frame.counts.x;
    if mode == MODE_BLENDED {
        let floor_rel = best.reliability - frame.params.x;
        var sum = vec3<f32>(0.0);
        var weight = 0.0;
        for (var i = 0u; i < count; i = i + 1u) {
            let f = (*top)[i];
            if f.reliability >= floor_rel {
                sum = sum + f.reliability * unpack_rgba8(f.colour).rgb;
                weight = weight + f.reliability;
            }
        }
        return sum / weight;
    }
    if mode == MODE_SCAN_COLOUR {
        return scan_colour(best.scan);
    }
    if mode == MODE_RELIABILITY {
        return heat(best.reliability);
    }
    return unpack_rgba8(best.colour).rgb;
}

fn srgb_to_linear(c: vec3<f32>) -> vec3<f32> {
    let lo = c / 12.92;
    let hi = pow((c + vec3<f32>(0.055)) / 1.055, vec3<f32>(2.4));
    return select(hi, lo, c <= vec3<f32>(0.04045));
}

// Colours are display (sRGB-encoded) values throughout; an sRGB target would encode
// them again, so they are decoded first.
fn to_target(c: vec3<f32>) -> vec4<f32> {
    if frame.params.z > 0.5 {
        return vec4<f32>(srgb_to_linear(c), 1.0);
    }
    return vec4<f32>(c, 1.0);
}

// A triangle covering the screen.
struct FullscreenOut {
    @builtin(position) clip: vec4<f32>,
}

@vertex
fn vs_fullscreen(@builtin(vertex_index) i: u32) -> FullscreenOut {
    let x = f32((i << 1u) & 2u) * 2.0 - 1.0;
    let y = f32(i & 2u) * 2.0 - 1.0;
    return FullscreenOut(vec4<f32>(x, y, 0.0, 1.0));
}
