// points.wgsl: the point proxy of Lechelek et al. (2019) on the GPU, mirrored by
// `points/` on the CPU. Each scan's points are disks (§4): pass 1 splats them as the
// ellipses they project to, nearest kept (`vs_splat`, `fs_splat_*`); pass 2 scatters
// every point's centre into a front or a back image by comparing its depth with pass
// 1's (`vs_scatter`, `fs_scatter`); `points_fill.wgsl` fills both by pull-push and
// keeps the result where pass 1 drew. The colour pass (§4-5, eqs. 1-5) back-projects
// each pixel's surface point into every acquisition view, tests it against that
// view's own depth map and the grazing angle, and accumulates the view's colour with
// weight `max(0, V . V_k) / (|d - d_k| + 1)` (times a radiance texture's hat weight);
// the output pass divides by the weight, into the target or, as radiance, into the
// tone-mapping pass's input.
// The same splat and scatter passes build each acquisition view's depth map once, its
// points placed at their texture coordinates (`shape.z`), so the distorted EO image
// and its depth map share one pixel grid.

const NEAR_M: f32 = 1.0e-3;
const MAX_SPLAT_PX: f32 = 64.0;
const MIN_MINOR_PX: f32 = 0.75;
const GRAZING_LAMBDA: f32 = 1.0e-4;
// Pass 2: a point agrees with pass 1 within this many of its radii (and 1 % of depth).
const CLASS_TOLERANCE_RADII: f32 = 2.0;

struct PointsView {
    // fx, fy, cx, cy (pixel centres at integers)
    intrinsics: vec4<f32>,
    // x, y: width, height; z: 1 when the points sit at their texture coordinates (an
    // acquisition view's own scan); w: the class scatter keeps (1 front, 0 back)
    shape: vec4<f32>,
}

struct PointsScan {
    view_from_scan: mat4x4<f32>,
    // The acquisition view with the virtual view's frame as its model frame.
    eo: EoView,
    // x: sigma_m, y: sigma_per_m
    noise: vec4<f32>,
}

@group(0) @binding(0) var<uniform> frame: Frame;
@group(1) @binding(0) var<uniform> view: PointsView;
@group(1) @binding(1) var accumulated: texture_2d<f32>;
// Depth maps hold f32 bits in r32uint (colour-renderable everywhere, unlike r32float).
@group(2) @binding(0) var<uniform> points_scan: PointsScan;
@group(2) @binding(1) var eo_texture: texture_2d<f32>;
@group(2) @binding(2) var eo_sampler: sampler;
@group(2) @binding(3) var acquisition_depth: texture_2d<u32>;
@group(3) @binding(0) var splat_z: texture_2d<u32>;
@group(3) @binding(1) var splat_normal: texture_2d<f32>;
@group(3) @binding(2) var view_depth: texture_2d<u32>;

struct PointIn {
    @location(0) position: vec3<f32>,
    @location(1) radius_m: f32,
    @location(2) normal: vec3<f32>,
    @location(3) textured: f32,
    @location(4) uv: vec2<f32>,
}

// A point in the view: its centre's pixel, depth and normal, and whether it is drawn.
struct Placed {
    centre: vec2<f32>,
    z: f32,
    normal: vec3<f32>,
    drawn: bool,
}

fn place(p: PointIn) -> Placed {
    var out: Placed;
    let q = (points_scan.view_from_scan * vec4<f32>(p.position, 1.0)).xyz;
    out.z = q.z;
    out.normal = (points_scan.view_from_scan * vec4<f32>(p.normal, 0.0)).xyz;
    let k = view.intrinsics;
    let in_front = q.z > NEAR_M;
    if view.shape.z > 0.5 {
        out.centre = p.uv * view.shape.xy - vec2<f32>(0.5);
        out.drawn = in_front && p.textured > 0.5;
    } else {
        let z = max(q.z, NEAR_M);
        out.centre = vec2<f32>(k.x * q.x / z + k.z, k.y * q.y / z + k.w);
        out.drawn = in_front;
    }
    // Far outside the view: not drawn (keeps the clip coordinates finite).
    out.drawn = out.drawn && all(abs(out.centre) < vec2<f32>(1.0e6));
    return out;
}

