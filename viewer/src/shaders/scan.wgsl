// scan.wgsl: draws one scan's mesh relative to the virtual camera. Per fragment it
// evaluates the accumulated reliability (Sec. 3): interpolated normal accuracy x
// point-of-view confidence x range confidence. Entry points: painter (plain
// textured), prepass (nearest valid distance and its sigma), layer (colour +
// reliability, distance, sigma, scan id; the naive layers), layer_packed (reliability,
// distance, sigma and packed colour in one target; the k-buffer, which knows each
// layer's scan).

struct Scan {
    view_from_scan: mat4x4<f32>,
    // xyz: the acquisition centre of projection in the view frame
    cop_view: vec4<f32>,
    // x: sigma_m, y: sigma_per_m
    noise: vec4<f32>,
    // x: scan id
    ids: vec4<u32>,
}

@group(0) @binding(0) var<uniform> frame: Frame;
@group(1) @binding(0) var<uniform> scan: Scan;
@group(1) @binding(1) var eo_texture: texture_2d<f32>;
@group(1) @binding(2) var eo_sampler: sampler;

struct VertexIn {
    @location(0) position: vec3<f32>,
    @location(1) uv: vec2<f32>,
    @location(2) accuracy: f32,
    @location(3) acquisition_range: f32,
}

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) p_view: vec3<f32>,
    @location(1) uv: vec2<f32>,
    @location(2) accuracy: f32,
    @location(3) acquisition_range: f32,
}

@vertex
fn vs_scan(v: VertexIn) -> VsOut {
    let p = scan.view_from_scan * vec4<f32>(v.position, 1.0);
    var out: VsOut;
    out.clip = frame.clip_from_view * vec4<f32>(p.xyz, 1.0);
    out.p_view = p.xyz;
    out.uv = v.uv;
    out.accuracy = v.accuracy;
    out.acquisition_range = v.acquisition_range;
    return out;
}

// Reliability, distance to the virtual COP and range noise sigma of a fragment.
fn evaluate(in: VsOut) -> vec3<f32> {
    let d = length(in.p_view);
    // POV confidence: cosine between the directions to the acquisition and virtual COPs.
    let to_cop = scan.cop_view.xyz - in.p_view;
    let lc = length(to_cop);
    var pov = 0.0;
    if lc > 1e-6 && d > 1e-6 {
        pov = clamp(dot(to_cop, -in.p_view) / (lc * d), 0.0, 1.0);
    }
    // Range confidence: min(1, d_virtual / d_acquisition)^gamma.
    let ratio = clamp(d / max(in.acquisition_range, 1e-6), 0.0, 1.0);
    var range_conf = ratio;
    let gamma = frame.params.y;
    if gamma != 1.0 && ratio > 0.0 {
        range_conf = pow(ratio, gamma);
    }
    let reliability = clamp(clamp(in.accuracy, 0.0, 1.0) * pov * range_conf, 0.0, 1.0);
    let sigma = max(scan.noise.x + scan.noise.y * max(in.acquisition_range, 0.0), 0.0);
    return vec3<f32>(reliability, d, sigma);
}

@fragment
fn fs_painter(in: VsOut) -> @location(0) vec4<f32> {
    return to_target(textureSample(eo_texture, eo_sampler, in.uv).rgb);
}

@fragment
fn fs_prepass(in: VsOut) -> @location(0) vec2<u32> {
    let e = evaluate(in);
    if e.x <= 0.0 {
        discard;
    }
    return vec2<u32>(bitcast<u32>(e.y), bitcast<u32>(e.z));
}

struct LayerOut {
    @location(0) colour: vec4<f32>,
    @location(1) data: vec4<u32>,
}

@fragment
fn fs_layer(in: VsOut) -> LayerOut {
    let colour = textureSample(eo_texture, eo_sampler, in.uv);
    let e = evaluate(in);
    if e.x <= 0.0 {
        discard;
    }
    var out: LayerOut;
    out.colour = vec4<f32>(colour.rgb, 1.0);
    out.data = vec4<u32>(bitcast<u32>(e.x), bitcast<u32>(e.y), bitcast<u32>(e.z), scan.ids.x);
    return out;
}

// The k-buffer's layer: one 16-byte target (the colour packed as the k-buffer keeps
// it), so a layer pass writes one attachment and a merge reads one texel per layer.
@fragment
fn fs_layer_packed(in: VsOut) -> @location(0) vec4<u32> {
    let colour = textureSample(eo_texture, eo_sampler, in.uv);
    let e = evaluate(in);
    if e.x <= 0.0 {
        discard;
    }
    return vec4<u32>(bitcast<u32>(e.x), bitcast<u32>(e.y), bitcast<u32>(e.z), pack_rgba8(vec4<f32>(colour.rgb, 1.0)));
}
