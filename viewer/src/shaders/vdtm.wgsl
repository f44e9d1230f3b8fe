// vdtm.wgsl: view-dependent texture mapping on the merged surface (Debevec, Yu &
// Borshukov 1998, §8). Each polygon carries, for this frame, at most three acquisition
// views and their weights (its view map's answer, computed on the CPU); each fragment
// projects its own position into those views' EO images through the calibrated camera
// model (plumb_bob distortion evaluated per fragment, so straight edges stay where the
// lens put them) and blends the samples. Polygons no view saw (holes) carry Gouraud
// vertex colours. Two switches go beyond the paper (its §9): a resolution term that
// lowers a view that saw the surface coarser than this frame needs (after Buehler et
// al.'s unstructured lumigraph), and feathering near each image's border. Positions
// are f32 relative to the model's origin; the transforms are composed in f64 first.

const MAX_VIEWS_PER_POLYGON: u32 = 3u;

struct VdtmFrame {
    view_from_model: mat4x4<f32>,
    // xyz: the eye in the model frame
    eye_model: vec4<f32>,
    // x: the eye's focal length, px; y: feather width, px (0: off); z: 1 when the
    // resolution term is on
    params: vec4<f32>,
}

// A polygon's views this frame (layers of `images`) and their weights.
struct PolygonBlend {
    // xyz: the views; w: how many (0: a hole)
    views: vec4<u32>,
    weights: vec4<f32>,
}

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<uniform> vdtm: VdtmFrame;
@group(0) @binding(2) var<storage, read> eo_views: array<EoView>;
@group(0) @binding(3) var<storage, read> blends: array<PolygonBlend>;
@group(0) @binding(4) var images: texture_2d_array<f32>;
@group(0) @binding(5) var image_sampler: sampler;

struct VdtmIn {
    @location(0) position: vec3<f32>,
    @location(1) colour: vec4<f32>,
    @location(2) polygon: u32,
}

struct VdtmOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) p_model: vec3<f32>,
    @location(1) colour: vec3<f32>,
    @location(2) @interpolate(flat) views: vec4<u32>,
    @location(3) @interpolate(flat) weights: vec4<f32>,
}

@vertex
fn vs_vdtm(v: VdtmIn) -> VdtmOut {
    let p = vdtm.view_from_model * vec4<f32>(v.position, 1.0);
    let count = arrayLength(&blends);
    var blend = PolygonBlend(vec4<u32>(0u), vec4<f32>(0.0));
    if v.polygon < count {
        blend = blends[v.polygon];
    }
    var out: VdtmOut;
    out.clip = frame.clip_from_view * vec4<f32>(p.xyz, 1.0);
    out.p_model = v.position;
    out.colour = v.colour.rgb;
    out.views = blend.views;
    out.weights = blend.weights;
    return out;
}

// Metres of surface one pixel covers at distance `distance` with focal length
// `focal_px`, seen at `cos_angle` from the normal (grazing views held at 84 degrees,
// so the footprint stays finite).
fn footprint_m(distance: f32, focal_px: f32, cos_angle: f32) -> f32 {
    return distance / (max(focal_px, 1e-6) * max(abs(cos_angle), 0.1));
}

@fragment
fn fs_vdtm(in: VdtmOut) -> @location(0) vec4<f32> {
    // The polygon's normal from the screen-space derivatives, taken first: they need
    // uniform control flow.
    let n_raw = cross(dpdx(in.p_model), dpdy(in.p_model));
    let count = min(in.views.w, MAX_VIEWS_PER_POLYGON);
    if count == 0u {
        // §6: a hole, filled in object space.
        return to_target(in.colour);
    }
    let n_len = length(n_raw);
    let n = select(vec3<f32>(0.0), n_raw / max(n_len, 1e-30), n_len > 1e-30);
    let to_eye = vdtm.eye_model.xyz - in.p_model;
    let eye_distance = length(to_eye);
    let eye_cos = select(1.0, dot(n, to_eye) / max(eye_distance, 1e-30), n_len > 1e-30 && eye_distance > 1e-30);
    let eye_footprint = footprint_m(eye_distance, vdtm.params.x, eye_cos);

    var colours: array<vec3<f32>, 3>;
    var paper: array<f32, 3>;
    var adjusted: array<f32, 3>;
    let views = array<u32, 3>(in.views.x, in.views.y, in.views.z);
    let weights = array<f32, 3>(in.weights.x, in.weights.y, in.weights.z);
    let view_count = arrayLength(&eo_views);
    for (var i = 0u; i < MAX_VIEWS_PER_POLYGON; i = i + 1u) {
        colours[i] = vec3<f32>(0.0);
        paper[i] = 0.0;
        adjusted[i] = 0.0;
        if i >= count || views[i] >= view_count {
            continue;
        }
        let view = eo_views[views[i]];
        let pixel = project_eo(view, in.p_model);
        if pixel.z == 0.0 {
            continue;
        }
        let size = view.shape.yz;
        let uv = (pixel.xy + vec2<f32>(0.5)) / max(size, vec2<f32>(1.0));
        colours[i] = textureSampleLevel(images, image_sampler, uv, i32(views[i]), 0.0).rgb;
        paper[i] = max(weights[i], 0.0);
        var w = paper[i];
        // Beyond the paper: feathering, weights falling to 0 at the image's border.
        if vdtm.params.y > 0.0 {
            let inside = min(min(pixel.x + 0.5, size.x - 0.5 - pixel.x), min(pixel.y + 0.5, size.y - 0.5 - pixel.y));
            w = w * smoothstep(0.0, vdtm.params.y, inside);
        }
        // Beyond the paper: the resolution term, a view coarser than the frame needs
        // counts for less (footprint ratio, at most 1).
        if vdtm.params.z > 0.5 {
            let to_view = view.centre_model.xyz - in.p_model;
            let view_distance = length(to_view);
            let view_cos = select(1.0, dot(n, to_view) / max(view_distance, 1e-30), n_len > 1e-30 && view_distance > 1e-30);
            let view_footprint = footprint_m(view_distance, view.intrinsics.y, view_cos);
            w = w * clamp(eye_footprint / max(view_footprint, 1e-30), 0.0, 1.0);
        }
        adjusted[i] = w;
    }
    // Renormalised; where the switches took every weight away, the paper's own.
    var total = adjusted[0] + adjusted[1] + adjusted[2];
    var use_paper = !(total > 1e-6);
    if use_paper {
        total = paper[0] + paper[1] + paper[2];
    }
    if !(total > 1e-6) {
        return to_target(in.colour);
    }
    var c = vec3<f32>(0.0);
    for (var i = 0u; i < MAX_VIEWS_PER_POLYGON; i = i + 1u) {
        c = c + colours[i] * select(adjusted[i], paper[i], use_paper);
    }
    return to_target(c / total);
}
