// composite_naive.wgsl: the baseline with one layer per visible scan (memory grows
// with the number of scans): Algorithm 2 over all layers of a pixel at once.

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var layer_colour: texture_2d_array<f32>;
@group(0) @binding(2) var layer_data: texture_2d_array<u32>;

fn load_frag(xy: vec2<i32>, l: u32) -> Frag {
    let data = textureLoad(layer_data, xy, i32(l), 0);
    let colour = textureLoad(layer_colour, xy, i32(l), 0).rgb;
    return Frag(colour, bitcast<f32>(data.x), bitcast<f32>(data.y), bitcast<f32>(data.z), data.w);
}

@fragment
fn fs_composite(in: FullscreenOut) -> @location(0) vec4<f32> {
    let xy = vec2<i32>(in.clip.xy);
    let layers = frame.counts.z;
    // Steps 1-2: the nearest valid fragment anchors range compliance.
    var found = false;
    var near = empty_frag();
    for (var l = 0u; l < layers; l = l + 1u) {
        let f = load_frag(xy, l);
        if is_valid(f) && (!found || f.distance < near.distance || (f.distance == near.distance && f.scan < near.scan)) {
            near = f;
            found = true;
        }
    }
    // Step 3: rank the compliant ones, keeping k.
    let k = clamp(frame.counts.y, 1u, MAX_K);
    var top: array<Ranked, MAX_K>;
    var count = 0u;
    if found {
        for (var l = 0u; l < layers; l = l + 1u) {
            let f = load_frag(xy, l);
            if is_valid(f) && is_range_compliant(f, near.distance, near.sigma) {
                insert_ranked(&top, &count, k, ranked_of(f));
            }
        }
    }
    return to_target(shade(&top, count));
}