// A pixel position (centres at integers) as clip coordinates at reverse depth
// `NEAR_M / z` (nearer is greater, as the renderer's depth test expects).
fn clip_of(pixel: vec2<f32>, z: f32) -> vec4<f32> {
    let ndc = vec2<f32>(
        (pixel.x + 0.5) / view.shape.x * 2.0 - 1.0,
        1.0 - (pixel.y + 0.5) / view.shape.y * 2.0,
    );
    return vec4<f32>(ndc, clamp(NEAR_M / z, 0.0, 1.0), 1.0);
}

// Equal depths agree; beyond `tolerance_m` plus 1 % of the map's depth a point is
// behind (`splat::depth_agrees`).
fn depth_agrees(z: f32, map_z: f32, tolerance_m: f32) -> bool {
    return map_z > 0.0 && (z - map_z) <= tolerance_m + 0.01 * abs(map_z);
}

struct SplatOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) @interpolate(flat) centre: vec2<f32>,
    // x: semi-major, y: semi-minor (pixels), zw: the minor axis (unit, pixels)
    @location(1) @interpolate(flat) axes: vec4<f32>,
    @location(2) @interpolate(flat) z: f32,
    @location(3) @interpolate(flat) normal: vec3<f32>,
}

const CORNERS = array<vec2<f32>, 6>(
    vec2<f32>(-1.0, -1.0), vec2<f32>(1.0, -1.0), vec2<f32>(-1.0, 1.0),
    vec2<f32>(-1.0, 1.0), vec2<f32>(1.0, -1.0), vec2<f32>(1.0, 1.0),
);

// Pass 1: a disk as the ellipse it projects to, semi-major `r f / z`, semi-minor
// shortened by the normal's z (§4); the quad bounds it with a pixel to spare.
@vertex
fn vs_splat(@builtin(vertex_index) corner: u32, p: PointIn) -> SplatOut {
    var out: SplatOut;
    let placed = place(p);
    if !placed.drawn {
        out.clip = vec4<f32>(2.0, 2.0, 2.0, 1.0);
        return out;
    }
    let a = clamp(max(p.radius_m, 0.0) * view.intrinsics.y / placed.z, MIN_MINOR_PX, MAX_SPLAT_PX);
    let n_len = length(placed.normal);
    let n = select(vec3<f32>(0.0, 0.0, -1.0), placed.normal / n_len, n_len > 1.0e-12);
    let n_xy = length(n.xy);
    let axis = select(vec2<f32>(1.0, 0.0), n.xy / n_xy, n_xy > 1.0e-6);
    let b = min(max(a * min(abs(n.z), 1.0), MIN_MINOR_PX), a);
    let pixel = placed.centre + CORNERS[corner % 6u] * (a + 1.0);
    out.clip = clip_of(pixel, placed.z);
    out.centre = placed.centre;
    out.axes = vec4<f32>(a, b, axis);
    out.z = placed.z;
    out.normal = n;
    return out;
}

fn inside_ellipse(in: SplatOut) -> bool {
    let d = floor(in.clip.xy) - in.centre;
    let minor = dot(d, in.axes.zw);
    let major = -d.x * in.axes.w + d.y * in.axes.z;
    return major * major / (in.axes.x * in.axes.x) + minor * minor / (in.axes.y * in.axes.y) <= 1.0;
}

@fragment
fn fs_splat_depth(in: SplatOut) -> @location(0) vec4<u32> {
    if !inside_ellipse(in) {
        discard;
    }
    return vec4<u32>(bitcast<u32>(in.z), 0u, 0u, 0u);
}

struct SplatTargets {
    @location(0) z: vec4<u32>,
    @location(1) normal: vec4<f32>,
}

@fragment
fn fs_splat_depth_normal(in: SplatOut) -> SplatTargets {
    if !inside_ellipse(in) {
        discard;
    }
    return SplatTargets(vec4<u32>(bitcast<u32>(in.z), 0u, 0u, 0u), vec4<f32>(in.normal, 1.0));
}

struct ScatterOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) @interpolate(flat) z: f32,
    @location(1) @interpolate(flat) radius_m: f32,
}

// Pass 2: each point at the pixel of its centre.
@vertex
fn vs_scatter(p: PointIn) -> ScatterOut {
    var out: ScatterOut;
    let placed = place(p);
    if !placed.drawn {
        out.clip = vec4<f32>(2.0, 2.0, 2.0, 1.0);
        return out;
    }
    out.clip = clip_of(round(placed.centre), placed.z);
    out.z = placed.z;
    out.radius_m = max(p.radius_m, 0.0);
    return out;
}

@fragment
fn fs_scatter(in: ScatterOut) -> @location(0) vec4<u32> {
    let map_z = bitcast<f32>(textureLoad(splat_z, vec2<i32>(floor(in.clip.xy)), 0).x);
    let front = depth_agrees(in.z, map_z, CLASS_TOLERANCE_RADII * in.radius_m);
    if front != (view.shape.w > 0.5) {
        discard;
    }
    return vec4<u32>(bitcast<u32>(in.z), 0u, 0u, 0u);
}

// The colour pass, once per scan: this acquisition view's weighted colour at every
// pixel whose surface point it sees.
@fragment
fn fs_colour(in: FullscreenOut) -> @location(0) vec4<f32> {
    let pixel = vec2<i32>(floor(in.clip.xy));
    let z = bitcast<f32>(textureLoad(view_depth, pixel, 0).x);
    if !(z > NEAR_M) {
        discard;
    }
    let k = view.intrinsics;
    let p = vec3<f32>((f32(pixel.x) - k.z) / k.x * z, (f32(pixel.y) - k.w) / k.y * z, z);
    let eo = points_scan.eo;
    let projected = project_eo(eo, p);
    let size = eo.shape.yz;
    let inside = all(projected.xy >= vec2<f32>(-0.5)) && all(projected.xy <= size - vec2<f32>(0.5));
    if projected.z == 0.0 || !inside {
        discard;
    }
    // Eq. 5's geometry: the directions to the eye (the origin) and to the view's centre.
    let to_eye = -p;
    let to_view = eo.centre_model.xyz - p;
    let n_raw = textureLoad(splat_normal, pixel, 0).xyz;
    let d = length(to_eye);
    let d_k = length(to_view);
    let n_len = length(n_raw);
    if !(d > 0.0 && d_k > 0.0 && n_len > 0.0) {
        discard;
    }
    let v = to_eye / d;
    let v_k = to_view / d_k;
    let cos_k = dot(n_raw / n_len, v_k);
    // The grazing-angle test (the surface seen at least this far from edge-on).
    if cos_k <= GRAZING_LAMBDA {
        discard;
    }
    // The view's own depth map: is the point what the view saw there? Within three
    // range sigmas, and a map pixel's footprint grown by the slope it was seen at.
    let q_z = (eo.eo_from_model * vec4<f32>(p, 1.0)).z;
    let map_size = vec2<f32>(textureDimensions(acquisition_depth));
    let map_pixel = clamp(floor((projected.xy + 0.5) / size * map_size), vec2<f32>(0.0), map_size - 1.0);
    let map_z = bitcast<f32>(textureLoad(acquisition_depth, vec2<i32>(map_pixel), 0).x);
    let sigma = points_scan.noise.x + points_scan.noise.y * max(q_z, 0.0);
    let footprint = q_z * (size.x / map_size.x) / max(eo.intrinsics.x, 1.0e-6);
    let tolerance = 3.0 * sigma + 2.0 * footprint / max(cos_k, 0.2);
    if !depth_agrees(q_z, map_z, tolerance) {
        discard;
    }
    let w = max(dot(v, v_k), 0.0) / (abs(d - d_k) + 1.0);
    if !(w > 0.0) {
        discard;
    }
    let uv = (projected.xy + vec2<f32>(0.5)) / size;
    // An EO image is opaque; a radiance texture's alpha is its hat weight (0 where the
    // exposure saw black or saturation there).
    let texel = textureSampleLevel(eo_texture, eo_sampler, uv, 0.0);
    let weight = w * clamp(texel.a, 0.0, 1.0);
    if !(weight > 0.0) {
        discard;
    }
    return vec4<f32>(texel.rgb * weight, weight);
}

// The output: the weighted mean (eq. 5), the background where no view saw the surface.
@fragment
fn fs_points_output(in: FullscreenOut) -> @location(0) vec4<f32> {
    let acc = textureLoad(accumulated, vec2<i32>(floor(in.clip.xy)), 0);
    if acc.a > 0.0 {
        return to_target(acc.rgb / acc.a);
    }
    return to_target(frame.background.rgb);
}

// The output as radiance for the tone-mapping pass: the weighted mean, alpha 0 where
// no view measured the pixel.
@fragment
fn fs_points_radiance(in: FullscreenOut) -> @location(0) vec4<f32> {
    let acc = textureLoad(accumulated, vec2<i32>(floor(in.clip.xy)), 0);
    if acc.a > 0.0 {
        return vec4<f32>(acc.rgb / acc.a, 1.0);
    }
    return vec4<f32>(0.0);
}
